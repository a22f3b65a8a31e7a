//! The dropout of a training forward pass, in one place: its sites in the solo forward's order, and
//! its masks drawn from libtorch's generator exactly as `at::dropout` draws them on the CPU.
//!
//! A forward either draws its own masks (`at::dropout` at each site, as the reference does) or is
//! given them, drawn beforehand by [`DropoutMasks::draw`]. On the CPU the two are the same bits:
//! `at::dropout` (no fused kernel on the CPU) is `noise = empty_like(x).bernoulli_(1 - p);
//! noise.div_(1 - p); x * noise`, and [`draw_noise`] is that noise. Masks drawn beforehand are
//! drawn apart from the forward that uses them; the batched model of a pack (`pdt_pack::model`)
//! draws its per-run masks with the same sites and noise.

use crate::config::PromptDtConfig;
use tch::{Device, Kind, Tensor};

/// One dropout site of the trunk.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DropoutSite {
    /// The drop probability (`at::dropout` draws nothing at 0).
    pub p: f64,
    /// The attention weights (`[B, nh, L, L]`); otherwise a hidden state (`[B, L, H]`).
    pub attention: bool,
}

/// The trunk's dropout sites in the order the solo forward meets them: the embeddings, then per
/// layer the attention weights, the attention output and the MLP output.
pub fn dropout_sites(cfg: &PromptDtConfig) -> Vec<DropoutSite> {
    let hidden = |p| DropoutSite { p, attention: false };
    let mut sites = vec![hidden(cfg.embd_pdrop)];
    for _ in 0..cfg.n_layer {
        sites.extend([
            DropoutSite { p: cfg.attn_pdrop, attention: true },
            hidden(cfg.resid_pdrop),
            hidden(cfg.resid_pdrop),
        ]);
    }
    sites
}

/// Fills `noise` (contiguous, float) with `at::dropout`'s noise for probability `p` on the CPU:
/// `bernoulli_(1 - p)` then `div_(1 - p)`, drawn from libtorch's generator in memory order, so a
/// contiguous tensor (or contiguous rows of one) gets what a fresh tensor of its shape gets.
pub fn draw_noise(noise: &mut Tensor, p: f64) {
    pdt_torch::bernoulli::bernoulli_(noise, 1.0 - p);
    let _ = noise.g_div_scalar_(1.0 - p);
}

/// `at::dropout(x, p, train = true)` on the CPU: `x * noise` with [`draw_noise`]'s noise, the ops
/// and bits of libtorch's (whose noise is `empty_like(x)`, so `x`'s memory order: a contiguous `x`
/// only; any other goes to `at::dropout`, as does a tensor elsewhere than on the CPU).
fn dropout_cpu(x: Tensor, p: f64) -> Tensor {
    if x.device() != Device::Cpu
        || x.kind() != Kind::Float
        || !x.is_contiguous()
        || p <= 0.0
        || p >= 1.0
        || x.numel() == 0
    {
        return x.dropout(p, true);
    }
    let mut noise = Tensor::empty(x.size().as_slice(), (Kind::Float, Device::Cpu));
    draw_noise(&mut noise, p);
    x * noise
}

/// The masks of one training forward pass (`None` at a site with `p = 0`, where `at::dropout`
/// draws nothing and returns its input).
#[derive(Debug)]
pub struct DropoutMasks {
    /// The embeddings `[B, L, H]`.
    pub embd: Option<Tensor>,
    /// Per layer: attention weights `[B, nh, L, L]`, attention output and MLP output `[B, L, H]`.
    pub layers: Vec<[Option<Tensor>; 3]>,
}

impl DropoutMasks {
    /// The mask of site `at` (`None`: no dropout there).
    fn at(&self, at: At) -> Option<&Tensor> {
        match at {
            At::Embeddings => self.embd.as_ref(),
            At::Layer(i, j) => self.layers.get(i).and_then(|l| l[j].as_ref()),
        }
    }

    /// The masks in the order of [`dropout_sites`] (one per site), grouped per layer.
    pub fn from_sites(sites: Vec<Option<Tensor>>) -> Self {
        let mut it = sites.into_iter();
        let embd = it.next().flatten();
        let mut layers = Vec::new();
        while let Some(attn) = it.next() {
            layers.push([attn, it.next().flatten(), it.next().flatten()]);
        }
        Self { embd, layers }
    }

    /// Draws the masks a training forward of `batch` sequences of `len` tokens would draw at its
    /// sites, from libtorch's generator as it stands (the caller seeds it, and holds whatever lock
    /// keeps other threads from drawing meanwhile).
    pub fn draw(cfg: &PromptDtConfig, batch: i64, len: i64, device: Device) -> Self {
        let (h, nh) = (cfg.hidden_size as i64, cfg.n_head as i64);
        let sites = dropout_sites(cfg)
            .into_iter()
            .map(|site| {
                (site.p > 0.0).then(|| {
                    let shape: &[i64] =
                        if site.attention { &[batch, nh, len, len] } else { &[batch, len, h] };
                    let mut noise = Tensor::empty(shape, (Kind::Float, device));
                    draw_noise(&mut noise, site.p);
                    noise
                })
            })
            .collect();
        Self::from_sites(sites)
    }
}

/// How a forward pass applies dropout.
#[derive(Debug, Clone, Copy)]
pub enum Dropout<'a> {
    /// Evaluation: none.
    Off,
    /// Training, the masks drawn at each site (`at::dropout`, the reference's op).
    Draw,
    /// Training with these masks (drawn beforehand by [`DropoutMasks::draw`] for this batch and
    /// sequence length).
    Given(&'a DropoutMasks),
}

/// Where in the trunk a dropout is applied.
#[derive(Debug, Clone, Copy)]
pub(crate) enum At {
    Embeddings,
    /// Layer `i`'s attention weights (0), attention output (1) or MLP output (2).
    Layer(usize, usize),
}

impl Dropout<'_> {
    /// `train`: [`Dropout::Draw`], else [`Dropout::Off`].
    pub fn train(train: bool) -> Self {
        if train {
            Dropout::Draw
        } else {
            Dropout::Off
        }
    }

    /// `x` after the dropout of probability `p` at site `at`.
    pub(crate) fn apply(&self, x: Tensor, p: f64, at: At) -> Tensor {
        match self {
            Dropout::Off => x,
            Dropout::Draw => dropout_cpu(x, p),
            Dropout::Given(m) => match m.at(at) {
                // `at::dropout` returns `input * noise`.
                Some(mask) => x * mask,
                None => x,
            },
        }
    }

    /// [`Self::apply_states`] when `states`, else [`Self::apply`].
    pub(crate) fn apply_rows(&self, x: Tensor, p: f64, at: At, states: bool) -> Tensor {
        if states {
            self.apply_states(x, p, at)
        } else {
            self.apply(x, p, at)
        }
    }

    /// [`Self::apply`] to the state tokens' rows of a site (`crate::gpt2::LastBlock::StateTokens`):
    /// `x` is `[..., L/3, D]` where the full forward's site is `[..., L, D]`. Given masks are read
    /// at those rows. Drawn ones, on the CPU, are drawn at the full site's shape as `at::dropout`
    /// draws them and read there too, so each row gets the full forward's mask and the generator
    /// ends where the full forward leaves it. On CUDA (whose fused dropout kernel no draw of ours
    /// reproduces anyway) they are drawn at the smaller shape.
    pub(crate) fn apply_states(&self, x: Tensor, p: f64, at: At) -> Tensor {
        match self {
            Dropout::Given(m) => match m.at(at) {
                Some(mask) => x * crate::tokens::state_rows(mask),
                None => x,
            },
            // `at::dropout` draws nothing at p = 0.
            Dropout::Draw if p > 0.0 && !x.device().is_cuda() => {
                let mut full = x.size();
                let d = full.len().saturating_sub(2);
                if let Some(rows) = full.get_mut(d) {
                    *rows *= 3;
                }
                let mut noise = Tensor::empty(full.as_slice(), (x.kind(), x.device()));
                draw_noise(&mut noise, p);
                x * crate::tokens::state_rows(&noise)
            }
            _ => self.apply(x, p, at),
        }
    }
}
