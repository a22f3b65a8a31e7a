//! The library's errors as `promptdt.Error`s (`python/promptdt/errors.py`).
//!
//! Each Python class there is also the built-in exception the same failure raised before the
//! hierarchy existed, so no caller's `except ValueError` breaks. An error of the library crates is
//! sorted by its chain of causes: an `std::io::Error` anywhere in it makes it a `FileError` (a
//! `NotFoundError` for a missing file) carrying the system call's `errno`; everything else the
//! library refuses is an `InvalidInputError` (a `ValueError`).

use std::error::Error as StdError;

pyo3::import_exception!(promptdt.errors, InvalidInputError);
pyo3::import_exception!(promptdt.errors, ArgumentTypeError);
pyo3::import_exception!(promptdt.errors, FileError);
pyo3::import_exception!(promptdt.errors, NotFoundError);
pyo3::import_exception!(promptdt.errors, StateError);

use pyo3::PyErr;

/// Which `promptdt.Error` a failure becomes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    Invalid,
    /// A missing file or directory (`ENOENT`).
    NotFound,
    /// Any other failure of the operating system.
    File,
    State,
}

/// A failure sorted and worded, not yet a Python exception: it crosses threads (a long call runs
/// without the GIL) where a library error type need not be `Send`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Failure {
    pub(crate) kind: Kind,
    pub(crate) message: String,
    pub(crate) errno: Option<i32>,
}

impl Failure {
    /// `message` as the given kind (no cause to look into).
    pub(crate) fn new(kind: Kind, message: impl Into<String>) -> Failure {
        Failure { kind, message: message.into(), errno: None }
    }

    /// A library error, sorted by the first I/O error in its chain of causes (itself included).
    pub(crate) fn of(e: &(dyn StdError + 'static)) -> Failure {
        let mut cause = Some(e);
        let mut io = None;
        while let Some(c) = cause {
            io = c.downcast_ref::<std::io::Error>();
            if io.is_some() {
                break;
            }
            cause = c.source();
        }
        let kind = match io.map(std::io::Error::kind) {
            None => Kind::Invalid,
            Some(std::io::ErrorKind::NotFound) => Kind::NotFound,
            Some(_) => Kind::File,
        };
        Failure { kind, message: e.to_string(), errno: io.and_then(std::io::Error::raw_os_error) }
    }

    /// The Python exception, its message in the Python package's terms.
    pub(crate) fn into_py(self) -> PyErr {
        let message = crate::python_terms(&self.message);
        match (self.kind, self.errno) {
            (Kind::Invalid, _) => InvalidInputError::new_err(message),
            (Kind::State, _) => StateError::new_err(message),
            // OSError(errno, strerror) sets `.errno`; its str() is "[Errno N] message".
            (Kind::NotFound, Some(n)) => NotFoundError::new_err((n, message)),
            (Kind::NotFound, None) => NotFoundError::new_err(message),
            (Kind::File, Some(n)) => FileError::new_err((n, message)),
            (Kind::File, None) => FileError::new_err(message),
        }
    }
}

/// A library error as its `promptdt.Error` (see [`Failure::of`]).
pub(crate) fn lib_error<E: StdError + 'static>(e: E) -> PyErr {
    Failure::of(&e).into_py()
}
