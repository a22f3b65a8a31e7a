//! The run directory's schema, with no libtorch below it: what a run directory holds, owned in one
//! place so that the trainer, the evaluator, the report, `reproduce`, the server and the Python
//! package read and write the same typed files.
//!
//! - [`config`]: `config.toml`, the whole experiment ([`config::TrainConfig`]) with every option type
//!   it names (the optimiser's, the loss's, the evaluator's, MACAW's), so that a crate can read a
//!   run's configuration without linking the crates that act on it.

pub mod config;
