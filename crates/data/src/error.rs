//! Errors of the data crate. Each names the file, field or shape at fault.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("wrong shape for `{field}`: expected {expected}, got {got}")]
    Shape { field: &'static str, expected: String, got: String },
    #[error("empty dataset")]
    Empty,
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("pickle: {0}")]
    Pickle(#[from] crate::pickle::PickleError),
    #[error("{path}: {source}")]
    InFile { path: PathBuf, source: Box<DataError> },
}

impl DataError {
    /// Wraps an error with the file it came from.
    pub fn in_file(self, path: impl Into<PathBuf>) -> Self {
        DataError::InFile { path: path.into(), source: Box::new(self) }
    }
}
