//! [`PickleError`]: why a pickle was refused.

/// Why a pickle was refused. Every variant says where (byte offset of the opcode) and, where it
/// helps, which opcode.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PickleError {
    #[error("truncated at byte {offset} while reading {opcode} {what}: {available} bytes left")]
    Truncated { offset: usize, opcode: &'static str, what: String, available: usize },
    #[error("input ended at byte {offset} without a STOP opcode (is the file truncated?)")]
    NoStop { offset: usize },
    #[error("unknown opcode 0x{byte:02x} at byte {offset}")]
    UnknownOpcode { offset: usize, byte: u8 },
    #[error("opcode {opcode} at byte {offset} is not supported: {reason}")]
    UnsupportedOpcode { offset: usize, opcode: &'static str, reason: &'static str },
    #[error(
        "global {module}.{name} is not allowed ({opcode} at byte {offset}); only the numpy array, \
         numpy scalar and bytes constructors are"
    )]
    GlobalNotAllowed { offset: usize, opcode: &'static str, module: String, name: String },
    #[error("{opcode} at byte {offset}: {message}")]
    Invalid { offset: usize, opcode: &'static str, message: String },
    #[error("{opcode} at byte {offset}: {message}")]
    Limit { offset: usize, opcode: &'static str, message: String },
}

impl PickleError {
    /// Byte offset of the opcode at fault (or of the end of input).
    pub fn offset(&self) -> usize {
        match self {
            PickleError::Truncated { offset, .. }
            | PickleError::NoStop { offset }
            | PickleError::UnknownOpcode { offset, .. }
            | PickleError::UnsupportedOpcode { offset, .. }
            | PickleError::GlobalNotAllowed { offset, .. }
            | PickleError::Invalid { offset, .. }
            | PickleError::Limit { offset, .. } => *offset,
        }
    }
}
