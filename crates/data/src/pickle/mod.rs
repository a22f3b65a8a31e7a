//! A reader for Python pickles of numpy data that never executes code.
//!
//! A pickle is a program for a small stack machine. Its `GLOBAL`/`STACK_GLOBAL` opcodes import any
//! Python callable and `REDUCE` calls it, which is why `pickle.load` on an untrusted file can run
//! anything. This module implements the stack machine itself and knows exactly the callables that
//! numpy arrays, numpy scalars and `bytes` are pickled with (see [`parse`]); any other global is
//! refused when it is named, before anything could use it. Those few "calls" are re-implemented
//! here as plain data transformations, so nothing is imported or run.
//!
//! Bounds, so that a hostile file cannot exhaust memory or the stack:
//! - every length field is checked against the bytes actually left before anything is allocated;
//! - array sizes are `product(shape) * itemsize` with checked multiplication and must equal the
//!   data length;
//! - the stack, the mark stack and the memo grow by at most one entry per opcode, so they are
//!   bounded by the input length;
//! - values the reader creates (copied array data, the returned tree) are charged against a budget
//!   proportional to the input size, which stops "billion laughs" files that reference one
//!   memoised object many times;
//! - the returned tree is at most [`MAX_DEPTH`] containers deep (this also rejects cycles, e.g. a
//!   list that contains itself).

mod arena;
mod error;
mod machine;
mod tree;
mod value;

pub use error::PickleError;
pub use value::{DType, NdArray, PyValue};

use machine::Machine;

/// Deepest nesting of containers in the returned tree. The reference files nest 3 deep (list ->
/// dict -> array); the limit keeps a hostile file (or a list that contains itself) from
/// exhausting the Rust stack while the tree is built.
pub const MAX_DEPTH: usize = 64;

/// Memory the reader may spend on values it creates (copied array data, decoded bytes, the
/// returned tree), per input byte, plus a fixed allowance. The tree costs roughly one `PyValue`
/// per input opcode; 64 per byte covers that (a list of a million `None`s is a 1 MB file and a
/// 48 MB tree) while stopping files that expand a small memoised object a million times.
const BUDGET_PER_INPUT_BYTE: usize = 64;
const BUDGET_BASE: usize = 1 << 20;

/// Highest pickle protocol this reader knows (Python 3.8+ writes 5).
const MAX_PROTOCOL: u8 = 5;

/// Parses a pickle (protocols 2 to 5) into a value tree without executing anything.
///
/// Understood: `None`, `bool`, `int` (64-bit), `float`, `str`, `bytes`, `bytearray`, `list`,
/// `tuple`, `dict`, numpy arrays and numpy scalars of the [`DType`]s, as numpy 1.x and 2.x pickle
/// them. The only globals accepted, and only as callables, are
/// `numpy.core.multiarray._reconstruct` / `numpy._core.multiarray._reconstruct` (with
/// `numpy.ndarray`), `numpy.dtype`, `numpy.core.multiarray.scalar` / `numpy._core.multiarray.scalar`,
/// `numpy.core.numeric._frombuffer` / `numpy._core.numeric._frombuffer` (protocol-5 in-band
/// buffers), `_codecs.encode` (how protocol 2 writes `bytes`) and `builtins.bytes` /
/// `__builtin__.bytes` with no arguments (protocol 2's empty `bytes`). Big-endian arrays are
/// byte-swapped to little-endian. Bytes after the `STOP` opcode are ignored, as Python does.
pub fn parse(bytes: &[u8]) -> Result<PyValue, PickleError> {
    Machine::new(bytes).run()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(bytes: &[u8]) -> PickleError {
        match parse(bytes) {
            Ok(v) => panic!("expected an error, parsed {v:?}"),
            Err(e) => e,
        }
    }

    #[test]
    fn small_values() {
        assert_eq!(parse(b"\x80\x02N.").ok(), Some(PyValue::None));
        assert_eq!(parse(b"\x80\x02K\x07.").ok(), Some(PyValue::Int(7)));
        assert_eq!(parse(b"\x80\x02J\xff\xff\xff\xff.").ok(), Some(PyValue::Int(-1)));
        assert_eq!(parse(b"\x80\x02\x8a\x01\xff.").ok(), Some(PyValue::Int(-1)));
        assert_eq!(parse(b"\x80\x02\x8a\x00.").ok(), Some(PyValue::Int(0)));
        assert_eq!(
            parse(b"\x80\x02G?\xf8\x00\x00\x00\x00\x00\x00.").ok(),
            Some(PyValue::Float(1.5))
        );
    }

    #[test]
    fn memo_shares_mutable_lists() {
        // l = []; memo[0] = l; push memo[0]; append 1 to the top one; (l, l): both see the 1.
        let v = parse(b"\x80\x02]q\x00h\x00K\x01a\x86.").ok();
        let inner = PyValue::List(vec![PyValue::Int(1)]);
        assert_eq!(v, Some(PyValue::Tuple(vec![inner.clone(), inner])));
    }

    #[test]
    fn duplicate_keys_keep_first_position_and_last_value() {
        let v = parse(b"\x80\x02}(K\x01K\x02K\x05K\x06\x88K\x03u.").ok();
        assert_eq!(
            v,
            Some(PyValue::Dict(vec![
                (PyValue::Int(1), PyValue::Int(3)),
                (PyValue::Int(5), PyValue::Int(6)),
            ]))
        );
    }

    #[test]
    fn errors_name_offset_and_opcode() {
        let e = err(b"\x80\x04\x8e\x00\x00\x00\x00\x00\x00\x00\x10abc.");
        assert_eq!(
            e.to_string(),
            format!(
                "truncated at byte 2 while reading BINBYTES8 length {}: 4 bytes left",
                1u64 << 60
            )
        );
        assert_eq!(err(b"\x80\x02\xff.").to_string(), "unknown opcode 0xff at byte 2");
        let e = err(b"\x80\x02cposix\nsystem\n.");
        assert!(e.to_string().starts_with("global posix.system is not allowed (GLOBAL at byte 2)"));
        assert_eq!(
            err(b"").to_string(),
            "input ended at byte 0 without a STOP opcode (is the file truncated?)"
        );
        assert!(matches!(
            err(b"\x80\x02J\x01\x00"),
            PickleError::Truncated { offset: 2, opcode: "BININT", .. }
        ));
    }
}
