//! A pack of N Prompt-DT models of one shape, computed as one: every parameter carries a
//! leading run dimension N (a `Conv1D` weight `[N, in, out]`, a LayerNorm weight `[N, H]`, the
//! timestep table `[N, max_ep_len, H]`), and the forward pass runs all N models with batched matrix
//! products (`baddbmm`), one kernel per layer for the whole pack.
//!
//! Each run's computation equals its solo [`pdt_model::PromptDt`] computation up to rounding:
//! - Runs may differ in prompt length (Table 1) and in whether they use a prompt at all (MT-ORL):
//!   every run's prompt is *left*-padded to the pack's prompt length `P` with masked steps, so its
//!   sequence is `[padding ; its prompt ; its history]`. The model has no position embedding (the
//!   timestep embedding is the only position information), so the shift changes nothing; the
//!   padding comes first, so the causal order of the solo sequence is kept; and padded keys get the
//!   padding bias (-1e4), so their softmax weight underflows to exactly 0 for every real query.
//!   (A padded step's own prediction is read by nothing and differs from solo's: a query whose
//!   keys are all masked attends to whatever keys its row has, and the pack's row has more.)
//!   A run without prompt has all `P` prompt steps padded, and its prompt tokens are replaced by
//!   zeros (`where`, not a product), so no value or gradient of its prompt layers enters.
//! - Dropout: for each run, libtorch's generator is seeded with the run's seed and the masks are
//!   drawn in the solo forward's order and shapes (`at::dropout` on the CPU: `empty_like(x)
//!   .bernoulli_(1-p).div_(1-p)`, then `x * noise`), then padded and stacked; so on the CPU a run's
//!   masks are bit for bit solo's.
//! - Nothing mixes runs: every op is per row of the run dimension (matrix products per run, norms and
//!   softmax per token, the loss per run), so a run's results do not depend on the other runs' data.
//!
//! Row `n * B + b` of a flattened `[N*B, ...]` tensor is sample `b` of run `n`.

use pdt_model::{PromptDtConfig, Segments};
use tch::{Device, Kind, Tensor};

/// Why a pack's forward pass or weights were refused.
#[derive(Debug, thiserror::Error)]
pub enum PackedError {
    #[error("run {slot}: {what}")]
    Input { slot: usize, what: String },
    #[error("the pack has no run with inputs")]
    Empty,
    #[error("parameter `{name}`: {what}")]
    Weight { name: String, what: String },
    #[error("run {slot} is outside the pack of {slots}")]
    Slot { slot: usize, slots: usize },
}

/// The solo parameters' names (reference `state_dict` order, [`PromptDtConfig::parameter_names`])
/// and shapes.
pub fn parameter_shapes(cfg: &PromptDtConfig) -> Vec<(String, Vec<i64>)> {
    let (h, ds, da) = (cfg.hidden_size as i64, cfg.state_dim as i64, cfg.act_dim as i64);
    let (inner, e) = (cfg.n_inner as i64, cfg.max_ep_len as i64);
    cfg.parameter_names()
        .into_iter()
        .map(|name| {
            let bias = name.ends_with(".bias");
            // The module name without `.weight` / `.bias` and without the `prompt_` prefix.
            let module = name.rsplit_once('.').map_or(name.as_str(), |(m, _)| m);
            let module = module.strip_prefix("prompt_").unwrap_or(module);
            let last = module.rsplit('.').next().unwrap_or(module);
            // (in, out) of the linear layers; LayerNorms and the rest below.
            let linear: Option<(i64, i64)> = match last {
                "embed_return" => Some((1, h)),
                "embed_state" => Some((ds, h)),
                "embed_action" => Some((da, h)),
                "predict_state" => Some((h, ds)),
                "0" => Some((h, da)), // predict_action.0
                "predict_return" => Some((h, 1)),
                _ => None,
            };
            let conv: Option<(i64, i64)> = match module.rsplit('.').take(2).collect::<Vec<_>>()[..]
            {
                ["c_attn", "attn"] => Some((h, 3 * h)),
                ["c_proj", "attn"] => Some((h, h)),
                ["c_fc", "mlp"] => Some((h, inner)),
                ["c_proj", "mlp"] => Some((inner, h)),
                _ => None,
            };
            let shape = match (linear, conv) {
                // nn.Linear stores its weight (out, in); HF's Conv1D stores (in, out).
                (Some((i, o)), _) => {
                    if bias {
                        vec![o]
                    } else {
                        vec![o, i]
                    }
                }
                (None, Some((i, o))) => {
                    if bias {
                        vec![o]
                    } else {
                        vec![i, o]
                    }
                }
                (None, None) if last == "embed_timestep" => vec![e, h],
                (None, None) if last == "wte" => vec![1, h],
                _ => vec![h], // LayerNorms
            };
            (name, shape)
        })
        .collect()
}

/// Positions in [`PromptDtConfig::parameter_names`] of one layer's weight (its bias follows).
#[derive(Debug, Clone, Copy)]
struct BlockIdx {
    ln_1: usize,
    c_attn: usize,
    attn_proj: usize,
    ln_2: usize,
    c_fc: usize,
    mlp_proj: usize,
}

#[derive(Debug, Clone, Copy)]
struct EmbIdx {
    timestep: usize,
    ret: usize,
    state: usize,
    action: usize,
}

#[derive(Debug, Clone)]
struct Idx {
    blocks: Vec<BlockIdx>,
    ln_f: usize,
    history: EmbIdx,
    prompt: EmbIdx,
    embed_ln: usize,
    predict_action: usize,
}

impl Idx {
    fn new(names: &[String]) -> Result<Self, PackedError> {
        let at = |name: String| {
            names.iter().position(|n| *n == name).ok_or_else(|| PackedError::Weight {
                name,
                what: "not a parameter of the model".into(),
            })
        };
        let n_layer = names.iter().filter(|n| n.ends_with(".ln_1.weight")).count();
        let blocks = (0..n_layer)
            .map(|i| {
                let w = |m: &str| at(format!("transformer.h.{i}.{m}.weight"));
                Ok(BlockIdx {
                    ln_1: w("ln_1")?,
                    c_attn: w("attn.c_attn")?,
                    attn_proj: w("attn.c_proj")?,
                    ln_2: w("ln_2")?,
                    c_fc: w("mlp.c_fc")?,
                    mlp_proj: w("mlp.c_proj")?,
                })
            })
            .collect::<Result<Vec<_>, PackedError>>()?;
        let emb = |p: &str| -> Result<EmbIdx, PackedError> {
            Ok(EmbIdx {
                timestep: at(format!("{p}embed_timestep.weight"))?,
                ret: at(format!("{p}embed_return.weight"))?,
                state: at(format!("{p}embed_state.weight"))?,
                action: at(format!("{p}embed_action.weight"))?,
            })
        };
        Ok(Self {
            blocks,
            ln_f: at("transformer.ln_f.weight".into())?,
            history: emb("")?,
            prompt: emb("prompt_")?,
            embed_ln: at("embed_ln.weight".into())?,
            predict_action: at("predict_action.0.weight".into())?,
        })
    }
}

/// One run's inputs to a pack's forward pass: its history and, when it uses one, its prompt.
#[derive(Debug, Clone, Copy)]
pub struct PackedRow<'a> {
    pub history: &'a Segments,
    pub prompt: Option<&'a Segments>,
}

/// The inputs of every run of a pack, stacked and padded to the pack's prompt length.
///
/// # Shapes
/// `history`: `[N*B, K, ...]`; `prompt`: `[N*B, P, ...]` (absent when `P = 0`), each run's prompt
/// left-padded with masked zero steps.
#[derive(Debug)]
pub struct PackedBatch {
    pub history: Segments,
    pub prompt: Option<Segments>,
    /// Prompt steps of each run (0: no prompt, or no inputs).
    pub prompt_lens: Vec<i64>,
    /// Runs with inputs; the others got a placeholder batch (zeros, fully masked prompt).
    pub present: Vec<bool>,
    /// Samples per run (B), history steps (K) and the pack's prompt length (P).
    pub batch: i64,
    pub k: i64,
    pub p: i64,
}

impl PackedBatch {
    /// Stacks the runs' inputs (`rows[n] = None` for a run without inputs this step: it gets a
    /// finite placeholder). Every run must have `batch` samples of `k` history steps and at most
    /// `p` prompt steps.
    pub fn new(
        rows: &[Option<PackedRow<'_>>],
        batch: i64,
        k: i64,
        p: i64,
        cfg: &PromptDtConfig,
        device: Device,
    ) -> Result<Self, PackedError> {
        let (ds, da) = (cfg.state_dim as i64, cfg.act_dim as i64);
        if rows.iter().all(Option::is_none) {
            return Err(PackedError::Empty);
        }
        let mut histories = Vec::with_capacity(rows.len());
        let mut prompts = Vec::with_capacity(rows.len());
        let mut prompt_lens = Vec::with_capacity(rows.len());
        for (slot, row) in rows.iter().enumerate() {
            let bad = |what: String| PackedError::Input { slot, what };
            let Some(row) = row else {
                histories.push(shared_placeholder(batch, k, ds, da, 1.0, device));
                prompts.push(shared_placeholder(batch, p, ds, da, 0.0, device));
                prompt_lens.push(0);
                continue;
            };
            check_segments(row.history, batch, k, ds, da)
                .map_err(|w| bad(format!("history {w}")))?;
            histories.push(row.history.shallow_clone());
            let lp = match row.prompt {
                Some(pr) => {
                    let lp = pr.len();
                    if lp > p {
                        return Err(bad(format!("prompt of {lp} steps, the pack holds {p}")));
                    }
                    check_segments(pr, batch, lp, ds, da)
                        .map_err(|w| bad(format!("prompt {w}")))?;
                    prompts.push(left_pad(pr, p - lp, device));
                    lp
                }
                None => {
                    prompts.push(shared_placeholder(batch, p, ds, da, 0.0, device));
                    0
                }
            };
            if 3 * (lp + k) > cfg.n_positions as i64 {
                return Err(bad(format!(
                    "3 x ({lp} prompt + {k} history steps) tokens exceed n_positions = {}",
                    cfg.n_positions
                )));
            }
            prompt_lens.push(lp);
        }
        Ok(Self {
            history: cat_segments(&histories),
            prompt: (p > 0).then(|| cat_segments(&prompts)),
            prompt_lens,
            present: rows.iter().map(Option::is_some).collect(),
            batch,
            k,
            p,
        })
    }

    /// Number of runs (N).
    pub fn slots(&self) -> i64 {
        self.prompt_lens.len() as i64
    }

    /// The actions and the loss mask of every step of the packed sequence, prompt steps first:
    /// `[N, B, P+K, da]` and `[N, B, P+K]` (float). `supervise_prompt` `[N]` (float, on the
    /// device; a pack uploads it once) is 1 where run `n`'s loss reads its prompt steps (the
    /// paper's loss), 0 where they are masked (the reference's).
    pub fn targets(&self, supervise_prompt: &Tensor) -> (Tensor, Tensor) {
        let (n, b) = (self.slots(), self.batch);
        let h = &self.history;
        let Some(p) = &self.prompt else {
            let da = h.actions.size()[2];
            return (h.actions.view([n, b, self.k, da]), h.mask.view([n, b, self.k]));
        };
        let da = h.actions.size()[2];
        let keep = supervise_prompt.view([n, 1, 1]);
        let prompt_mask = p.mask.view([n, b, self.p]) * keep; // 0/1 products of finite masks
        let actions = Tensor::cat(&[&p.actions, &h.actions], 1).view([n, b, self.p + self.k, da]);
        let mask = Tensor::cat(&[prompt_mask, h.mask.view([n, b, self.k])], 2);
        (actions, mask)
    }
}

/// Zeros (timestep 0) with the given mask value: a finite stand-in.
fn placeholder(b: i64, t: i64, ds: i64, da: i64, mask: f64, device: Device) -> Segments {
    let f = (Kind::Float, device);
    Segments {
        states: Tensor::zeros([b, t, ds], f),
        actions: Tensor::zeros([b, t, da], f),
        returns_to_go: Tensor::zeros([b, t, 1], f),
        timesteps: Tensor::zeros([b, t], (Kind::Int64, device)),
        mask: Tensor::full([b, t], mask, f),
    }
}

/// [`placeholder`], made once per shape and reused: a pack whose runs lack a prompt (MT-ORL,
/// MT-BC-Finetune) needs one for each of them at every step, which made anew was 24 more
/// allocations and fills per step for 6 such runs (on a GPU, a kernel each). Read only: `cat`
/// copies it into the pack's batch. At most `KEEP` shapes are kept (a pack has one or two).
fn shared_placeholder(b: i64, t: i64, ds: i64, da: i64, mask: f64, device: Device) -> Segments {
    type Key = (i64, i64, i64, i64, u64, Device);
    const KEEP: usize = 16;
    static MADE: std::sync::Mutex<Vec<(Key, Segments)>> = std::sync::Mutex::new(Vec::new());
    let key = (b, t, ds, da, mask.to_bits(), device);
    let mut made = MADE.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, s)) = made.iter().find(|(k, _)| *k == key) {
        return s.shallow_clone();
    }
    let s = placeholder(b, t, ds, da, mask, device);
    if made.len() < KEEP {
        made.push((key, s.shallow_clone()));
    }
    s
}

/// `pad` masked zero steps before `s`'s steps.
fn left_pad(s: &Segments, pad: i64, device: Device) -> Segments {
    if pad == 0 {
        return s.shallow_clone();
    }
    let (b, ds, da) = (s.batch_size(), s.states.size()[2], s.actions.size()[2]);
    let z = placeholder(b, pad, ds, da, 0.0, device);
    Segments {
        states: Tensor::cat(&[&z.states, &s.states], 1),
        actions: Tensor::cat(&[&z.actions, &s.actions], 1),
        returns_to_go: Tensor::cat(&[&z.returns_to_go, &s.returns_to_go], 1),
        timesteps: Tensor::cat(&[&z.timesteps, &s.timesteps], 1),
        mask: Tensor::cat(&[&z.mask, &s.mask], 1),
    }
}

fn cat_segments(rows: &[Segments]) -> Segments {
    let cat = |f: fn(&Segments) -> &Tensor| Tensor::cat(&rows.iter().map(f).collect::<Vec<_>>(), 0);
    Segments {
        states: cat(|s| &s.states),
        actions: cat(|s| &s.actions),
        returns_to_go: cat(|s| &s.returns_to_go),
        timesteps: cat(|s| &s.timesteps),
        mask: cat(|s| &s.mask),
    }
}

fn check_segments(s: &Segments, b: i64, t: i64, ds: i64, da: i64) -> Result<(), String> {
    let expect = [
        ("states", &s.states, vec![b, t, ds]),
        ("actions", &s.actions, vec![b, t, da]),
        ("returns_to_go", &s.returns_to_go, vec![b, t, 1]),
        ("timesteps", &s.timesteps, vec![b, t]),
        ("mask", &s.mask, vec![b, t]),
    ];
    for (name, tensor, want) in expect {
        if tensor.size() != want {
            return Err(format!("`{name}` has shape {:?}, expected {want:?}", tensor.size()));
        }
    }
    if t == 0 {
        return Err("has no steps".into());
    }
    Ok(())
}

mod trunk;

pub use trunk::{DropoutSeeds, LayerNormPlan, MaskDraw, PackedPromptDt};
