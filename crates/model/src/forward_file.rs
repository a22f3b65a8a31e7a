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

use crate::checkpoint::{self, CheckpointError};
use crate::config::PromptDtConfig;
use crate::prompt_dt::{ForwardError, PromptDt, Segments, Sequence};
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
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: not a Prompt-DT model: {message}")]
    NotPromptDt { path: PathBuf, message: String },
    #[error(
        "{path}: `{name}`[{index}] is {value}; an attention mask holds 1 (a real step) or 0 \
         (padding)"
    )]
    Mask { path: PathBuf, name: String, index: usize, value: f32 },
    #[error(
        "{path}: `{name}` row {row} is all 0: sample {row} has no real step (the model would \
         attend over padding only and still return actions)"
    )]
    EmptyMaskRow { path: PathBuf, name: String, row: usize },
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

/// Refuses a file that is not Prompt-DT weights (a SAC policy, an optimiser state, MACAW
/// weights, ...) by its tensor names, before anything asks for a number of heads: every name of
/// the reference `state_dict` for the file's number of blocks must be there, and nothing else
/// but the two per-block buffers.
fn check_names(path: &Path, st: &SafeTensors<'_>, n_layer: usize) -> Result<(), ForwardFileError> {
    // With no block at all, report block 0's tensors as missing too.
    let names = PromptDtConfig { n_layer: n_layer.max(1), ..PromptDtConfig::reference(1, 1) }
        .parameter_names();
    let present: std::collections::BTreeSet<&str> =
        st.names().into_iter().map(|n| n.as_str()).collect();
    let buffer = |name: &str| {
        (0..n_layer).any(|i| {
            name == format!("transformer.h.{i}.attn.bias")
                || name == format!("transformer.h.{i}.attn.masked_bias")
        })
    };
    let mut missing: Vec<&str> =
        names.iter().map(String::as_str).filter(|n| !present.contains(n)).collect();
    missing.sort_unstable();
    let unexpected: Vec<&str> =
        present.iter().copied().filter(|n| !names.iter().any(|e| e == n) && !buffer(n)).collect();
    if missing.is_empty() && unexpected.is_empty() {
        return Ok(());
    }
    // A few names of each kind say what the file is; all of them would bury the message.
    let list = |v: &[&str]| {
        let shown: Vec<String> = v.iter().take(4).map(|n| format!("`{n}`")).collect();
        match v.len() {
            n if n > 4 => format!("{} and {} more", shown.join(", "), n - 4),
            _ => shown.join(", "),
        }
    };
    let mut parts = Vec::new();
    if !missing.is_empty() {
        parts.push(if missing.len() == names.len() {
            format!(
                "none of the {} tensors of the reference state_dict ({})",
                names.len(),
                list(&missing)
            )
        } else {
            format!(
                "missing {} of the {} tensors of the reference state_dict ({})",
                missing.len(),
                names.len(),
                list(&missing)
            )
        });
    }
    if !unexpected.is_empty() {
        parts.push(format!(
            "{} tensors that are not Prompt-DT's ({})",
            unexpected.len(),
            list(&unexpected)
        ));
    }
    Err(ForwardFileError::NotPromptDt { path: path.into(), message: parts.join("; ") })
}

/// Reads the architecture (dims, width, depth, MLP size, timestep table) off a weights file. The
/// number of attention heads comes from the file's metadata (promptdt writes it) or `n_head`; a
/// file without it (a PyTorch `state_dict` export) needs `n_head`, since every divisor of the
/// width would load and run, with different results. Every other field the metadata records must
/// agree with the shapes: metadata that disagrees with the tensors is not trusted for the heads
/// either.
pub fn infer_config(
    path: &Path,
    n_head: Option<usize>,
) -> Result<PromptDtConfig, ForwardFileError> {
    let bytes = pdt_base::fs::read_limited(path, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
        .map_err(|source| ForwardFileError::Io { path: path.into(), source })?;
    let st = checkpoint::deserialize(path, &bytes)?;
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
    let n_layer =
        (0..).take_while(|i| st.tensor(&format!("transformer.h.{i}.ln_1.weight")).is_ok()).count();
    check_names(path, &st, n_layer)?;
    checkpoint::check_dtypes(path, &st, n_layer)?;
    let key = checkpoint::ARCHITECTURE_KEY;
    let recorded = checkpoint::recorded_architecture(path, &bytes)?;
    // A recorded field must be a whole number; a missing one is not checked.
    let field = |name: &str| -> Result<Option<usize>, ForwardFileError> {
        match recorded.as_ref().and_then(|m| m.get(name)) {
            None => Ok(None),
            Some(v) => {
                v.as_u64().and_then(|n| usize::try_from(n).ok()).map(Some).ok_or_else(|| {
                    arch(format!("metadata `{key}` has {name} = {v}, expected a whole number"))
                })
            }
        }
    };
    let recorded_heads = match (&recorded, field("n_head")?) {
        (Some(_), None) | (Some(_), Some(0)) => {
            return Err(arch(format!("metadata `{key}` has no n_head >= 1")))
        }
        (_, heads) => heads,
    };
    let n_head = match (recorded_heads, n_head) {
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
    // The causal-mask buffer gives the context length; without it, the recorded value or GPT-2's.
    let n_positions = match shape("transformer.h.0.attn.bias") {
        Ok(s) if s.len() == 4 => Some(s[3]),
        _ => None,
    };
    let from_shapes: [(&str, Option<usize>, &str); 7] = [
        ("state_dim", Some(state_dim), "`embed_state.weight` is [hidden_size, state_dim]"),
        ("act_dim", Some(act_dim), "`embed_action.weight` is [hidden_size, act_dim]"),
        ("hidden_size", Some(hidden), "`embed_state.weight` is [hidden_size, state_dim]"),
        ("n_layer", Some(n_layer), "the blocks `transformer.h.<i>`"),
        ("n_inner", Some(n_inner), "`transformer.h.0.mlp.c_fc.weight` is [hidden_size, n_inner]"),
        ("max_ep_len", Some(max_ep_len), "`embed_timestep.weight` is [max_ep_len, hidden_size]"),
        (
            "n_positions",
            n_positions,
            "`transformer.h.0.attn.bias` is [1, 1, n_positions, n_positions]",
        ),
    ];
    for (name, actual, source) in from_shapes {
        if let (Some(said), Some(actual)) = (field(name)?, actual) {
            if said != actual {
                return Err(arch(format!(
                    "metadata `{key}` says {name} = {said}, but the weights have {actual} \
                     ({source}): the metadata does not describe these weights"
                )));
            }
        }
    }
    let n_positions = match n_positions {
        Some(n) => n,
        None => field("n_positions")?.unwrap_or(1024),
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
    // A sample whose mask is all padding runs (the additive bias makes its attention uniform over
    // padding) and returns actions that mean nothing: refuse it by row. Shapes that are not
    // [B, K] are left to the shape check.
    if name.ends_with("attention_mask") && shape.len() == 2 && shape[1] > 0 {
        let row_sums: Vec<f32> = Vec::<f32>::try_from(t.view(shape.as_slice()).sum_dim_intlist(
            [1i64].as_slice(),
            false,
            Kind::Float,
        ))
        .unwrap_or_default();
        if let Some(row) = row_sums.iter().position(|&s| s == 0.0) {
            return Err(ForwardFileError::EmptyMaskRow {
                path: path.into(),
                name: name.into(),
                row,
            });
        }
    }
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
            // The model turns the mask into an additive bias without looking at its values, so a
            // 7 or a -3 would run and silently weight attention; only 0 and 1 have a meaning.
            if name.ends_with("attention_mask") {
                if let Some(index) = v.iter().position(|&x| x != 0.0 && x != 1.0) {
                    return Err(ForwardFileError::Mask {
                        path: path.into(),
                        name: name.into(),
                        index,
                        value: v[index],
                    });
                }
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

/// What a run's configuration says of the model its checkpoints hold (`model forward` of a file in
/// a run's `checkpoints/`): compared with what is read off the weights, since the number of heads
/// changes no shape and a file's own record of it could be wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct RunArchitecture {
    /// The configuration file it comes from (for messages).
    pub source: PathBuf,
    /// `[model]` fields by name: hidden_size, n_layer, n_head, n_inner, max_ep_len, n_positions.
    pub fields: Vec<(&'static str, usize)>,
}

impl RunArchitecture {
    fn check(&self, weights: &Path, cfg: &PromptDtConfig) -> Result<(), ForwardFileError> {
        let have = cfg.shape_fields();
        for (name, said) in &self.fields {
            let Some((_, actual)) = have.iter().find(|(n, _)| n == name) else { continue };
            if actual != said {
                return Err(ForwardFileError::Architecture {
                    path: weights.into(),
                    message: format!(
                        "the weights have {name} = {actual}, but their run's {} says [model] \
                         {name} = {said}",
                        self.source.display()
                    ),
                });
            }
        }
        Ok(())
    }
}

/// What [`forward_file`] did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ForwardSummary {
    pub batch: i64,
    pub history_steps: i64,
    pub prompt_steps: i64,
    pub act_dim: usize,
}

/// Loads `weights`, runs the model in eval mode on `inputs`, writes `action_preds` to `out`. With
/// `run` (the weights are a run's checkpoint), the architecture must be what the run's
/// configuration says.
pub fn forward_file(
    weights: &Path,
    inputs: &Path,
    out: &Path,
    device: Device,
    n_head: Option<usize>,
    run: Option<&RunArchitecture>,
) -> Result<ForwardSummary, ForwardFileError> {
    let cfg = infer_config(weights, n_head)?;
    if let Some(run) = run {
        run.check(weights, &cfg)?;
    }
    let mut vs = VarStore::new(device);
    let model = PromptDt::new(&vs.root(), &cfg);
    checkpoint::load(&mut vs, weights, &cfg)?;
    let bytes = pdt_base::fs::read_limited(inputs, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
        .map_err(|source| ForwardFileError::Io { path: inputs.into(), source })?;
    let st = SafeTensors::deserialize(&bytes).map_err(|e| ForwardFileError::Format {
        path: inputs.into(),
        message: pdt_base::tensor_file::describe_safetensors_error(&e, bytes.len()),
    })?;
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
    let preds = tch::no_grad(|| model.forward(&history, Sequence::eval(prompt.as_ref())))
        .to_device(Device::Cpu);
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
    pdt_base::fs::write_atomic(out, &bytes)
        .map_err(|source| ForwardFileError::Io { path: out.into(), source })?;
    Ok(ForwardSummary {
        batch: history.batch_size(),
        history_steps: history.len(),
        prompt_steps: prompt.as_ref().map_or(0, Segments::len),
        act_dim: cfg.act_dim,
    })
}
