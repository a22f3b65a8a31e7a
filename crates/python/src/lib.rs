//! `promptdt._native`: the Rust side of the Python package (PyO3).
//!
//! Thin bindings over the library crates, the same calls the CLI makes: a trained run's policy
//! (`pdt_policy::Policy`, each episode a `pdt_policy::Episode`, the runtime `promptdt serve` acts
//! through too, so that Python rollouts take
//! `promptdt eval`'s actions), the environment families behind a vector of environments stepped on
//! worker threads (`pdt_envs::vec_env::VecEnv`), the dataset readers (native files and the
//! reference pickles, through the safe reader), and training, evaluation and collection. The
//! Python layer (`python/promptdt`) adds the gymnasium vector env, dataclasses and Minari.
//!
//! Arrays cross as numpy arrays: outputs are moved into numpy without a copy (a Rust `Vec` becomes
//! the array's buffer), inputs are read in place when they already have the dtype and layout
//! wanted, converted otherwise. Every error is a Python exception naming the file, field or shape.
//! Long calls release the GIL; train and collect also stop on Ctrl-C (`signals`).

use numpy::prelude::*;
use numpy::PyArray2;
use pyo3::exceptions::{PyFileNotFoundError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::path::Path;
use std::sync::{Mutex, MutexGuard};

pub(crate) fn value_error(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

pub(crate) fn lock<T>(m: &Mutex<T>) -> PyResult<MutexGuard<'_, T>> {
    // A panic while the lock was held (none is expected) leaves the state unusable, not unsafe.
    m.lock().map_err(|_| PyRuntimeError::new_err("internal state poisoned by an earlier panic"))
}

pub(crate) fn existing(path: &Path, what: &str) -> PyResult<()> {
    if path.exists() {
        Ok(())
    } else {
        Err(PyFileNotFoundError::new_err(format!(
            "{what} {}: no such file or directory",
            path.display()
        )))
    }
}

/// A `[rows, cols]` numpy array that owns `v` (no copy).
pub(crate) fn array2<'py, T: numpy::Element>(
    py: Python<'py>,
    v: Vec<T>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArray2<T>>> {
    v.into_pyarray(py).reshape([rows, cols]).map_err(value_error)
}

/// Dataset files: `load_dataset`, `write_dataset`.
mod data;
/// Environment families and `VecEnv`.
mod envs;
/// `Policy`, `Prompt`, `TaskPlan`: a trained run acting through `pdt_policy`.
mod policy;
/// The CLI's library calls: train, evaluate, collect, experiments, benchmark.
mod runs;
/// Long calls that Ctrl-C stops, and their progress reported to Python.
mod signals;

/// Sets libtorch's intra-op threads for this process.
#[pyfunction]
fn set_num_threads(threads: usize) -> PyResult<()> {
    if threads == 0 {
        return Err(value_error("threads must be at least 1"));
    }
    tch::set_num_threads(threads as i32);
    Ok(())
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("LIBTORCH_VERSION", "2.11.0")?;
    m.add_function(wrap_pyfunction!(data::load_dataset, m)?)?;
    m.add_function(wrap_pyfunction!(data::write_dataset, m)?)?;
    m.add_function(wrap_pyfunction!(data::check_dims, m)?)?;
    m.add_function(wrap_pyfunction!(envs::families, m)?)?;
    m.add_function(wrap_pyfunction!(envs::task_params, m)?)?;
    m.add_function(wrap_pyfunction!(runs::train, m)?)?;
    m.add_function(wrap_pyfunction!(runs::evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(runs::collect_scripted, m)?)?;
    m.add_function(wrap_pyfunction!(runs::is_scripted, m)?)?;
    m.add_function(wrap_pyfunction!(runs::experiments, m)?)?;
    m.add_function(wrap_pyfunction!(runs::collect_from_agent, m)?)?;
    m.add_function(wrap_pyfunction!(set_num_threads, m)?)?;
    m.add_function(wrap_pyfunction!(runs::bench_envs, m)?)?;
    m.add_class::<envs::VecEnv>()?;
    m.add_class::<policy::Policy>()?;
    m.add_class::<policy::Prompt>()?;
    m.add_class::<policy::TaskPlan>()?;
    Ok(())
}
