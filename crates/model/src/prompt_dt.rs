//! Prompt-DT: the reference's `PromptDecisionTransformer` (`promptdt-reference.md` a.2-a.4).
//!
//! A sequence is `[prompt tokens ; history tokens]`, each step contributing three tokens in the order
//! (return-to-go, state, action). The action for step t is predicted from the hidden state of its
//! *state* token, so it sees R_t and s_t but not a_t (causal attention).

use crate::config::PromptDtConfig;
use crate::dropout::Dropout;
use crate::gpt2::{Gpt2, LastBlock, PrefixCache};
use crate::lora::LoraAdapters;
use tch::nn::{self, Init, Module};
use tch::{Device, Kind, Tensor};

/// One set of trajectory segments as tensors: the history (`K` steps) or the prompt (`Lp = J*H`).
///
/// # Shapes
/// `states [B, T, ds]`, `actions [B, T, da]`, `returns_to_go [B, T, 1]`, `timesteps [B, T]` (int64),
/// `mask [B, T]` (float, 1 = real step, 0 = left padding).
#[derive(Debug)]
pub struct Segments {
    pub states: Tensor,
    pub actions: Tensor,
    pub returns_to_go: Tensor,
    pub timesteps: Tensor,
    pub mask: Tensor,
}

impl Segments {
    /// Copies host arrays (row-major) to `device`. Lengths must match `[b, t, ds]` etc.
    #[allow(clippy::too_many_arguments)] // a flat host-to-device copy; the fields are named by the caller
    pub fn from_host(
        b: usize,
        t: usize,
        ds: usize,
        da: usize,
        states: &[f32],
        actions: &[f32],
        returns_to_go: &[f32],
        timesteps: &[i64],
        mask: &[f32],
        device: Device,
    ) -> Self {
        let (b, t, ds, da) = (b as i64, t as i64, ds as i64, da as i64);
        let sizes_fit = [
            (states.len(), b * t * ds),
            (actions.len(), b * t * da),
            (returns_to_go.len(), b * t),
            (mask.len(), b * t),
            (timesteps.len(), b * t),
        ]
        .iter()
        .all(|&(len, want)| len as i64 == want);
        // (Sizes that do not fit take the plain path, whose `view` refuses them as before.)
        if device.is_cuda() && sizes_fit {
            // Two uploads (one per dtype) instead of five, neither making the host wait for the
            // stream (`pdt_torch::device::upload`); the fields are views of the float buffer.
            let mut floats =
                Vec::with_capacity(states.len() + actions.len() + returns_to_go.len() + mask.len());
            for v in [states, actions, returns_to_go, mask] {
                floats.extend_from_slice(v);
            }
            let buf = pdt_torch::device::upload(&floats, device);
            let mut at = 0i64;
            let mut take = |shape: &[i64]| {
                let n: i64 = shape.iter().product();
                let v = buf.narrow(0, at, n).view(shape);
                at += n;
                v
            };
            return Self {
                states: take(&[b, t, ds]),
                actions: take(&[b, t, da]),
                returns_to_go: take(&[b, t, 1]),
                mask: take(&[b, t]),
                timesteps: pdt_torch::device::upload(timesteps, device).view([b, t]),
            };
        }
        let f = |v: &[f32], shape: &[i64]| Tensor::from_slice(v).view(shape).to_device(device);
        Self {
            states: f(states, &[b, t, ds]),
            actions: f(actions, &[b, t, da]),
            returns_to_go: f(returns_to_go, &[b, t, 1]),
            timesteps: Tensor::from_slice(timesteps).view([b, t]).to_device(device),
            mask: f(mask, &[b, t]),
        }
    }

    pub fn batch_size(&self) -> i64 {
        self.states.size()[0]
    }

    pub fn len(&self) -> i64 {
        self.states.size()[1]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A second handle on the same tensors (nothing writes to a batch once it is built).
    pub fn shallow_clone(&self) -> Self {
        Self {
            states: self.states.shallow_clone(),
            actions: self.actions.shallow_clone(),
            returns_to_go: self.returns_to_go.shallow_clone(),
            timesteps: self.timesteps.shallow_clone(),
            mask: self.mask.shallow_clone(),
        }
    }
}

/// Embedding layers of one branch (history, or prompt with the `prompt_` prefix).
#[derive(Debug)]
struct Embeddings {
    timestep: nn::Embedding,
    ret: nn::Linear,
    state: nn::Linear,
    action: nn::Linear,
}

/// PyTorch's default `nn.Linear` init: W and b ~ U(-1/sqrt(fan_in), 1/sqrt(fan_in)). The outer layers
/// of the reference keep it (only the GPT-2 trunk is re-initialised).
fn torch_linear(p: nn::Path, n_in: usize, n_out: usize) -> nn::Linear {
    let bound = 1.0 / (n_in as f64).sqrt();
    let init = Init::Uniform { lo: -bound, up: bound };
    nn::linear(
        p,
        n_in as i64,
        n_out as i64,
        nn::LinearConfig { ws_init: init, bs_init: Some(init), bias: true },
    )
}

impl Embeddings {
    fn new(p: &nn::Path, prefix: &str, cfg: &PromptDtConfig) -> Self {
        let h = cfg.hidden_size;
        // PyTorch's default nn.Embedding init is N(0, 1).
        let emb_cfg = nn::EmbeddingConfig {
            ws_init: Init::Randn { mean: 0.0, stdev: 1.0 },
            ..Default::default()
        };
        Self {
            timestep: nn::embedding(
                p / format!("{prefix}embed_timestep"),
                cfg.max_ep_len as i64,
                h as i64,
                emb_cfg,
            ),
            ret: torch_linear(p / format!("{prefix}embed_return"), 1, h),
            state: torch_linear(p / format!("{prefix}embed_state"), cfg.state_dim, h),
            action: torch_linear(p / format!("{prefix}embed_action"), cfg.act_dim, h),
        }
    }

    /// Interleaves (R_t, s_t, a_t) per step. Returns tokens `[B, 3T, H]` and their mask `[B, 3T]`.
    fn tokens(&self, seg: &Segments, hidden: i64) -> (Tensor, Tensor) {
        let (b, t) = (seg.batch_size(), seg.len());
        // The same timestep embedding is added to all three tokens of a step; it is the only
        // position information (no `wpe`).
        let time = self.timestep.forward(&seg.timesteps); // [B, T, H]
        let s = self.state.forward(&seg.states) + &time;
        let a = self.action.forward(&seg.actions) + &time;
        let r = self.ret.forward(&seg.returns_to_go) + &time;
        let tokens = Tensor::stack(&[r, s, a], 1).permute([0, 2, 1, 3]).reshape([b, 3 * t, hidden]); // [B, 3T, H]
        let m = &seg.mask;
        let mask = Tensor::stack(&[m, m, m], 1).permute([0, 2, 1]).reshape([b, 3 * t]); // [B, 3T]
        (tokens, mask)
    }
}

/// A prompt already embedded: the tokens the trunk sees before the history, as
/// [`PromptDt::prompt_tokens`] makes them from segments, or as an adaptation tuned them (soft
/// prompt tuning learns `tokens` directly). With `prompt_tokens(p)` a forward runs the same ops
/// as with `p` itself.
///
/// # Shapes
/// `tokens [P, 3Lp, H]`, `mask [P, 3Lp]` (float, 1 = real token).
#[derive(Debug)]
pub struct PromptTokens {
    pub tokens: Tensor,
    pub mask: Tensor,
}

/// How a prompt is given to [`PromptDt::forward`] and [`PromptDt::prefix`].
#[derive(Debug, Clone, Copy)]
pub enum Prompt<'a> {
    /// Segments, embedded by the prompt's own embeddings (no LayerNorm: reference pitfall 1).
    Segments(&'a Segments),
    /// Already embedded ([`PromptDt::prompt_tokens`], or as an adaptation tuned them).
    Tokens(&'a PromptTokens),
}

impl<'a> From<&'a Segments> for Prompt<'a> {
    fn from(p: &'a Segments) -> Self {
        Prompt::Segments(p)
    }
}

impl<'a> From<&'a PromptTokens> for Prompt<'a> {
    fn from(p: &'a PromptTokens) -> Self {
        Prompt::Tokens(p)
    }
}

/// Which steps' actions a [`Sequence`] forward returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Steps {
    /// The history's, `[B, K, da]`: the reference's output and loss.
    History,
    /// Every step of the sequence, prompt steps first, `[B, Lp+K, da]`: the paper's loss also
    /// supervises the prompt's.
    All,
}

/// A forward pass of every token through every block: training (with dropout), fine-tuning,
/// evaluation-time adaptation and the reference's evaluation.
#[derive(Debug, Clone, Copy)]
pub struct Sequence<'a> {
    /// `None`: no prompt, the reference's `--no-prompt` (MT-ORL / MT-BC).
    pub prompt: Option<Prompt<'a>>,
    /// LoRA adapters on the attention projections; `None` runs the same ops as without LoRA.
    pub lora: Option<&'a LoraAdapters>,
    /// Off (evaluation), drawn at each site (training), or masks drawn beforehand
    /// ([`crate::dropout::DropoutMasks::draw`] for [`PromptDt::token_count`] tokens, the same
    /// bits on the CPU as the ones the forward would draw).
    pub dropout: Dropout<'a>,
    /// What the last block computes; `None`: the model's ([`PromptDt::set_last_block`]).
    pub last_block: Option<LastBlock>,
    pub steps: Steps,
}

impl<'a> Sequence<'a> {
    /// The history's actions with `prompt` given as segments and dropout as `dropout`, the
    /// model's last block, no LoRA.
    pub fn new(prompt: Option<&'a Segments>, dropout: Dropout<'a>) -> Self {
        let prompt = prompt.map(Prompt::Segments);
        Self { prompt, lora: None, dropout, last_block: None, steps: Steps::History }
    }

    /// [`Self::new`] in evaluation mode (no dropout).
    pub fn eval(prompt: Option<&'a Segments>) -> Self {
        Self::new(prompt, Dropout::Off)
    }

    /// [`Self::new`] in training mode (dropout drawn at each site, as the reference).
    pub fn train(prompt: Option<&'a Segments>) -> Self {
        Self::new(prompt, Dropout::Draw)
    }

    /// The same pass, returning every step's actions ([`Steps::All`]).
    pub fn all_steps(self) -> Self {
        Self { steps: Steps::All, ..self }
    }
}

/// The acting path (evaluation mode): the action of the last history step only, `[B, da]`, the
/// prompt's keys and values read from a cache instead of recomputed each step.
#[derive(Debug, Clone, Copy, Default)]
pub struct Act<'a> {
    /// The prompt's cache ([`PromptDt::prefix`], one row per sequence: [`PrefixCache::select`]);
    /// `None`: no prompt.
    pub prompt: Option<&'a PrefixCache>,
    /// LoRA adapters (the cache made with the same ones); `None` runs the same ops as without.
    pub lora: Option<&'a LoraAdapters>,
}

/// What [`PromptDt::forward`] runs. Two kinds rather than one set of options, so that no
/// combination is left undefined: a cached prompt exists only in evaluation mode and yields only
/// the last step's action.
#[derive(Debug, Clone, Copy)]
pub enum Forward<'a> {
    Sequence(Sequence<'a>),
    Act(Act<'a>),
}

impl<'a> From<Sequence<'a>> for Forward<'a> {
    fn from(s: Sequence<'a>) -> Self {
        Forward::Sequence(s)
    }
}

impl<'a> From<Act<'a>> for Forward<'a> {
    fn from(a: Act<'a>) -> Self {
        Forward::Act(a)
    }
}

/// Why a forward pass was refused. (Shapes are checked up front because libtorch would otherwise
/// raise a C++ exception that tch turns into a panic.)
#[derive(Debug, thiserror::Error)]
pub enum ForwardError {
    #[error("input `{name}` has shape {got:?}, expected {expected}")]
    Shape { name: &'static str, got: Vec<i64>, expected: String },
    #[error("input `{name}` has shape {got:?}: {what}")]
    Empty { name: &'static str, got: Vec<i64>, what: &'static str },
    #[error(
        "sequence of {tokens} tokens (3 x ({prompt} prompt + {history} history steps)) exceeds n_positions = {max}"
    )]
    TooLong { tokens: i64, prompt: i64, history: i64, max: i64 },
    #[error("timestep {value} in `{name}` is outside the embedding table [0, {max_ep_len})")]
    Timestep { name: &'static str, value: i64, max_ep_len: i64 },
}

/// The Prompt-DT network. Field names follow the reference `state_dict`.
#[derive(Debug)]
pub struct PromptDt {
    pub cfg: PromptDtConfig,
    history: Embeddings,
    prompt: Embeddings,
    /// Layer norm of the history tokens only. Reference quirk (pitfall 1): prompt tokens skip it.
    embed_ln: nn::LayerNorm,
    transformer: Gpt2,
    /// Unused by the loss and by acting; kept so that weights round-trip with the reference.
    _predict_state: nn::Linear,
    predict_action: nn::Linear,
    /// Unused, kept for the same reason.
    _predict_return: nn::Linear,
    /// What the last block of a full forward computes ([`LastBlock::default_for`] the device).
    last_block: LastBlock,
    /// Forward passes in bf16 autocast (`run.matmul = "bf16"`): the process's setting when the
    /// model was built ([`pdt_torch::autocast::bf16`]), or [`PromptDt::set_bf16`]'s.
    bf16: bool,
}

impl PromptDt {
    /// Builds the model's variables under `p` (normally `vs.root()`), initialised as the reference
    /// does; the caller seeds libtorch's generator first (`tch::manual_seed`) for a reproducible init.
    pub fn new(p: &nn::Path, cfg: &PromptDtConfig) -> Self {
        let h = cfg.hidden_size;
        let ln_cfg = nn::LayerNormConfig { eps: 1e-5, ..Default::default() };
        Self {
            cfg: cfg.clone(),
            history: Embeddings::new(p, "", cfg),
            prompt: Embeddings::new(p, "prompt_", cfg),
            embed_ln: nn::layer_norm(p / "embed_ln", vec![h as i64], ln_cfg),
            transformer: Gpt2::new(p / "transformer", cfg),
            _predict_state: torch_linear(p / "predict_state", h, cfg.state_dim),
            predict_action: torch_linear(p / "predict_action" / 0, h, cfg.act_dim),
            _predict_return: torch_linear(p / "predict_return", h, 1),
            last_block: LastBlock::default_for(p.device()),
            bf16: pdt_torch::autocast::bf16(),
        }
    }

    /// Whether forward passes run in bf16 autocast (by default the process's `run.matmul` when the
    /// model was built). Setting it skips `pdt_torch::device::set_matmul`'s hardware check: the
    /// caller has made it (`pdt_torch::device::bf16_allowed`), as the parity test does.
    pub fn set_bf16(&mut self, on: bool) {
        self.bf16 = on;
    }

    pub fn bf16(&self) -> bool {
        self.bf16
    }

    /// What the last block of a [`Sequence`] forward computes unless it says
    /// ([`Sequence::last_block`]; by default [`LastBlock::default_for`] the device the model was
    /// built on).
    pub fn set_last_block(&mut self, last: LastBlock) {
        self.last_block = last;
    }

    pub fn last_block(&self) -> LastBlock {
        self.last_block
    }

    /// Checks the inputs' shapes, sequence length and timestep range, so that the forward pass
    /// cannot fail inside libtorch.
    pub fn check_inputs(
        &self,
        history: &Segments,
        prompt: Option<&Segments>,
    ) -> Result<(), ForwardError> {
        let (ds, da) = (self.cfg.state_dim as i64, self.cfg.act_dim as i64);
        let b = history.states.size().first().copied().unwrap_or(0);
        let mut prompt_len = 0;
        for (which, seg) in [("history", Some(history)), ("prompt", prompt)] {
            let Some(seg) = seg else { continue };
            let t = seg.states.size().get(1).copied().unwrap_or(0);
            // An empty batch or sequence is named as such: "expected [0, 20, 20]" would read as
            // if a shape of 0 were fine.
            let states = if which == "prompt" { "prompt_states" } else { "states" };
            if b == 0 {
                return Err(ForwardError::Empty {
                    name: states,
                    got: seg.states.size(),
                    what: "the batch size (dimension 0) must be at least 1",
                });
            }
            if t == 0 && seg.states.dim() == 3 {
                return Err(ForwardError::Empty {
                    name: states,
                    got: seg.states.size(),
                    what: "the number of steps (dimension 1) must be at least 1",
                });
            }
            let expect = [
                ("states", &seg.states, vec![b, t, ds]),
                ("actions", &seg.actions, vec![b, t, da]),
                ("returns_to_go", &seg.returns_to_go, vec![b, t, 1]),
                ("timesteps", &seg.timesteps, vec![b, t]),
                ("mask", &seg.mask, vec![b, t]),
            ];
            for (name, tensor, want) in expect {
                if tensor.size() != want || b == 0 || t == 0 {
                    return Err(ForwardError::Shape {
                        name: if which == "prompt" { prompt_name(name) } else { name },
                        got: tensor.size(),
                        expected: format!("{want:?} (batch {b}, {t} steps, non-empty)"),
                    });
                }
            }
            let (lo, hi) =
                (seg.timesteps.min().int64_value(&[]), seg.timesteps.max().int64_value(&[]));
            let max_ep_len = self.cfg.max_ep_len as i64;
            for value in [lo, hi] {
                if !(0..max_ep_len).contains(&value) {
                    let name = if which == "prompt" { "prompt_timesteps" } else { "timesteps" };
                    return Err(ForwardError::Timestep { name, value, max_ep_len });
                }
            }
            if which == "prompt" {
                prompt_len = t;
            }
        }
        let k = history.len();
        let tokens = 3 * (prompt_len + k);
        if tokens > self.cfg.n_positions as i64 {
            return Err(ForwardError::TooLong {
                tokens,
                prompt: prompt_len,
                history: k,
                max: self.cfg.n_positions as i64,
            });
        }
        Ok(())
    }

    /// The model's forward pass: predicted actions, `[B, K, da]`, `[B, Lp+K, da]` or `[B, da]`
    /// as `how` asks ([`Sequence`] for every token through every block, as training, fine-tuning,
    /// adaptation and the reference's evaluation run it; [`Act`] for the acting path over a cached
    /// prompt). The caller must have checked the inputs with [`PromptDt::check_inputs`] (or built
    /// them with the sampler, which guarantees it).
    ///
    /// Deliberate differences from the reference code (`promptdt-reference.md` h.6, h.7): when the
    /// prompt has exactly as many steps as the history, the reference flattens all prompts of the
    /// batch into one row shared by every sample (mixing tasks, and crashing for B > 16); and when
    /// the prompt length is 1, 11, 21, ... it drops the last prompt return-to-go and crashes. Here
    /// every sample always gets its own prompt, whatever the lengths.
    ///
    /// Under `run.matmul = "bf16"` ([`pdt_torch::autocast`]) the pass runs inside libtorch's bf16
    /// autocast, as `torch.autocast` around the reference's forward would, and the actions come back
    /// in float32: the one difference from autocast, which would leave the action head's bf16
    /// output, so the reference's loss (`((a - b)**2).mean()`, not on autocast's float32 list)
    /// would be squared and averaged in bf16. Here the loss, and the actions an agent takes, are
    /// float32 (PyTorch's side of the parity test casts the same way).
    pub fn forward<'a>(&self, history: &Segments, how: impl Into<Forward<'a>>) -> Tensor {
        let how = how.into();
        let out = pdt_torch::autocast::scoped(self.bf16, self.device(), || match how {
            Forward::Sequence(s) => self.sequence(history, &s),
            Forward::Act(a) => self.act(history, &a),
        });
        // (fp32 and tf32: no op added, the bits as before.)
        if out.kind() == Kind::BFloat16 {
            out.to_kind(Kind::Float)
        } else {
            out
        }
    }

    /// [`Forward::Sequence`]: embeddings, `[prompt ; history]` tokens through the trunk, the head
    /// at the state tokens.
    fn sequence(&self, history: &Segments, s: &Sequence<'_>) -> Tensor {
        let hidden = self.cfg.hidden_size as i64;
        let b = history.batch_size();
        let (tokens, mask) = self.history.tokens(history, hidden);
        let tokens = self.embed_ln.forward(&tokens); // [B, 3K, H]
        let (tokens, mask) = match s.prompt {
            None => (tokens, mask),
            Some(Prompt::Segments(p)) => {
                let (p_tokens, p_mask) = self.prompt.tokens(p, hidden); // [B, 3Lp, H], no LayerNorm
                (Tensor::cat(&[p_tokens, tokens], 1), Tensor::cat(&[p_mask, mask], 1))
            }
            Some(Prompt::Tokens(p)) => {
                (Tensor::cat(&[&p.tokens, &tokens], 1), Tensor::cat(&[&p.mask, &mask], 1))
            }
        }; // [B, 3(Lp+K), H]
        let last = s.last_block.unwrap_or(self.last_block);
        let lora = s.lora.map(|a| a.layers.as_slice());
        let x = self.transformer.forward(&tokens, &mask, s.dropout, lora, last);
        let state_hidden = match last {
            LastBlock::AllTokens => {
                // [B, 3(Lp+K), H] -> [B, 3, Lp+K, H]: the hidden state at each state token.
                x.reshape([b, -1, 3, hidden]).permute([0, 2, 1, 3]).select(1, 1)
            }
            LastBlock::StateTokens => x, // [B, Lp+K, H] already
        };
        let actions = self.head(&state_hidden); // [B, Lp+K, da]
        match s.steps {
            Steps::All => actions,
            Steps::History => {
                let (k, steps) = (history.len(), actions.size()[1]);
                actions.narrow(1, steps - k, k) // [B, K, da]
            }
        }
    }

    /// [`Forward::Act`]: the action of the last history step, `[B, da]`, equal to the full
    /// forward's at step `K-1` in eval mode (`tests/it/act.rs`) with less work: the prompt's keys
    /// and values come from the cache (computed once by [`PromptDt::prefix`], one row per sequence
    /// via [`PrefixCache::select`]), the trailing action token is not fed, and the last layer runs
    /// for the last few positions only.
    fn act(&self, history: &Segments, a: &Act<'_>) -> Tensor {
        let hidden = self.cfg.hidden_size as i64;
        let (tokens, mask) = self.history.tokens(history, hidden);
        let tokens = self.embed_ln.forward(&tokens); // [B, 3K, H]
        let n = tokens.size()[1] - 1; // drop the last action token: [B, 3K-1, H]
        let lora = a.lora.map(|l| l.layers.as_slice());
        let (tokens, mask) = (tokens.narrow(1, 0, n), mask.narrow(1, 0, n));
        let tail = self.transformer.forward_last(a.prompt, &tokens, &mask, lora); // [B, R, H]

        // The head on all R rows (a matrix of R*B rows, whose kernel does not depend on B), then
        // the last, the state token of the last step.
        let rows = tail.size()[1];
        self.head(&tail).select(1, rows - 1) // [B, da]
    }

    /// The action head (with the reference's optional tanh).
    fn head(&self, hidden: &Tensor) -> Tensor {
        let actions = self.predict_action.forward(hidden);
        if self.cfg.action_tanh {
            actions.tanh()
        } else {
            actions
        }
    }

    /// The trunk's sequence length for these inputs: 3 tokens per prompt and history step (what
    /// [`crate::dropout::DropoutMasks::draw`] needs for masks drawn beforehand).
    pub fn token_count(history: &Segments, prompt: Option<&Segments>) -> i64 {
        3 * (history.len() + prompt.map_or(0, Segments::len))
    }

    /// The prompt's keys and values at every layer (eval mode, through `lora`'s adapters where
    /// given), once per prompt, for [`Act`]: one row per prompt of `prompt` (`[P, Lp, ...]`). Not
    /// a [`PromptDt::forward`] mode because it returns no actions but the cache the acting path
    /// reads.
    pub fn prefix<'a>(
        &self,
        prompt: impl Into<Prompt<'a>>,
        lora: Option<&LoraAdapters>,
    ) -> PrefixCache {
        let lora = lora.map(|a| a.layers.as_slice());
        let prompt = prompt.into();
        // Under bf16 the cache is computed as the acting pass that reads it is (`Self::forward`).
        pdt_torch::autocast::scoped(self.bf16, self.device(), || match prompt {
            Prompt::Segments(p) => {
                let (tokens, mask) = self.prompt.tokens(p, self.cfg.hidden_size as i64); // [P, 3Lp, H]
                self.transformer.prefix(&tokens, &mask, lora)
            }
            Prompt::Tokens(t) => self.transformer.prefix(&t.tokens, &t.mask, lora),
        })
    }

    /// The device the weights live on.
    pub fn device(&self) -> Device {
        self.predict_action.ws.device()
    }

    /// The prompt's embedded tokens (no LayerNorm, as in the full forward): what
    /// [`Prompt::Tokens`] takes and soft prompt tuning starts from.
    pub fn prompt_tokens(&self, prompt: &Segments) -> PromptTokens {
        let (tokens, mask) = self.prompt.tokens(prompt, self.cfg.hidden_size as i64);
        PromptTokens { tokens, mask }
    }

    /// The reference's loss (`train_step_mix`): mean squared error over the real (unpadded) history
    /// steps and all action dims. Prompt actions are not supervised (reference pitfall 3).
    pub fn action_loss(action_preds: &Tensor, target_actions: &Tensor, mask: &Tensor) -> Tensor {
        let da = action_preds.size().last().copied().unwrap_or(1);
        let keep = mask.reshape([-1]).gt(0.0);
        let pred = action_preds.reshape([-1, da]).index(&[Some(&keep)]);
        let target = target_actions.reshape([-1, da]).index(&[Some(&keep)]);
        (pred - target).pow_tensor_scalar(2).mean(None::<Kind>)
    }
}

/// The prompt inputs' names, as in the `model forward` file format.
fn prompt_name(name: &'static str) -> &'static str {
    match name {
        "states" => "prompt_states",
        "actions" => "prompt_actions",
        "returns_to_go" => "prompt_returns_to_go",
        "timesteps" => "prompt_timesteps",
        _ => "prompt_attention_mask",
    }
}
