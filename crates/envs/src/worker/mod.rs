//! Environments that live outside this process: a user's gymnasium environments, made and stepped
//! by a Python worker process that the `promptdt` Python package provides. [`WorkerSpec`] is what a
//! task suite's `[environment]` table declares about them.

mod spec;

pub use spec::{WorkerSpec, WorkerTask};
