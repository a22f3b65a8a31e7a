//! `promptdt model forward`: run the model on a batch stored in safetensors and write the predicted
//! actions, so users can check promptdt against their own PyTorch code.
//!
//! Input tensors (float32 unless said; `B` samples, `K` history steps, `Lp` prompt steps):
//!
//! | name | shape | |
//! |---|---|---|
//! | `states` | `[B, K, state_dim]` | normalised states |
//! | `actions` | `[B, K, act_dim]` | |
//! | `returns_to_go` | `[B, K, 1]` | already divided by the scale |
//! | `timesteps` | `[B, K]` | int64 (int32 accepted) |
//! | `attention_mask` | `[B, K]` | 1 real step, 0 padding (int64, int32, float32 or bool) |
//! | `prompt_states`, `prompt_actions`, `prompt_returns_to_go`, `prompt_timesteps`, `prompt_attention_mask` | same with `Lp` | optional: all or none |
//!
//! `rewards` / `prompt_rewards` may be present and are ignored (the model does not read rewards).
//! Output: `action_preds` `[B, K, act_dim]` float32, eval mode (dropout off).

use crate::checkpoint::{self, write_atomic, CheckpointError};
use crate::config::PromptDtConfig;
use crate::prompt_dt::{ForwardError, PromptDt, Segments};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tch::{nn::VarStore, Device, Kind, Tensor};

#[derive(Debug, thiserror::Error)]
pub enum ForwardFileError {
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a safetensors file: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: tensor `{name}` is missing")]
    Missing { path: PathBuf, name: &'static str },
    #[error("{path}: tensor `{name}` has dtype {dtype:?}, expected {expected}")]
    Dtype { path: PathBuf, name: String, dtype: Dtype, expected: &'static str },
    #[error("{path}: tensor `{name}` holds a non-finite value")]
    NonFinite { path: PathBuf, name: String },
    #[error(
        "{path}: the prompt tensors must be given all together or not at all; missing `{name}`"
    )]
    PartialPrompt { path: PathBuf, name: &'static str },
    #[error("{path}: {source}")]
    Forward { path: PathBuf, source: ForwardError },
    #[error("{path}: cannot infer the architecture: {message}")]
    Architecture { path: PathBuf, message: String },
}

/// Reads the architecture (dims, width, depth, MLP size, timestep table) off a weights file. The
/// number of attention heads comes from the file's metadata (promptdt writes it) or `n_head`; a
/// file without it (a PyTorch `state_dict` export) needs `n_head`, since every divisor of the
/// width would load and run, with different results.
pub fn infer_config(
    path: &Path,
    n_head: Option<usize>,
) -> Result<PromptDtConfig, ForwardFileError> {
    let bytes = pdt_base::fs::read_limited(path, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
        .map_err(|source| ForwardFileError::Io { path: path.into(), source })?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| ForwardFileError::Format { path: path.into(), message: e.to_string() })?;
    let arch = |message: String| ForwardFileError::Architecture { path: path.into(), message };
    let shape = |name: &str| -> Result<Vec<usize>, ForwardFileError> {
        st.tensor(name).map(|t| t.shape().to_vec()).map_err(|_| arch(format!("no tensor `{name}`")))
    };
    let two = |name: &str| -> Result<(usize, usize), ForwardFileError> {
        match shape(name)?.as_slice() {
            [a, b] => Ok((*a, *b)),
            s => Err(arch(format!("`{name}` has shape {s:?}, expected 2 dims"))),
        }
    };
    let header = SafeTensors::read_metadata(&bytes)
        .map_err(|e| ForwardFileError::Format { path: path.into(), message: e.to_string() })?
        .1;
    let recorded: Option<usize> = match header.metadata() {
        Some(meta) => match meta.get(checkpoint::ARCHITECTURE_KEY) {
            Some(text) => {
                let v: serde_json::Value = serde_json::from_str(text).map_err(|e| {
                    arch(format!("metadata `{}` is not JSON: {e}", checkpoint::ARCHITECTURE_KEY))
                })?;
                Some(v["n_head"].as_u64().filter(|&n| n >= 1).ok_or_else(|| {
                    arch(format!("metadata `{}` has no n_head >= 1", checkpoint::ARCHITECTURE_KEY))
                })? as usize)
            }
            None => None,
        },
        None => None,
    };
    let n_head = match (recorded, n_head) {
        (Some(r), Some(g)) if r != g => {
            return Err(arch(format!(
                "the weights record n_head = {r}, but --n-head {g} was given"
            )))
        }
        (Some(r), _) => r,
        (None, Some(g)) => g,
        (None, None) => {
            return Err(arch(
                "the number of attention heads is not recorded in the weights (a PyTorch \
                 state_dict export carries none) and cannot be read off their shapes; give \
                 --n-head N (the reference model has 1)"
                    .into(),
            ))
        }
    };
    let (hidden, state_dim) = two("embed_state.weight")?;
    let (_, act_dim) = two("embed_action.weight")?;
    let (max_ep_len, _) = two("embed_timestep.weight")?;
    let (_, n_inner) = two("transformer.h.0.mlp.c_fc.weight")?;
    let n_layer =
        (0..).take_while(|i| st.tensor(&format!("transformer.h.{i}.ln_1.weight")).is_ok()).count();
    let n_positions = match shape("transformer.h.0.attn.bias") {
        Ok(s) if s.len() == 4 => s[3],
        _ => 1024,
    };
    let cfg = PromptDtConfig {
        state_dim,
        act_dim,
        hidden_size: hidden,
        n_layer,
        n_head,
        n_inner,
        max_ep_len,
        n_positions,
        ..PromptDtConfig::reference(state_dim, act_dim)
    };
    cfg.validate().map_err(arch)?;
    Ok(cfg)
}

fn tensor_of(
    path: &Path,
    st: &SafeTensors<'_>,
    name: &str,
    kind: Kind,
) -> Result<Option<Tensor>, ForwardFileError> {
    let Ok(view) = st.tensor(name) else { return Ok(None) };
    let shape: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
    let t = decode(path, name, &view, kind)?;
    Ok(Some(t.view(shape.as_slice())))
}

fn decode(
    path: &Path,
    name: &str,
    view: &TensorView<'_>,
    kind: Kind,
) -> Result<Tensor, ForwardFileError> {
    let d = view.data();
    let bad = |expected| ForwardFileError::Dtype {
        path: path.into(),
        name: name.into(),
        dtype: view.dtype(),
        expected,
    };
    let le4 = |c: &[u8]| [c[0], c[1], c[2], c[3]];
    let le8 = |c: &[u8]| [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
    match kind {
        Kind::Int64 => {
            let v: Vec<i64> = match view.dtype() {
                Dtype::I64 => d.chunks_exact(8).map(|c| i64::from_le_bytes(le8(c))).collect(),
                Dtype::I32 => {
                    d.chunks_exact(4).map(|c| i32::from_le_bytes(le4(c)) as i64).collect()
                }
                _ => return Err(bad("int64 or int32")),
            };
            Ok(Tensor::from_slice(&v))
        }
        _ => {
            let v: Vec<f32> = match view.dtype() {
                Dtype::F32 => d.chunks_exact(4).map(|c| f32::from_le_bytes(le4(c))).collect(),
                Dtype::F64 => {
                    d.chunks_exact(8).map(|c| f64::from_le_bytes(le8(c)) as f32).collect()
                }
                Dtype::I64 => {
                    d.chunks_exact(8).map(|c| i64::from_le_bytes(le8(c)) as f32).collect()
                }
                Dtype::I32 => {
                    d.chunks_exact(4).map(|c| i32::from_le_bytes(le4(c)) as f32).collect()
                }
                Dtype::BOOL | Dtype::U8 => d.iter().map(|&b| f32::from(b)).collect(),
                _ => return Err(bad("float32, float64, int64, int32, uint8 or bool")),
            };
            if v.iter().any(|x| !x.is_finite()) {
                return Err(ForwardFileError::NonFinite { path: path.into(), name: name.into() });
            }
            Ok(Tensor::from_slice(&v))
        }
    }
}

fn segments(
    path: &Path,
    st: &SafeTensors<'_>,
    prefix: &'static str,
) -> Result<Option<Segments>, ForwardFileError> {
    const NAMES: [(&str, &str); 5] = [
        ("states", "prompt_states"),
        ("actions", "prompt_actions"),
        ("returns_to_go", "prompt_returns_to_go"),
        ("timesteps", "prompt_timesteps"),
        ("attention_mask", "prompt_attention_mask"),
    ];
    let mut got = Vec::new();
    for (plain, prompted) in NAMES {
        let name = if prefix.is_empty() { plain } else { prompted };
        let kind = if plain == "timesteps" { Kind::Int64 } else { Kind::Float };
        got.push((name, tensor_of(path, st, name, kind)?));
    }
    let present = got.iter().filter(|(_, t)| t.is_some()).count();
    if present == 0 && !prefix.is_empty() {
        return Ok(None);
    }
    if let Some((name, _)) = got.iter().find(|(_, t)| t.is_none()) {
        return Err(if prefix.is_empty() {
            ForwardFileError::Missing { path: path.into(), name }
        } else {
            ForwardFileError::PartialPrompt { path: path.into(), name }
        });
    }
    let mut it = got.into_iter().filter_map(|(_, t)| t);
    let mut next = || it.next().unwrap_or_else(Tensor::new);
    Ok(Some(Segments {
        states: next(),
        actions: next(),
        returns_to_go: next(),
        timesteps: next(),
        mask: next(),
    }))
}

/// What [`forward_file`] did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ForwardSummary {
    pub batch: i64,
    pub history_steps: i64,
    pub prompt_steps: i64,
    pub act_dim: usize,
}

/// Loads `weights`, runs the model in eval mode on `inputs`, writes `action_preds` to `out`.
pub fn forward_file(
    weights: &Path,
    inputs: &Path,
    out: &Path,
    device: Device,
    n_head: Option<usize>,
) -> Result<ForwardSummary, ForwardFileError> {
    let cfg = infer_config(weights, n_head)?;
    let mut vs = VarStore::new(device);
    let model = PromptDt::new(&vs.root(), &cfg);
    checkpoint::load(&mut vs, weights, cfg.n_layer)?;
    let bytes = pdt_base::fs::read_limited(inputs, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
        .map_err(|source| ForwardFileError::Io { path: inputs.into(), source })?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| ForwardFileError::Format { path: inputs.into(), message: e.to_string() })?;
    let to_dev = |s: Segments| Segments {
        states: s.states.to_device(device),
        actions: s.actions.to_device(device),
        returns_to_go: s.returns_to_go.to_device(device),
        timesteps: s.timesteps.to_device(device),
        mask: s.mask.to_device(device),
    };
    let history = segments(inputs, &st, "")?
        .map(to_dev)
        .ok_or(ForwardFileError::Missing { path: inputs.into(), name: "states" })?;
    let prompt = segments(inputs, &st, "prompt_")?.map(to_dev);
    model
        .check_inputs(&history, prompt.as_ref())
        .map_err(|source| ForwardFileError::Forward { path: inputs.into(), source })?;
    let preds =
        tch::no_grad(|| model.forward(&history, prompt.as_ref(), false)).to_device(Device::Cpu);
    let shape: Vec<usize> = preds.size().iter().map(|&d| d as usize).collect();
    let mut values = vec![0f32; preds.numel()];
    preds.contiguous().view([-1]).copy_data(&mut values, preds.numel());
    let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let view = TensorView::new(Dtype::F32, shape, &data)
        .map_err(|e| ForwardFileError::Format { path: out.into(), message: e.to_string() })?;
    let mut meta = BTreeMap::new();
    meta.insert("producer".to_string(), "promptdt model forward".to_string());
    let bytes = safetensors::serialize([("action_preds", view)], &Some(meta.into_iter().collect()))
        .map_err(|e| ForwardFileError::Format { path: out.into(), message: e.to_string() })?;
    write_atomic(out, &bytes)
        .map_err(|source| ForwardFileError::Io { path: out.into(), source })?;
    Ok(ForwardSummary {
        batch: history.batch_size(),
        history_steps: history.len(),
        prompt_steps: prompt.as_ref().map_or(0, Segments::len),
        act_dim: cfg.act_dim,
    })
}
