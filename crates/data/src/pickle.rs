//! (being written)
#[derive(Debug, thiserror::Error)]
#[error("stub")]
pub struct PickleError;
