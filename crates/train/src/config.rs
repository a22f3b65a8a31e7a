//! The training configuration. It is part of the run directory's schema and is read without
//! libtorch, so it lives in `pdt_rundir::config`; this path stays for the code that names it here.

pub use pdt_rundir::config::*;
