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
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyString};
use std::path::Path;

pub(crate) use errors::lib_error;
use errors::{ArgumentTypeError, Failure, Kind, NotFoundError};
use std::sync::{Mutex, MutexGuard};

/// `promptdt.InvalidInputError` (a `ValueError`) with `e`'s message: for a message made here. A
/// library error goes through [`lib_error`] instead, which looks at its cause (an I/O error is a
/// `promptdt.FileError`).
pub(crate) fn value_error(e: impl std::fmt::Display) -> PyErr {
    Failure::new(Kind::Invalid, e.to_string()).into_py()
}

/// The library's messages that tell a command-line user what to type (`--resume`, `--out`, a
/// script of the checkout), in the terms of the Python call that got them. The library crates
/// are shared with the CLI, whose wording they keep; pytests/test_errors.py triggers each of these
/// messages through the package, so a change of wording there fails a test here.
const PYTHON_TERMS: &[(&str, &str)] = &[
    // `train` into a directory that holds a run, or one another process holds.
    (
        "use --resume to continue it or pick another --out",
        "continue it with promptdt.train(out, resume=True) or pick another out",
    ),
    ("or pick another --out", "or pick another out"),
    // A run's data moved (`train(resume=True)`, `evaluate`).
    ("(--data DIR where it moved)", "(data=DIR where it moved)"),
    // `train(resume=True, iterations=N)` below what the run has done.
    ("--iterations ", "iterations="),
    // A run directory killed while being created.
    ("`promptdt train --resume` recreates it", "promptdt.train(out, resume=True) recreates it"),
    ("rerun `promptdt train --config <experiment> --out ", "rerun promptdt.train(config=..., out="),
    // `device="cuda"` without the CUDA part of libtorch: the package has no scripts/.
    (
        "install the CUDA part of libtorch 2.11.0 (python3 scripts/fetch_libtorch.py --cuda) and \
         put the directory it prints on LD_LIBRARY_PATH",
        "the promptdt package carries only the CPU part of libtorch; for device=\"cuda\", install \
         torch 2.11.0 with CUDA (pip install torch==2.11.0) and start Python with its torch/lib \
         directory on LD_LIBRARY_PATH",
    ),
];

/// `message` with [`PYTHON_TERMS`]' replacements.
pub(crate) fn python_terms(message: &str) -> String {
    let mut out = message.to_string();
    for (cli, python) in PYTHON_TERMS {
        out = out.replace(cli, python);
    }
    // The closing quote of the command line rewritten above.
    if out.contains("rerun promptdt.train(config=..., out=") {
        if let Some(end) = out.rfind('`') {
            out.replace_range(end..=end, ")");
        }
    }
    out
}

pub(crate) fn lock<T>(m: &Mutex<T>) -> PyResult<MutexGuard<'_, T>> {
    // A panic while the lock was held (none is expected) leaves the state unusable, not unsafe.
    m.lock().map_err(|_| {
        Failure::new(Kind::State, "internal state poisoned by an earlier panic").into_py()
    })
}

pub(crate) fn existing(path: &Path, what: &str) -> PyResult<()> {
    if path.exists() {
        Ok(())
    } else {
        Err(NotFoundError::new_err(format!("{what} {}: no such file or directory", path.display())))
    }
}

/// A non-negative integer argument `name` (`expected` says what it is, e.g. "a task index").
/// PyO3's own conversion to an unsigned type raises `OverflowError: can't convert negative int to
/// unsigned`, which names neither the argument nor what it takes; a float raises a TypeError
/// without the argument's name when it comes through a list.
pub(crate) fn uint_arg(name: &str, v: &Bound<'_, PyAny>, expected: &str) -> PyResult<u64> {
    if let Ok(x) = v.extract::<u64>() {
        return Ok(x);
    }
    let given = v.repr().map_or_else(|_| "?".to_string(), |r| r.to_string());
    if let Ok(x) = v.extract::<i64>() {
        return Err(value_error(format!("{name}: {x} given, expected {expected} (>= 0)")));
    }
    if v.is_instance_of::<pyo3::types::PyInt>() {
        return Err(value_error(format!("{name}: {given} is too large, expected {expected}")));
    }
    let ty = v.get_type().name().map_or_else(|_| "?".to_string(), |n| n.to_string());
    Err(ArgumentTypeError::new_err(format!(
        "{name}: {given} ({ty}) given, expected {expected} (an int)"
    )))
}

/// [`uint_arg`] as a `usize`.
pub(crate) fn usize_arg(name: &str, v: &Bound<'_, PyAny>, expected: &str) -> PyResult<usize> {
    let x = uint_arg(name, v, expected)?;
    usize::try_from(x)
        .map_err(|_| value_error(format!("{name}: {x} is too large, expected {expected}")))
}

/// A list of non-negative integers (any iterable but a string): each checked as [`uint_arg`],
/// named `name[i]`.
pub(crate) fn uint_list(name: &str, v: &Bound<'_, PyAny>, expected: &str) -> PyResult<Vec<u64>> {
    let ty = v.get_type().name().map_or_else(|_| "?".to_string(), |n| n.to_string());
    let not_a_list = || {
        ArgumentTypeError::new_err(format!("{name}: a {ty} given, expected a list of {expected}s"))
    };
    if v.is_instance_of::<PyString>() || v.is_instance_of::<PyBytes>() {
        return Err(not_a_list());
    }
    let items = v.try_iter().map_err(|_| not_a_list())?;
    items.enumerate().map(|(i, x)| uint_arg(&format!("{name}[{i}]"), &x?, expected)).collect()
}

/// [`uint_list`] as `usize`s.
pub(crate) fn usize_list(name: &str, v: &Bound<'_, PyAny>, expected: &str) -> PyResult<Vec<usize>> {
    uint_list(name, v, expected)?
        .into_iter()
        .enumerate()
        .map(|(i, x)| {
            usize::try_from(x).map_err(|_| {
                value_error(format!("{name}[{i}]: {x} is too large, expected {expected}"))
            })
        })
        .collect()
}

/// A `[rows, cols]` numpy array that owns `v` (no copy).
pub(crate) fn array2<'py, T: numpy::Element>(
    py: Python<'py>,
    v: Vec<T>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArray2<T>>> {
    v.into_pyarray(py).reshape([rows, cols]).map_err(lib_error)
}

/// `collect(suite, policy=...)`: a suite's datasets from a Python policy.
mod collect;
/// Dataset files: `load_dataset`, `write_dataset`.
mod data;
/// Environment families and `VecEnv`.
mod envs;
/// The library's errors as `promptdt.Error`s.
mod errors;
/// `evaluate(run, env=factory)`: environments made by a Python factory, answered in-process.
mod factory;
/// `Policy`, `PromptBandit`: a trained run acting through `pdt_policy`.
mod policy;
/// `Prompt`, `TaskPlan`, `Adaptation`: what a `Policy` acts with.
mod prompts;
// The frames of `render_mode="rgb_array"`, gymnasium's way to get an episode's pictures.
mod render;
/// The CLI's library calls: train, evaluate, collect, experiments, benchmark.
mod runs;
/// Long calls that Ctrl-C stops, and their progress reported to Python.
mod signals;

/// Sets libtorch's intra-op threads for this process.
#[pyfunction]
fn set_num_threads(threads: &Bound<'_, PyAny>) -> PyResult<()> {
    let threads = usize_arg("threads", threads, "a number of threads")?;
    if threads == 0 {
        return Err(value_error("threads: 0 given, expected at least 1"));
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
    m.add_function(wrap_pyfunction!(envs::family_info, m)?)?;
    m.add_function(wrap_pyfunction!(data::prompt_indices, m)?)?;
    m.add_function(wrap_pyfunction!(envs::task_params, m)?)?;
    m.add_function(wrap_pyfunction!(runs::train, m)?)?;
    m.add_function(wrap_pyfunction!(runs::evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(runs::collect_scripted, m)?)?;
    m.add_function(wrap_pyfunction!(runs::is_scripted, m)?)?;
    m.add_function(wrap_pyfunction!(runs::experiments, m)?)?;
    m.add_function(wrap_pyfunction!(runs::collect_from_agent, m)?)?;
    m.add_function(wrap_pyfunction!(collect::collect_policy, m)?)?;
    m.add_function(wrap_pyfunction!(set_num_threads, m)?)?;
    m.add_function(wrap_pyfunction!(runs::bench_envs, m)?)?;
    m.add_function(wrap_pyfunction!(render::render, m)?)?;
    m.add_class::<envs::VecEnv>()?;
    m.add_class::<policy::Policy>()?;
    m.add_class::<prompts::Prompt>()?;
    m.add_class::<policy::PromptBandit>()?;
    m.add_class::<prompts::Adaptation>()?;
    m.add_class::<prompts::TaskPlan>()?;
    Ok(())
}
