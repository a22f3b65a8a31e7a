//! The GPT-2 trunk of the reference (`trajectory_gpt2.py`, a copy of HF transformers 4.5.1's GPT-2
//! with the position embedding `wpe` removed). Pre-LN blocks, single-head causal attention, ReLU MLP.
//!
//! Every op mirrors the reference's, in the same order, so that results (and gradients) are
//! bit-identical to PyTorch on CPU: `addmm` for Conv1D, `where(causal, w, -1e4)` then `+ mask`,
//! `softmax`, `at::dropout`.

use crate::config::PromptDtConfig;
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
    fn forward(&self, x: &Tensor, masks: &Masks<'_>, train: bool) -> Tensor {
        let (b, l) = (x.size()[0], x.size()[1]);
        let hd = self.hidden / self.n_head;
        let qkv = self.c_attn.forward(x).split(self.hidden, 2); // 3 x [B, L, H]
        let q = qkv[0].view([b, l, self.n_head, hd]).permute([0, 2, 1, 3]); // [B, nh, L, hd]
        let k = qkv[1].view([b, l, self.n_head, hd]).permute([0, 2, 3, 1]); // [B, nh, hd, L]
        let v = qkv[2].view([b, l, self.n_head, hd]).permute([0, 2, 1, 3]); // [B, nh, L, hd]
        let w = q.matmul(&k) / (hd as f64).powf(0.5); // [B, nh, L, L]
                                                      // Reference quirk (HF 4.5.1): masked scores are *replaced* by -1e4 (not -inf), then the
                                                      // padding bias is *added*; a fully padded row therefore still softmaxes to finite values.
        let w = w.where_self(masks.causal, masks.masked_bias) + masks.pad_bias;
        let w = w.softmax(-1, None::<Kind>).dropout(self.attn_pdrop, train);
        let a = w.matmul(&v); // [B, nh, L, hd]
        let a = a.permute([0, 2, 1, 3]).contiguous().view([b, l, self.hidden]); // [B, L, H]
        self.c_proj.forward(&a).dropout(self.resid_pdrop, train)
    }
}

#[derive(Debug)]
struct Mlp {
    c_fc: Conv1D,
    c_proj: Conv1D,
    resid_pdrop: f64,
}

impl Mlp {
    fn forward(&self, x: &Tensor, train: bool) -> Tensor {
        self.c_proj.forward(&self.c_fc.forward(x).relu()).dropout(self.resid_pdrop, train)
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

    fn forward(&self, x: &Tensor, masks: &Masks<'_>, train: bool) -> Tensor {
        let h = x + self.attn.forward(&self.ln_1.forward(x), masks, train);
        &h + self.mlp.forward(&self.ln_2.forward(&h), train)
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

    /// # Shapes
    /// `inputs_embeds`: `[B, L, H]`; `token_mask`: `[B, L]` (1 = real token, 0 = padding), float.
    /// Returns `[B, L, H]`.
    pub fn forward(&self, inputs_embeds: &Tensor, token_mask: &Tensor, train: bool) -> Tensor {
        let l = inputs_embeds.size()[1];
        debug_assert!(l <= self.n_positions, "caller checks the sequence length");
        // As the reference, the causal mask is the top-left L x L slice of the persistent buffer.
        let causal = self.causal.narrow(0, 0, l).narrow(1, 0, l).contiguous().view([1, 1, l, l]);
        // [B, 1, 1, L]: 0 for real tokens, -1e4 for padding (HF's extended attention mask).
        let pad_bias = (1.0 - token_mask.unsqueeze(1).unsqueeze(1)) * -10000.0;
        let masks = Masks { causal: &causal, masked_bias: &self.masked_bias, pad_bias: &pad_bias };
        let mut x = inputs_embeds.dropout(self.embd_pdrop, train);
        for block in &self.h {
            x = block.forward(&x, &masks, train);
        }
        self.ln_f.forward(&x)
    }
}
