//! The GPT-2 trunk of the reference (`trajectory_gpt2.py`, a copy of HF transformers 4.5.1's GPT-2
//! with the position embedding `wpe` removed). Pre-LN blocks, single-head causal attention, ReLU MLP.
//!
//! Every op mirrors the reference's, in the same order, so that results (and gradients) are
//! bit-identical to PyTorch on CPU: `addmm` for Conv1D, `where(causal, w, -1e4)` then `+ mask`,
//! `softmax`, `at::dropout`.

use crate::config::PromptDtConfig;
use crate::dropout::{At, Dropout};
use crate::lora::{LoraLayer, LoraPair};
use crate::tokens::state_rows;
use tch::nn::{self, Init, Module};
use tch::{Kind, Tensor};

/// HF's `Conv1D`: a linear layer whose weight is stored `(in, out)`, computing `x @ W + b`.
/// Kept (instead of `nn::Linear`) so the weights have the reference layout and name.
#[derive(Debug)]
pub struct Conv1D {
    pub weight: Tensor,
    pub bias: Tensor,
    n_out: i64,
}

impl Conv1D {
    fn new(p: nn::Path, n_in: usize, n_out: usize) -> Self {
        let (n_in, n_out) = (n_in as i64, n_out as i64);
        // GPT2PreTrainedModel._init_weights: weights N(0, 0.02), biases 0.
        let weight = p.var("weight", &[n_in, n_out], Init::Randn { mean: 0.0, stdev: 0.02 });
        let bias = p.var("bias", &[n_out], Init::Const(0.0));
        Self { weight, bias, n_out }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let mut size_out = x.size();
        let n_in = size_out.pop().unwrap_or(0);
        size_out.push(self.n_out);
        self.bias.addmm(&x.view([-1, n_in]), &self.weight).view(size_out.as_slice())
    }

    /// [`Self::forward`] plus a LoRA delta when one is given. Without one it is exactly
    /// [`Self::forward`] (the same ops), so the default path keeps its bits.
    fn forward_lora(&self, x: &Tensor, lora: Option<&LoraPair>) -> Tensor {
        let y = self.forward(x);
        match lora {
            None => y,
            Some(l) => y + l.delta(x),
        }
    }
}

fn layer_norm(p: nn::Path, h: usize, eps: f64) -> nn::LayerNorm {
    let cfg = nn::LayerNormConfig { eps, ..Default::default() };
    nn::layer_norm(p, vec![h as i64], cfg)
}

#[derive(Debug)]
struct Attention {
    c_attn: Conv1D,
    c_proj: Conv1D,
    n_head: i64,
    hidden: i64,
    attn_pdrop: f64,
    resid_pdrop: f64,
}

impl Attention {
    /// # Shapes
    /// `x`: `[B, L, H]`; `causal`: bool `[1, 1, L, L]`; `pad_bias`: `[B, 1, 1, L]` (0 keep, -1e4 pad).
    /// Queries of the last `rows` positions `[B, nh, rows, hd]`, keys `[B, nh, hd, L]` and values
    /// `[B, nh, L, hd]` of `x` (`[B, L, H]`, after `ln_1`).
    fn qkv(&self, x: &Tensor, rows: i64, lora: Option<&LoraLayer>) -> (Tensor, Tensor, Tensor) {
        let (b, l) = (x.size()[0], x.size()[1]);
        let hd = self.hidden / self.n_head;
        let qkv = self.c_attn.forward_lora(x, lora.map(|l| &l.c_attn)).split(self.hidden, 2); // 3 x [B, L, H]

        // All rows (training, full forward): no narrow. A narrow of the whole length is a no-op
        // view forward, but its backward allocates a zeroed `[B, L, H]` and copies the gradient
        // into it, at every layer of every training step (the reference has no such op).
        let q = if rows == l { qkv[0].shallow_clone() } else { qkv[0].narrow(1, l - rows, rows) };
        let q = q.view([b, rows, self.n_head, hd]);
        let k = qkv[1].view([b, l, self.n_head, hd]).permute([0, 2, 3, 1]);
        let v = qkv[2].view([b, l, self.n_head, hd]).permute([0, 2, 1, 3]);
        (q.permute([0, 2, 1, 3]), k, v)
    }

    /// `states`: the queries of the state tokens only ([`LastBlock::StateTokens`]), `[B, L/3, H]`
    /// out, `masks.causal` holding their rows (`[1, 1, L/3, L]`); otherwise every position's (the
    /// reference's ops, none added).
    fn forward(
        &self,
        x: &Tensor,
        masks: &Masks<'_>,
        drop: &Dropout<'_>,
        layer: usize,
        lora: Option<&LoraLayer>,
        states: bool,
    ) -> Tensor {
        let (b, l) = (x.size()[0], x.size()[1]);
        let hd = self.hidden / self.n_head;
        let (q, k, v) = self.qkv(x, l, lora); // [B, nh, L, hd], [B, nh, hd, L], [B, nh, L, hd]
        let q = if states { state_rows(&q) } else { q }; // [B, nh, R, hd]: R = L/3 or L
        let rows = q.size()[2];
        let w = q.matmul(&k) / (hd as f64).powf(0.5); // [B, nh, R, L]

        // Reference quirk (HF 4.5.1): masked scores are *replaced* by -1e4 (not -inf), then the
        // padding bias is *added*; a fully padded row therefore still softmaxes to finite values.
        let w = w.where_self(masks.causal, masks.masked_bias) + masks.pad_bias;
        let w = drop.apply_rows(
            w.softmax(-1, None::<Kind>),
            self.attn_pdrop,
            At::Layer(layer, 0),
            states,
        );
        let a = w.matmul(&v); // [B, nh, R, hd]
        let a = a.permute([0, 2, 1, 3]).contiguous().view([b, rows, self.hidden]); // [B, R, H]
        let proj = lora.and_then(|l| l.c_proj.as_ref());
        let y = self.c_proj.forward_lora(&a, proj);
        drop.apply_rows(y, self.resid_pdrop, At::Layer(layer, 1), states)
    }

    /// Keys `[B, nh, hd, L]` and values `[B, nh, L, hd]` of `x` (`[B, L, H]`, after `ln_1`).
    fn keys_values(&self, x: &Tensor, lora: Option<&LoraLayer>) -> (Tensor, Tensor) {
        let (_, k, v) = self.qkv(x, 0, lora);
        (k, v)
    }

    /// Eval-mode attention of `x` (`[B, L, H]`, after `ln_1`) over a cached prefix and itself,
    /// for the query rows `rows` (the last `rows` positions). The same ops as [`Self::forward`],
    /// on a prefix of keys and values computed earlier.
    ///
    /// # Shapes
    /// `prefix`: keys `[B, nh, hd, P]`, values `[B, nh, P, hd]`; `causal`: bool `[1, 1, rows, P+L]`;
    /// `pad_bias`: `[B, 1, 1, P+L]`. Returns `[B, rows, H]`.
    #[allow(clippy::too_many_arguments)] // the masks and rows of one cached pass, from one caller
    fn forward_cached(
        &self,
        x: &Tensor,
        prefix: Option<&LayerCache>,
        causal: &Tensor,
        masked_bias: &Tensor,
        pad_bias: &Tensor,
        rows: i64,
        lora: Option<&LoraLayer>,
    ) -> Tensor {
        let b = x.size()[0];
        let hd = self.hidden / self.n_head;
        let (q, k, v) = self.qkv(x, rows, lora); // [B, nh, rows, hd], [B, nh, hd, L], [B, nh, L, hd]
        let (k, v) = match prefix {
            Some(c) => (Tensor::cat(&[&c.keys, &k], 3), Tensor::cat(&[&c.values, &v], 2)), // P+L
            None => (k, v),
        };
        let w = q.matmul(&k) / (hd as f64).powf(0.5); // [B, nh, rows, P+L]
        let w = w.where_self(causal, masked_bias) + pad_bias;
        let a = w.softmax(-1, None::<Kind>).matmul(&v); // [B, nh, rows, hd]
        let a = a.permute([0, 2, 1, 3]).contiguous().view([b, rows, self.hidden]); // [B, rows, H]
        self.c_proj.forward_lora(&a, lora.and_then(|l| l.c_proj.as_ref()))
    }
}

#[derive(Debug)]
struct Mlp {
    c_fc: Conv1D,
    c_proj: Conv1D,
    resid_pdrop: f64,
}

impl Mlp {
    /// `states`: `x` holds the state tokens' rows of the block (its dropout mask read there).
    fn forward(&self, x: &Tensor, drop: &Dropout<'_>, layer: usize, states: bool) -> Tensor {
        let y = self.c_proj.forward(&self.c_fc.forward(x).relu());
        drop.apply_rows(y, self.resid_pdrop, At::Layer(layer, 2), states)
    }
}

#[derive(Debug)]
struct Block {
    ln_1: nn::LayerNorm,
    attn: Attention,
    ln_2: nn::LayerNorm,
    mlp: Mlp,
}

impl Block {
    fn new(p: nn::Path, cfg: &PromptDtConfig) -> Self {
        let h = cfg.hidden_size;
        let attn_p = &p / "attn";
        let mlp_p = &p / "mlp";
        Self {
            ln_1: layer_norm(&p / "ln_1", h, cfg.layer_norm_epsilon),
            attn: Attention {
                c_attn: Conv1D::new(&attn_p / "c_attn", h, 3 * h),
                c_proj: Conv1D::new(&attn_p / "c_proj", h, h),
                n_head: cfg.n_head as i64,
                hidden: h as i64,
                attn_pdrop: cfg.attn_pdrop,
                resid_pdrop: cfg.resid_pdrop,
            },
            ln_2: layer_norm(&p / "ln_2", h, cfg.layer_norm_epsilon),
            mlp: Mlp {
                c_fc: Conv1D::new(&mlp_p / "c_fc", h, cfg.n_inner),
                c_proj: Conv1D::new(&mlp_p / "c_proj", cfg.n_inner, h),
                resid_pdrop: cfg.resid_pdrop,
            },
        }
    }

    /// `states`: the outputs at the state tokens only, `[B, L/3, H]` from `x` `[B, L, H]`, each
    /// row the full block's output at its position (keys and values still from every position).
    fn forward(
        &self,
        x: &Tensor,
        masks: &Masks<'_>,
        drop: &Dropout<'_>,
        layer: usize,
        lora: Option<&LoraLayer>,
        states: bool,
    ) -> Tensor {
        let a = self.attn.forward(&self.ln_1.forward(x), masks, drop, layer, lora, states);
        let h = if states { state_rows(x) + a } else { x + a }; // [B, R, H]
        &h + self.mlp.forward(&self.ln_2.forward(&h), drop, layer, states)
    }

    /// Eval mode, over a cached prefix, for the last `rows` positions of `x` (`[B, L, H]`):
    /// returns `[B, rows, H]`. Keys and values still come from every position of `x`.
    #[allow(clippy::too_many_arguments)] // the masks and rows of one cached pass, from one caller
    fn forward_cached(
        &self,
        x: &Tensor,
        prefix: Option<&LayerCache>,
        causal: &Tensor,
        masked_bias: &Tensor,
        pad_bias: &Tensor,
        rows: i64,
        lora: Option<&LoraLayer>,
    ) -> Tensor {
        let l = x.size()[1];
        let a = self.attn.forward_cached(
            &self.ln_1.forward(x),
            prefix,
            causal,
            masked_bias,
            pad_bias,
            rows,
            lora,
        );
        let h = x.narrow(1, l - rows, rows) + a; // [B, rows, H]
        &h + self.mlp.forward(&self.ln_2.forward(&h), &Dropout::Off, 0, false)
    }
}

/// Positions the last layer of [`Gpt2::forward_last`] runs for (see there).
pub const LAST_ROWS: i64 = 8;

/// Which positions the last block of a full forward pass computes outputs for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LastBlock {
    /// Every position: the reference's ops, on the CPU bit for bit PyTorch's.
    AllTokens,
    /// The state tokens only (positions 1, 4, 7, ... of Prompt-DT's `(R, s, a)` interleaving), the
    /// only outputs its action head reads. Nothing after the last block mixes positions, so these
    /// are the same values in exact arithmetic, for a third of the last block's queries,
    /// attention output and MLP rows (its keys and values still come from every position).
    /// Differs from the reference code, which runs the block on every token; not bit for bit
    /// `AllTokens` (BLAS sums a product of fewer rows in its own order).
    StateTokens,
}

impl LastBlock {
    /// `StateTokens` on CUDA (no path there is bitwise, and the step is bound by arithmetic at
    /// large batches), `AllTokens` elsewhere (the CPU's parity with PyTorch).
    pub fn default_for(device: tch::Device) -> Self {
        if device.is_cuda() {
            LastBlock::StateTokens
        } else {
            LastBlock::AllTokens
        }
    }
}

/// The keys and values of a prefix at one layer.
#[derive(Debug)]
pub struct LayerCache {
    /// `[B, nh, hd, P]`
    keys: Tensor,
    /// `[B, nh, P, hd]`
    values: Tensor,
}

/// The keys and values of a prefix (the prompt) at every layer, and its padding bias. Attention is
/// causal and the prefix comes first, so these do not depend on what follows: a prompted policy
/// computes them once per prompt instead of once per step (`Gpt2::prefix`).
#[derive(Debug)]
pub struct PrefixCache {
    layers: Vec<LayerCache>,
    /// `[B, 1, 1, P]`: 0 for real tokens, -1e4 for padding.
    pad_bias: Tensor,
}

impl PrefixCache {
    /// Number of prefixes (rows).
    pub fn rows(&self) -> i64 {
        self.pad_bias.size()[0]
    }

    /// Number of prefix tokens.
    pub fn len(&self) -> i64 {
        self.pad_bias.size()[3]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Stacks caches of prefixes of the same length, rows in order (`None` if any length differs).
    pub fn cat(caches: &[&PrefixCache]) -> Option<PrefixCache> {
        let first = caches.first()?;
        if caches.iter().any(|c| c.len() != first.len() || c.layers.len() != first.layers.len()) {
            return None;
        }
        let layers = (0..first.layers.len())
            .map(|i| LayerCache {
                keys: Tensor::cat(&caches.iter().map(|c| &c.layers[i].keys).collect::<Vec<_>>(), 0),
                values: Tensor::cat(
                    &caches.iter().map(|c| &c.layers[i].values).collect::<Vec<_>>(),
                    0,
                ),
            })
            .collect();
        let pad_bias = Tensor::cat(&caches.iter().map(|c| &c.pad_bias).collect::<Vec<_>>(), 0);
        Some(PrefixCache { layers, pad_bias })
    }

    /// The prefixes of `index` (`[B]` int64 rows into this cache): one per sequence of a batch.
    pub fn select(&self, index: &Tensor) -> PrefixCache {
        PrefixCache {
            layers: self
                .layers
                .iter()
                .map(|c| LayerCache {
                    keys: c.keys.index_select(0, index),
                    values: c.values.index_select(0, index),
                })
                .collect(),
            pad_bias: self.pad_bias.index_select(0, index),
        }
    }
}

/// The masks every attention layer of one forward pass uses.
struct Masks<'a> {
    /// bool `[1, 1, L, L]`, lower triangular.
    causal: &'a Tensor,
    /// 0-d float -1e4: the value masked scores are replaced with.
    masked_bias: &'a Tensor,
    /// `[B, 1, 1, L]`: 0 for real tokens, -1e4 for padding.
    pad_bias: &'a Tensor,
}

/// The trunk: `drop -> h.0 .. h.{n-1} -> ln_f`, fed with embeddings (no token or position lookup).
#[derive(Debug)]
pub struct Gpt2 {
    /// `transformer.wte`: the reference keeps GPT-2's token embedding (vocab 1). It is never used, but
    /// it is a parameter (it counts, it is in the state_dict, and AdamW sees it).
    _wte: Tensor,
    h: Vec<Block>,
    ln_f: nn::LayerNorm,
    embd_pdrop: f64,
    n_positions: i64,
    /// tril(ones(n_positions, n_positions)) as bool, built once (the reference's `attn.bias` buffer).
    causal: Tensor,
    /// The reference's `attn.masked_bias` buffer, built once.
    masked_bias: Tensor,
}

impl Gpt2 {
    pub fn new(p: nn::Path, cfg: &PromptDtConfig) -> Self {
        let hidden = cfg.hidden_size as i64;
        let wte = (&p / "wte").var("weight", &[1, hidden], Init::Randn { mean: 0.0, stdev: 0.02 });
        let h = (0..cfg.n_layer).map(|i| Block::new(&p / "h" / i, cfg)).collect();
        Self {
            _wte: wte,
            h,
            ln_f: layer_norm(&p / "ln_f", cfg.hidden_size, cfg.layer_norm_epsilon),
            embd_pdrop: cfg.embd_pdrop,
            n_positions: cfg.n_positions as i64,
            causal: Tensor::ones([cfg.n_positions as i64; 2], (Kind::Bool, p.device())).tril(0),
            masked_bias: Tensor::from(-1e4f32).to_device(p.device()),
        }
    }

    /// The whole sequence through every block, with `drop`'s dropout and LoRA adapters where
    /// given (one per layer; none runs the same ops as without LoRA). With `last` as
    /// [`LastBlock::StateTokens`] the last block computes the state tokens only.
    ///
    /// # Shapes
    /// `inputs_embeds`: `[B, L, H]`; `token_mask`: `[B, L]` (1 = real token, 0 = padding), float.
    /// Returns `[B, L, H]`, or `[B, L/3, H]` for [`LastBlock::StateTokens`] (`L` a multiple of 3).
    pub fn forward(
        &self,
        inputs_embeds: &Tensor,
        token_mask: &Tensor,
        drop: Dropout<'_>,
        lora: Option<&[LoraLayer]>,
        last: LastBlock,
    ) -> Tensor {
        let l = inputs_embeds.size()[1];
        debug_assert!(l <= self.n_positions, "caller checks the sequence length");
        // As the reference, the causal mask is the top-left L x L slice of the persistent buffer.
        let causal = self.causal.narrow(0, 0, l).narrow(1, 0, l).contiguous().view([1, 1, l, l]);
        // [B, 1, 1, L]: 0 for real tokens, -1e4 for padding (HF's extended attention mask).
        let pad_bias = (1.0 - token_mask.unsqueeze(1).unsqueeze(1)) * -10000.0;
        let masks = Masks { causal: &causal, masked_bias: &self.masked_bias, pad_bias: &pad_bias };
        let mut x = drop.apply(inputs_embeds.shallow_clone(), self.embd_pdrop, At::Embeddings);
        let n = self.h.len();
        for (i, block) in self.h.iter().enumerate() {
            let adapter = lora.and_then(|a| a.get(i));
            x = if i + 1 == n && last == LastBlock::StateTokens {
                let causal = state_rows(&causal); // [1, 1, L/3, L]
                let rows = Masks { causal: &causal, ..masks };
                block.forward(&x, &rows, &drop, i, adapter, true) // [B, L/3, H]
            } else {
                block.forward(&x, &masks, &drop, i, adapter, false)
            };
        }
        self.ln_f.forward(&x)
    }

    /// The keys and values of a prefix at every layer (eval mode, through LoRA adapters where
    /// given), for [`Self::forward_last`].
    ///
    /// # Shapes
    /// `embeds`: `[P, Lp, H]`; `token_mask`: `[P, Lp]` float (1 real, 0 padding).
    pub fn prefix(
        &self,
        embeds: &Tensor,
        token_mask: &Tensor,
        lora: Option<&[LoraLayer]>,
    ) -> PrefixCache {
        let l = embeds.size()[1];
        let causal = self.causal.narrow(0, 0, l).narrow(1, 0, l).contiguous().view([1, 1, l, l]);
        let pad_bias = (1.0 - token_mask.unsqueeze(1).unsqueeze(1)) * -10000.0; // [P, 1, 1, Lp]
        let masks = Masks { causal: &causal, masked_bias: &self.masked_bias, pad_bias: &pad_bias };
        let mut layers = Vec::with_capacity(self.h.len());
        let mut x = embeds.shallow_clone();
        for (i, block) in self.h.iter().enumerate() {
            let adapter = lora.and_then(|a| a.get(i));
            let (keys, values) = block.attn.keys_values(&block.ln_1.forward(&x), adapter);
            layers.push(LayerCache { keys, values });
            x = block.forward(&x, &masks, &Dropout::Off, 0, adapter, false);
        }
        PrefixCache { layers, pad_bias }
    }

    /// Eval mode: the outputs at the last (at most [`LAST_ROWS`]) positions of `[prefix ‖ embeds]`,
    /// with the prefix's keys and values taken from `prefix` (one row per sequence, see
    /// [`PrefixCache::select`]), through LoRA adapters where given (one per layer).
    /// Every layer but the last runs on all positions of `embeds` (their keys and values are
    /// needed); the last runs attention and MLP for the last position only.
    ///
    /// # Shapes
    /// `embeds`: `[B, L, H]`; `token_mask`: `[B, L]`. Returns `[B, min(L, LAST_ROWS), H]`.
    pub fn forward_last(
        &self,
        prefix: Option<&PrefixCache>,
        embeds: &Tensor,
        token_mask: &Tensor,
        lora: Option<&[LoraLayer]>,
    ) -> Tensor {
        let l = embeds.size()[1];
        let p = prefix.map_or(0, PrefixCache::len);
        let total = p + l;
        debug_assert!(total <= self.n_positions, "caller checks the sequence length");
        let pad = (1.0 - token_mask.unsqueeze(1).unsqueeze(1)) * -10000.0; // [B, 1, 1, L]
        let pad_bias = match prefix {
            Some(c) => Tensor::cat(&[&c.pad_bias, &pad], 3), // [B, 1, 1, P+L]
            None => pad,
        };
        // Rows P..P+L of the causal mask of the whole sequence.
        let rows_of = |rows: i64| {
            self.causal
                .narrow(0, total - rows, rows)
                .narrow(1, 0, total)
                .contiguous()
                .view([1, 1, rows, total])
        };
        // The last layer runs for the last LAST_ROWS positions, not one: BLAS picks its kernels by
        // matrix size, and with one or two rows per sequence an episode alone (a 1- or 2-row
        // product) got other bits than the same episode batched with others. Measured on AVX2:
        // 2 or 3 rows differ, 4 and more are batch-invariant (`tests/it/act.rs`); 8 leaves margin.
        let tail = l.min(LAST_ROWS);
        let (all, last) = (rows_of(l), rows_of(tail));
        let mut x = embeds.shallow_clone();
        let n = self.h.len();
        for (i, block) in self.h.iter().enumerate() {
            let cache = prefix.map(|c| &c.layers[i]);
            let adapter = lora.and_then(|a| a.get(i));
            x = if i + 1 < n {
                block.forward_cached(&x, cache, &all, &self.masked_bias, &pad_bias, l, adapter)
            } else {
                block.forward_cached(&x, cache, &last, &self.masked_bias, &pad_bias, tail, adapter)
            };
        }
        self.ln_f.forward(&x) // [B, tail, H]
    }
}
