//! The machine's arena: the stack slots ([`Val`]) and the objects they point to ([`Obj`]), shared by
//! the machine that builds them ([`super::machine`]) and the builder that turns them into a
//! [`PyValue`](super::PyValue) tree ([`super::tree`]). Kept apart from both so neither imports the
//! other's internals.

use super::{DType, NdArray, PickleError};
use super::{BUDGET_BASE, BUDGET_PER_INPUT_BYTE};

pub(super) type Res<T> = Result<T, PickleError>;

/// A stack slot. Containers and strings live in the machine's `objs` and are referenced by index,
/// which gives Python's sharing semantics (a memoised list appended to later is the same list)
/// without reference counting, and keeps cycles harmless until the tree is built.
#[derive(Debug, Clone, Copy)]
pub(super) enum Val {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Obj(usize),
}

/// The callables a pickle may name. Each is re-implemented in `Machine::call`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Callable {
    /// `numpy.core.multiarray._reconstruct(numpy.ndarray, (0,), b'b')`: an empty array that a
    /// later BUILD fills with `(version, shape, dtype, is_fortran, rawdata)`.
    Reconstruct,
    /// `numpy.ndarray`: only legal as the first argument of `_reconstruct`.
    NdarrayType,
    /// `numpy.dtype(code, align, copy)`; a later BUILD sets its byte order.
    Dtype,
    /// `numpy.core.multiarray.scalar(dtype, rawbytes)`: a numpy scalar.
    Scalar,
    /// `numpy.core.numeric._frombuffer(buffer, dtype, shape, order[, axis_order])`: protocol 5.
    FromBuffer,
    /// `_codecs.encode(str, 'latin1')`: how protocol 2 writes `bytes`.
    CodecsEncode,
    /// `builtins.bytes()`: how protocol 2 writes `b''`.
    Bytes,
}

impl Callable {
    pub(super) fn lookup(module: &str, name: &str) -> Option<Callable> {
        Some(match (module, name) {
            ("numpy.core.multiarray" | "numpy._core.multiarray", "_reconstruct") => {
                Callable::Reconstruct
            }
            ("numpy.core.multiarray" | "numpy._core.multiarray", "scalar") => Callable::Scalar,
            ("numpy.core.numeric" | "numpy._core.numeric", "_frombuffer") => Callable::FromBuffer,
            ("numpy", "ndarray") => Callable::NdarrayType,
            ("numpy", "dtype") => Callable::Dtype,
            ("_codecs", "encode") => Callable::CodecsEncode,
            // Protocol 2 writes Python 3's `builtins` under its Python 2 name.
            ("builtins" | "__builtin__", "bytes") => Callable::Bytes,
            _ => return None,
        })
    }

    pub(super) fn name(self) -> &'static str {
        match self {
            Callable::Reconstruct => "numpy.core.multiarray._reconstruct",
            Callable::NdarrayType => "numpy.ndarray",
            Callable::Dtype => "numpy.dtype",
            Callable::Scalar => "numpy.core.multiarray.scalar",
            Callable::FromBuffer => "numpy.core.numeric._frombuffer",
            Callable::CodecsEncode => "_codecs.encode",
            Callable::Bytes => "builtins.bytes",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum ByteOrder {
    Little,
    Big,
    /// `|`: single-byte types.
    NotApplicable,
}

#[derive(Debug)]
pub(super) enum Obj {
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<Val>),
    Tuple(Vec<Val>),
    Dict(Vec<(Val, Val)>),
    Callable(Callable),
    /// A dtype; `order` is `None` until BUILD gives it one.
    Dtype {
        dtype: DType,
        order: Option<ByteOrder>,
        code: String,
    },
    /// Made by `_reconstruct`, waiting for BUILD to supply shape, dtype and data.
    PendingArray,
    Array(NdArray),
}

pub(super) fn over_budget_message(input_len: usize) -> String {
    format!(
        "the values would take more than {BUDGET_PER_INPUT_BYTE} x {input_len} + {BUDGET_BASE} \
         bytes: the file reuses memoised objects more than any data file does"
    )
}
