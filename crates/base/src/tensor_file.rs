//! Plain words for a safetensors file the safetensors crate refuses, for every reader of one
//! (weights, optimiser moments, RL agents and policies).

use safetensors::SafeTensorError;

/// Says in plain words what is wrong with a file the safetensors crate refuses: its own error
/// names (`HeaderTooSmall`, `InvalidHeaderLength`, ...) mean nothing to someone holding the file.
pub fn describe_safetensors_error(e: &SafeTensorError, file_len: usize) -> String {
    let not_st = "truncated, corrupt or not a safetensors file";
    match e {
        SafeTensorError::HeaderTooSmall => format!(
            "the file is {file_len} bytes, too short for a safetensors file (an 8-byte header \
             length, then the header): {not_st}"
        ),
        SafeTensorError::InvalidHeaderLength => format!(
            "the header length in the first 8 bytes is more than the {file_len}-byte file holds: \
             {not_st}"
        ),
        SafeTensorError::HeaderTooLarge => {
            format!("the header length in the first 8 bytes is over 100 MB: {not_st}")
        }
        SafeTensorError::InvalidHeader => format!("the header is not UTF-8 text: {not_st}"),
        SafeTensorError::InvalidHeaderStart => {
            format!("the header does not start with `{{`: {not_st}")
        }
        SafeTensorError::InvalidHeaderDeserialization => {
            format!("the header is not a valid safetensors JSON header: {not_st}")
        }
        SafeTensorError::JsonError(e) => {
            format!("the header is not a valid safetensors JSON header ({e}): {not_st}")
        }
        SafeTensorError::TensorInvalidInfo => {
            "a tensor's dtype and shape do not match the size of its data".into()
        }
        SafeTensorError::InvalidOffset(name) => format!(
            "tensor `{name}`: its data does not follow on from the previous tensor's (tensors must \
             tile the data section without gaps or overlaps)"
        ),
        SafeTensorError::MetadataIncompleteBuffer => format!(
            "the tensors' data does not end where the {file_len}-byte file ends: truncated file or \
             trailing bytes"
        ),
        SafeTensorError::ValidationOverflow => {
            "a tensor's shape overflows when multiplied out".into()
        }
        SafeTensorError::TensorNotFound(name) => format!("there is no tensor `{name}`"),
        SafeTensorError::InvalidTensorView(dtype, shape, len) => {
            format!("{len} bytes do not make a {dtype:?} tensor of shape {shape:?}")
        }
        SafeTensorError::IoError(e) => e.to_string(),
    }
}
