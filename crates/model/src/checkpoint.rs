//! Model weights as safetensors under the reference `state_dict` names, both ways.
//!
//! Reading accepts exactly the reference's 67-entry state_dict: every parameter must be present
//! with its shape, and the two per-block buffers (`attn.bias`, a uint8 tril(1024x1024) causal mask,
//! and `attn.masked_bias`, a 0-d float -1e4) may be present and are checked, not loaded (the causal
//! mask is rebuilt). Writing emits those buffers too, so `model.load_state_dict(strict=True)` in
//! PyTorch accepts the file. Anything else (an unknown name, a wrong shape or dtype, NaN) is an
//! error naming the file and tensor.

use pdt_base::tensor_file::describe_safetensors_error;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tch::{nn::VarStore, Kind, Tensor};

use crate::PromptDtConfig;

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: tensor `{name}` is missing")]
    Missing { path: PathBuf, name: String },
    #[error("{path}: tensor `{name}` has dtype {dtype:?}, expected {expected}")]
    Dtype { path: PathBuf, name: String, dtype: Dtype, expected: &'static str },
    #[error("{path}: unexpected tensor `{name}` (not a parameter or buffer of this model)")]
    Unexpected { path: PathBuf, name: String },
    #[error("{path}: tensor `{name}` has shape {got:?} and dtype {dtype}, expected shape {expected:?} ({what})")]
    Shape {
        path: PathBuf,
        name: String,
        got: Vec<usize>,
        dtype: String,
        expected: Vec<i64>,
        what: &'static str,
    },
    #[error("{path}: tensor `{name}` holds a non-finite value")]
    NonFinite { path: PathBuf, name: String },
    #[error("{path}: buffer `{name}` does not hold the reference's value ({what})")]
    Buffer { path: PathBuf, name: String, what: &'static str },
    #[error("{path}: {message}")]
    Architecture { path: PathBuf, message: String },
}

/// Names of the per-block buffers of the reference state_dict.
fn buffer_names(n_layer: usize) -> Vec<(String, &'static str)> {
    (0..n_layer)
        .flat_map(|i| {
            [
                (format!("transformer.h.{i}.attn.bias"), "bias"),
                (format!("transformer.h.{i}.attn.masked_bias"), "masked_bias"),
            ]
        })
        .collect()
}

/// Reads `tensor` as f32 values (from F32 or F64 files).
fn to_f32(view: &TensorView<'_>) -> Option<Vec<f32>> {
    let data = view.data();
    match view.dtype() {
        Dtype::F32 => Some(
            data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
        ),
        Dtype::F64 => Some(
            data.chunks_exact(8)
                .map(|c| {
                    f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32
                })
                .collect(),
        ),
        _ => None,
    }
}

/// Parses a weights file's bytes, with a plain message on failure.
pub(crate) fn deserialize<'a>(
    path: &Path,
    bytes: &'a [u8],
) -> Result<SafeTensors<'a>, CheckpointError> {
    SafeTensors::deserialize(bytes).map_err(|e| CheckpointError::Format {
        path: path.into(),
        message: describe_safetensors_error(&e, bytes.len()),
    })
}

/// Checks every tensor's dtype before anything reads values: parameters are float32 (float64 is
/// accepted and converted), the causal-mask buffers uint8, `masked_bias` float. A half-precision
/// export would otherwise be reported as whatever is read first (a "wrong" `masked_bias`).
pub(crate) fn check_dtypes(
    path: &Path,
    st: &SafeTensors<'_>,
    n_layer: usize,
) -> Result<(), CheckpointError> {
    let buffers: BTreeMap<String, &'static str> = buffer_names(n_layer).into_iter().collect();
    let mut names: Vec<&String> = st.names();
    names.sort();
    for name in names {
        let Ok(view) = st.tensor(name) else { continue };
        let (ok, expected) = match buffers.get(name.as_str()) {
            Some(&"bias") => (view.dtype() == Dtype::U8, "U8 (the causal-mask buffer)"),
            _ => (
                matches!(view.dtype(), Dtype::F32 | Dtype::F64),
                "F32 (F64 is accepted too; convert half-precision weights with .float())",
            ),
        };
        if !ok {
            return Err(CheckpointError::Dtype {
                path: path.into(),
                name: name.clone(),
                dtype: view.dtype(),
                expected,
            });
        }
    }
    Ok(())
}

/// The architecture a promptdt weights file records ([`ARCHITECTURE_KEY`] in its metadata), as a
/// JSON object; `None` for a file without it (a PyTorch `state_dict` export).
pub fn recorded_architecture(
    path: &Path,
    bytes: &[u8],
) -> Result<Option<serde_json::Map<String, serde_json::Value>>, CheckpointError> {
    let format = |message: String| CheckpointError::Format { path: path.into(), message };
    let (_, header) = SafeTensors::read_metadata(bytes)
        .map_err(|e| format(describe_safetensors_error(&e, bytes.len())))?;
    let key = ARCHITECTURE_KEY;
    match header.metadata().as_ref().and_then(|m| m.get(key)) {
        None => Ok(None),
        Some(text) => match serde_json::from_str(text) {
            Ok(serde_json::Value::Object(map)) => Ok(Some(map)),
            Ok(_) => Err(format(format!("metadata `{key}` is not a JSON object"))),
            Err(e) => Err(format(format!("metadata `{key}` is not JSON: {e}"))),
        },
    }
}

/// Checks what a weights file records of its architecture against the model it is loaded into:
/// every recorded field must equal `cfg`'s. The shapes check all but the number of attention
/// heads, which changes no shape: without this a checkpoint written with 4 heads would run as the
/// 2 its run's `config.toml` says (or the reverse), with other results and no error.
fn check_recorded(path: &Path, bytes: &[u8], cfg: &PromptDtConfig) -> Result<(), CheckpointError> {
    let Some(recorded) = recorded_architecture(path, bytes)? else { return Ok(()) };
    for (name, want) in cfg.shape_fields() {
        let Some(said) = recorded.get(name) else { continue };
        if said.as_u64() != u64::try_from(want).ok() {
            return Err(CheckpointError::Architecture {
                path: path.into(),
                message: format!(
                    "the weights record {name} = {said} (metadata `{ARCHITECTURE_KEY}`), but the \
                     model they are loaded into has {name} = {want} (the run's configuration, \
                     [model] in config.toml): they were not written by this run's model"
                ),
            });
        }
    }
    Ok(())
}

/// Loads weights into the variables of `vs` (built by [`crate::PromptDt::new`] with `cfg`). What
/// the file records of its architecture must be `cfg` ([`check_recorded`]).
pub fn load(vs: &mut VarStore, path: &Path, cfg: &PromptDtConfig) -> Result<(), CheckpointError> {
    let n_layer = cfg.n_layer;
    let bytes = pdt_base::fs::read_limited(path, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
        .map_err(|source| CheckpointError::Io { path: path.into(), source })?;
    let st = deserialize(path, &bytes)?;
    check_recorded(path, &bytes, cfg)?;
    let buffers: BTreeMap<String, &'static str> = buffer_names(n_layer).into_iter().collect();
    let mut vars = vs.variables();
    for name in st.names() {
        if !vars.contains_key(name) && !buffers.contains_key(name) {
            return Err(CheckpointError::Unexpected { path: path.into(), name: name.clone() });
        }
    }
    check_dtypes(path, &st, n_layer)?;
    for (name, kind) in &buffers {
        if let Ok(view) = st.tensor(name) {
            check_buffer(path, name, kind, &view)?;
        }
    }
    let mut loaded = Vec::with_capacity(vars.len());
    for (name, var) in vars.iter_mut() {
        let view = st
            .tensor(name)
            .map_err(|_| CheckpointError::Missing { path: path.into(), name: name.clone() })?;
        let expected = var.size();
        let shape_ok = view.shape().iter().map(|&d| d as i64).eq(expected.iter().copied());
        let values = to_f32(&view).filter(|_| shape_ok).ok_or_else(|| CheckpointError::Shape {
            path: path.into(),
            name: name.clone(),
            got: view.shape().to_vec(),
            dtype: format!("{:?}", view.dtype()),
            expected: expected.clone(),
            what: "float32 or float64",
        })?;
        if values.iter().any(|v| !v.is_finite()) {
            return Err(CheckpointError::NonFinite { path: path.into(), name: name.clone() });
        }
        loaded.push((var.shallow_clone(), Tensor::from_slice(&values).view(expected.as_slice())));
    }
    tch::no_grad(|| {
        for (mut var, value) in loaded {
            var.copy_(&value);
        }
    });
    Ok(())
}

/// Reads a float tensor file of ours (an optimiser's moments, MACAW's weights) into a map by name,
/// each tensor float32 on the CPU. Size-checked, the format's errors in plain words, and every value
/// finite: a NaN moment would otherwise poison the weights at the first step after a resume.
pub fn read_float_tensors(path: &Path) -> Result<BTreeMap<String, Tensor>, CheckpointError> {
    read_float_tensors_of(path, |_| Ok(()))
}

/// [`read_float_tensors`], with the file's tensor names first shown to `check`, so that a file of
/// another kind is named as such before its dtypes are (MACAW's weights against Prompt-DT's).
pub fn read_float_tensors_of(
    path: &Path,
    check: impl FnOnce(&[String]) -> Result<(), String>,
) -> Result<BTreeMap<String, Tensor>, CheckpointError> {
    let bytes = pdt_base::fs::read_limited(path, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
        .map_err(|source| CheckpointError::Io { path: path.into(), source })?;
    let st = deserialize(path, &bytes)?;
    let names: Vec<String> = st.names().into_iter().cloned().collect();
    check(&names).map_err(|message| CheckpointError::Format { path: path.into(), message })?;
    let mut out = BTreeMap::new();
    for (name, view) in st.tensors() {
        let values = to_f32(&view).ok_or_else(|| CheckpointError::Dtype {
            path: path.into(),
            name: name.clone(),
            dtype: view.dtype(),
            expected: "float32 or float64",
        })?;
        if values.iter().any(|v| !v.is_finite()) {
            return Err(CheckpointError::NonFinite { path: path.into(), name });
        }
        let shape: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
        out.insert(name, Tensor::from_slice(&values).view(shape.as_slice()));
    }
    Ok(out)
}

fn check_buffer(
    path: &Path,
    name: &str,
    kind: &str,
    view: &TensorView<'_>,
) -> Result<(), CheckpointError> {
    let bad = |what| CheckpointError::Buffer { path: path.into(), name: name.into(), what };
    match kind {
        "bias" => {
            if view.dtype() != Dtype::U8 || view.shape().len() != 4 || view.shape()[..2] != [1, 1] {
                return Err(bad("a uint8 [1, 1, N, N] lower-triangular causal mask"));
            }
            let n = view.shape()[2];
            if view.shape()[3] != n {
                return Err(bad("a uint8 [1, 1, N, N] lower-triangular causal mask"));
            }
            let data = view.data();
            let tril = (0..n).all(|i| (0..n).all(|j| data[i * n + j] == u8::from(j <= i)));
            if !tril {
                return Err(bad("a uint8 [1, 1, N, N] lower-triangular causal mask"));
            }
        }
        _ => {
            let v = to_f32(view).filter(|v| v.len() == 1).ok_or_else(|| bad("a 0-d float -1e4"))?;
            if v[0] != -1e4 {
                return Err(bad("a 0-d float -1e4"));
            }
        }
    }
    Ok(())
}

/// The safetensors metadata key of the architecture a weights file was written with (JSON of
/// [`crate::PromptDtConfig`]'s shape fields). The number of attention heads cannot be read off the
/// tensors' shapes, so without it a reader would have to guess.
pub const ARCHITECTURE_KEY: &str = "promptdt_architecture";

/// Writes the weights of `vs` plus the reference buffers, atomically (temp file + rename), with
/// the architecture in the metadata ([`ARCHITECTURE_KEY`]).
pub fn save(vs: &VarStore, path: &Path, cfg: &PromptDtConfig) -> Result<(), CheckpointError> {
    let (n_layer, n_positions) = (cfg.n_layer, cfg.n_positions);
    let io = |source| CheckpointError::Io { path: path.into(), source };
    let mut named: Vec<(String, Vec<u8>, Dtype, Vec<usize>)> = Vec::new();
    for (name, var) in vs.variables() {
        let t = var.to_device(tch::Device::Cpu).to_kind(Kind::Float).contiguous();
        let shape: Vec<usize> = t.size().iter().map(|&d| d as usize).collect();
        let mut values = vec![0f32; t.numel()];
        t.view([-1]).copy_data(&mut values, t.numel());
        named.push((
            name,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            Dtype::F32,
            shape,
        ));
    }
    let n = n_positions;
    let tril: Vec<u8> = (0..n * n).map(|k| u8::from(k % n <= k / n)).collect();
    for (name, kind) in buffer_names(n_layer) {
        match kind {
            "bias" => named.push((name, tril.clone(), Dtype::U8, vec![1, 1, n, n])),
            _ => named.push((name, (-1e4f32).to_le_bytes().to_vec(), Dtype::F32, vec![])),
        }
    }
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let views = named
        .iter()
        .map(|(name, data, dtype, shape)| {
            TensorView::new(*dtype, shape.clone(), data).map(|v| (name.clone(), v))
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| CheckpointError::Format { path: path.into(), message: e.to_string() })?;
    let arch = serde_json::json!({
        "state_dim": cfg.state_dim, "act_dim": cfg.act_dim, "hidden_size": cfg.hidden_size,
        "n_layer": cfg.n_layer, "n_head": cfg.n_head, "n_inner": cfg.n_inner,
        "max_ep_len": cfg.max_ep_len, "n_positions": cfg.n_positions,
    });
    let meta: std::collections::HashMap<String, String> =
        [(ARCHITECTURE_KEY.to_string(), arch.to_string())].into_iter().collect();
    let bytes = safetensors::serialize(views, &Some(meta))
        .map_err(|e| CheckpointError::Format { path: path.into(), message: e.to_string() })?;
    pdt_base::fs::write_atomic(path, &bytes).map_err(io)
}
