//! The pack's weights and its forward pass: the solo model's ops (`prompt_dt.rs`, `gpt2.rs`) in the
//! same order, with a run dimension in front of every weight.

use super::{parameter_shapes, BlockIdx, EmbIdx, Idx, PackedBatch, PackedError};
use pdt_model::dropout::{draw_noise, dropout_sites, DropoutMasks, DropoutSite};
use pdt_model::tokens::state_rows;
use pdt_model::{LastBlock, PromptDtConfig, Segments};
use tch::{Device, Kind, Tensor};

/// How a pack computes its LayerNorms (each run has its own weight and bias).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LayerNormPlan {
    /// libtorch's fused LayerNorm once per run: the solo kernel's bits, and on the CPU faster than
    /// one normalisation followed by a broadcast affine (which adds passes over the activations,
    /// forward and backward). About 20 operators per LayerNorm and run, forward and backward.
    PerRun,
    /// One normalisation for the pack, then each run's affine: a fixed number of kernels whatever
    /// the pack's size, which is what counts on a GPU, where each costs a launch.
    Batched,
}

impl LayerNormPlan {
    /// `Batched` on CUDA, `PerRun` elsewhere.
    pub fn default_for(device: Device) -> Self {
        if device.is_cuda() {
            LayerNormPlan::Batched
        } else {
            LayerNormPlan::PerRun
        }
    }
}

/// Per run, the seed libtorch's generator is set to before that run's dropout masks are drawn;
/// `None` for a run that gets no dropout this step (a run without inputs).
#[derive(Debug, Clone)]
pub struct DropoutSeeds(pub Vec<Option<i64>>);

/// How a pack draws its runs' dropout masks. Either way a run's masks come from libtorch's
/// generator seeded with the run's own seed for the step, so they depend on nothing of the other
/// runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MaskDraw {
    /// As the run's solo forward draws them on the CPU (`at::dropout`): one draw per site in the
    /// solo order at the run's own sequence length, so on the CPU bit for bit the solo run's
    /// masks. Two kernels per site and run.
    SoloOrder,
    /// Every site of a run in one draw over the pack's sequence length, then one scaling for the
    /// whole pack: one kernel per run. (On the CPU, where `bernoulli_` draws element after
    /// element from one stream, a run without padding gets `SoloOrder`'s masks.) On CUDA no draw order gives the solo run's masks anyway
    /// (libtorch's fused CUDA dropout kernel draws its own stream), and the ~20 launches per run
    /// and step that `SoloOrder` costs are what bound a pack's step there.
    PerRun,
}

impl MaskDraw {
    /// `PerRun` on CUDA, `SoloOrder` elsewhere.
    pub fn default_for(device: Device) -> Self {
        if device.is_cuda() {
            MaskDraw::PerRun
        } else {
            MaskDraw::SoloOrder
        }
    }
}

/// N Prompt-DT models of one shape with stacked weights (see the module documentation of
/// [`crate::model`]).
#[derive(Debug)]
pub struct PackedPromptDt {
    pub cfg: PromptDtConfig,
    slots: usize,
    /// Solo parameter names, reference `state_dict` order.
    names: Vec<String>,
    /// `[N, solo shape]` per name, leaf tensors that require gradients. Their run dimension may be
    /// strided (a flat optimiser re-points them at columns of one `[N, total]` buffer), so they
    /// are never `view`ed across it.
    weights: Vec<Tensor>,
    idx: Idx,
    /// tril(ones(n_positions, n_positions)) as bool (the reference's `attn.bias` buffer).
    causal: Tensor,
    masked_bias: Tensor,
    device: Device,
    mask_draw: MaskDraw,
    layer_norm: LayerNormPlan,
    /// `StateTokens` unless set otherwise: the pack is a tolerance path on every device.
    last_block: LastBlock,
    /// Per weight, its bound broadcast view if it has one ([`Self::bind_broadcast`]).
    bcast: Vec<Option<Broadcast>>,
    /// Tensors that depend only on what a step's batch shows of the pack's shape, made once and
    /// reused: an upload costs about eight host operators and a copy, the causal mask's cut a
    /// dozen operators and a kernel, every step otherwise.
    reused: std::sync::Mutex<Reused>,
}

/// See [`PackedPromptDt::reused`].
#[derive(Debug, Default)]
struct Reused {
    /// Per sequence length L: the causal mask's `[1, 1, L, L]` (contiguous).
    causal: std::collections::HashMap<i64, Tensor>,
    /// The patterns of which runs have a prompt.
    has_prompt: pdt_torch::device::BoolUploads,
}

/// A leaf view `[N, 1, d]` of a stacked one-dimensional parameter (a bias, a LayerNorm weight),
/// made when the weight had this address and these strides.
#[derive(Debug)]
struct Broadcast {
    view: Tensor,
    ptr: usize,
    strides: Vec<i64>,
}

/// The dropout masks of one forward pass, stacked over the runs (`None`: no dropout at that site):
/// embeddings, attention output and MLP output `[N, B*L, H]`, the activations' layout; per layer
/// attention weights `[N*B, nh, L, L]` (`MaskDraw::SoloOrder`) or `[N, B, nh, L, L]` (`PerRun`).
type Masks = DropoutMasks;

fn drop(x: Tensor, mask: Option<&Tensor>) -> Tensor {
    match mask {
        // `at::dropout` returns `input * noise`.
        Some(m) if m.size() == x.size() => x * m,
        // A `PerRun` attention mask, `[N, B, ...]` over the weights' `[N*B, ...]` (strided: a
        // run's sites are cut from one draw, so it is `x` that is viewed at the mask's shape, not
        // the mask copied).
        Some(m) => (x.reshape(m.size()) * m).reshape(x.size()),
        None => x,
    }
}

impl PackedPromptDt {
    /// A pack of `slots` models with zero weights (set each run's with [`Self::set_slot`]).
    pub fn new(cfg: &PromptDtConfig, slots: usize, device: Device) -> Result<Self, PackedError> {
        let shapes = parameter_shapes(cfg);
        let names: Vec<String> = shapes.iter().map(|(n, _)| n.clone()).collect();
        let n = slots as i64;
        let weights = shapes
            .iter()
            .map(|(_, s)| {
                let full: Vec<i64> = std::iter::once(n).chain(s.iter().copied()).collect();
                Tensor::zeros(full.as_slice(), (Kind::Float, device)).set_requires_grad(true)
            })
            .collect();
        let np = cfg.n_positions as i64;
        Ok(Self {
            cfg: cfg.clone(),
            slots,
            idx: Idx::new(&names)?,
            names,
            weights,
            causal: Tensor::ones([np, np], (Kind::Bool, device)).tril(0),
            masked_bias: Tensor::from(-1e4f32).to_device(device),
            device,
            mask_draw: MaskDraw::default_for(device),
            layer_norm: LayerNormPlan::default_for(device),
            last_block: LastBlock::StateTokens,
            bcast: (0..shapes.len()).map(|_| None).collect(),
            reused: Default::default(),
        })
    }

    pub fn slots(&self) -> usize {
        self.slots
    }

    pub fn device(&self) -> Device {
        self.device
    }

    /// How the dropout masks are drawn (default [`MaskDraw::default_for`] the device).
    pub fn set_mask_draw(&mut self, draw: MaskDraw) {
        self.mask_draw = draw;
    }

    /// What the last block of [`Self::forward_all_steps`] computes (by default the state tokens
    /// only; `AllTokens` is the reference's ops, as the solo CPU model runs them).
    pub fn set_last_block(&mut self, last: LastBlock) {
        self.last_block = last;
    }

    /// How the LayerNorms are computed (default [`LayerNormPlan::default_for`] the device).
    pub fn set_layer_norm(&mut self, plan: LayerNormPlan) {
        self.layer_norm = plan;
    }

    /// Solo parameter names, in the order of [`Self::weights`].
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// The stacked weights `[N, solo shape]`, in the order of [`Self::names`].
    pub fn weights(&self) -> &[Tensor] {
        &self.weights
    }

    /// Binds each one-dimensional parameter (biases, LayerNorm weights) to a leaf view `[N, 1, d]`
    /// of its stacked weight, sharing its storage; a view whose weight was re-pointed since (the
    /// flat optimiser's `set_data`) is made again. Why: the forward reads such a parameter broadcast
    /// over a run's rows, and an `unsqueeze` per use costs two operators and a backward node of
    /// four more, 35 uses a step: about 210 of the 2320 host operators a pack of 12's step
    /// dispatches on CUDA, where the step is bound by the host's dispatch. Once bound, the forward
    /// reads the views: take gradients with respect to [`Self::grad_inputs`] (a bound view's
    /// gradient is `[N, 1, d]`). Unbound or stale views are not read (the forward unsqueezes).
    pub fn bind_broadcast(&mut self) {
        for i in 0..self.weights.len() {
            if self.weights[i].dim() != 2 || self.bound(i).is_some() {
                continue;
            }
            let w = &self.weights[i];
            let view = tch::no_grad(|| w.detach().unsqueeze(1)).set_requires_grad(true);
            let (ptr, strides) = (w.data_ptr() as usize, w.stride());
            self.bcast[i] = Some(Broadcast { view, ptr, strides });
        }
    }

    /// Parameter `i`'s bound view, while its weight still has the storage it was made on.
    fn bound(&self, i: usize) -> Option<&Tensor> {
        let b = self.bcast.get(i)?.as_ref()?;
        let w = &self.weights[i];
        (b.ptr == w.data_ptr() as usize && b.strides == w.stride()).then_some(&b.view)
    }

    /// A one-dimensional parameter broadcast over a run's rows, `[N, 1, d]`.
    fn rows_of(&self, w: usize) -> Tensor {
        match self.bound(w) {
            Some(v) => v.shallow_clone(),
            None => self.weights[w].unsqueeze(1),
        }
    }

    /// What the forward reads each parameter through, in the order of [`Self::weights`]: its bound
    /// view ([`Self::bind_broadcast`]) or the weight itself. Differentiate with respect to these.
    pub fn grad_inputs(&self) -> Vec<Tensor> {
        (0..self.weights.len())
            .map(|i| self.bound(i).unwrap_or(&self.weights[i]).shallow_clone())
            .collect()
    }

    fn check_slot(&self, slot: usize) -> Result<(), PackedError> {
        if slot >= self.slots {
            return Err(PackedError::Slot { slot, slots: self.slots });
        }
        Ok(())
    }

    /// Sets run `slot`'s weights from solo-named tensors; every parameter must be given once, with
    /// its solo shape.
    pub fn set_slot(
        &mut self,
        slot: usize,
        weights: &[(String, Tensor)],
    ) -> Result<(), PackedError> {
        self.check_slot(slot)?;
        let mut found = vec![false; self.names.len()];
        for (name, t) in weights {
            let at =
                self.names.iter().position(|n| n == name).ok_or_else(|| PackedError::Weight {
                    name: name.clone(),
                    what: "not a parameter of the model".into(),
                })?;
            let want = &self.weights[at].size()[1..];
            if t.size() != want || t.kind() != Kind::Float || found[at] {
                return Err(PackedError::Weight {
                    name: name.clone(),
                    what: format!(
                        "shape {:?} {:?}, expected {want:?} Float once",
                        t.size(),
                        t.kind()
                    ),
                });
            }
            found[at] = true;
        }
        if let Some(i) = found.iter().position(|f| !f) {
            return Err(PackedError::Weight {
                name: self.names[i].clone(),
                what: "missing".into(),
            });
        }
        tch::no_grad(|| {
            for (name, t) in weights {
                if let Some(at) = self.names.iter().position(|n| n == name) {
                    self.weights[at].select(0, slot as i64).copy_(t);
                }
            }
        });
        Ok(())
    }

    /// Run `slot`'s weights as solo-named copies, in [`PromptDtConfig::parameter_names`] order.
    pub fn slot_weights(&self, slot: usize) -> Result<Vec<(String, Tensor)>, PackedError> {
        self.check_slot(slot)?;
        Ok(tch::no_grad(|| {
            self.names
                .iter()
                .zip(&self.weights)
                .map(|(n, w)| (n.clone(), w.select(0, slot as i64).detach().copy()))
                .collect()
        }))
    }

    /// `nn.Linear` per run: weight `[N, out, in]`, bias `[N, out]`; `x` `[N, R, in]` ->
    /// `[N, R, out]` (R: a run's rows, B*T).
    fn linear(&self, x: &Tensor, w: usize) -> Tensor {
        let (weight, bias) = (&self.weights[w], self.rows_of(w + 1));
        bias.baddbmm(x, &weight.transpose(1, 2), 1, 1)
    }

    /// HF `Conv1D` per run: weight `[N, in, out]`, bias `[N, out]`; `x` `[N, R, in]` ->
    /// `[N, R, out]`.
    fn conv1d(&self, x: &Tensor, w: usize) -> Tensor {
        let (weight, bias) = (&self.weights[w], self.rows_of(w + 1));
        bias.baddbmm(x, weight, 1, 1)
    }

    /// LayerNorm over the last dimension of `x` `[N, R, H]` with each run's weight and bias
    /// (`[N, H]`).
    fn layer_norm(&self, x: &Tensor, w: usize, eps: f64) -> Tensor {
        let h = x.size()[2];
        if self.layer_norm == LayerNormPlan::PerRun {
            // [N, H] each, through the bound views if any (what the gradients are taken of).
            let per_run = |i: usize| match self.bound(i) {
                Some(v) => v.squeeze_dim(1),
                None => self.weights[i].shallow_clone(),
            };
            let (weight, bias) = (per_run(w), per_run(w + 1));
            // `unbind`, not `get(i)` per run: its backward is one `stack`, where each `select`'s
            // would allocate and fill a gradient of the whole input.
            let (xs, ws, bs) = (x.unbind(0), weight.unbind(0), bias.unbind(0));
            let parts: Vec<Tensor> = xs
                .iter()
                .zip(ws.iter().zip(&bs))
                .map(|(x, (w, b))| x.layer_norm([h], Some(w), Some(b), eps, false))
                .collect();
            return Tensor::stack(&parts, 0);
        }
        let normed = x.layer_norm([h], None::<&Tensor>, None::<&Tensor>, eps, false); // [N, R, H]
        normed * self.rows_of(w) + self.rows_of(w + 1)
    }

    /// The causal mask of `l` tokens, `[1, 1, l, l]` (made once per length).
    fn causal(&self, l: i64) -> Tensor {
        let make = || self.causal.narrow(0, 0, l).narrow(1, 0, l).contiguous().view([1, 1, l, l]);
        match self.reused.lock() {
            Ok(mut r) => r.causal.entry(l).or_insert_with(make).shallow_clone(),
            // (A thread that panicked holding the lock: the same tensor, made afresh.)
            Err(_) => make(),
        }
    }

    /// `has[n]`, whether run n has a prompt, as `[N, 1, 1]` bools on the device (made once per
    /// pattern).
    fn has_prompt(&self, has: &[bool]) -> Tensor {
        let n = self.slots as i64;
        let flags = match self.reused.lock() {
            Ok(mut r) => r.has_prompt.get(has, self.device),
            Err(_) => pdt_torch::device::upload(has, self.device),
        };
        flags.view([n, 1, 1])
    }

    /// Interleaves (R_t, s_t, a_t) per step, as the solo `Embeddings::tokens`: tokens
    /// `[N, B*3T, H]` and their mask `[N*B, 3T]`.
    fn tokens(&self, e: &EmbIdx, seg: &Segments, b: i64) -> (Tensor, Tensor) {
        let hidden = self.cfg.hidden_size as i64;
        let n = self.slots as i64;
        let (rows, t) = (seg.batch_size(), seg.len());
        let table = &self.weights[e.timestep]; // [N, E, H]
        let big_e = table.size()[1];
        // Run n's timesteps index rows n*E.. of the flattened table.
        let offsets = Tensor::arange(n, (Kind::Int64, self.device)).view([n, 1]) * big_e;
        let index = seg.timesteps.reshape([n, b * t]) + offsets; // [N, B*T]
        let time = Tensor::embedding(&table.reshape([n * big_e, hidden]), &index, -1, false, false); // [N, B*T, H]
        let per_run = |x: &Tensor| x.reshape([n, b * t, -1]); // [N*B, T, d] -> [N, B*T, d]
        let s = self.linear(&per_run(&seg.states), e.state) + &time;
        let a = self.linear(&per_run(&seg.actions), e.action) + &time;
        let r = self.linear(&per_run(&seg.returns_to_go), e.ret) + &time;
        // [N, B*T, 3, H]: a step's three tokens side by side, so that the rows read R_0, s_0,
        // a_0, R_1, ... with no permutation (no copy).
        let tokens = Tensor::stack(&[r, s, a], 2).view([n, b * 3 * t, hidden]);
        let m = &seg.mask;
        let mask = Tensor::stack(&[m, m, m], 2).view([rows, 3 * t]); // [N*B, T, 3] -> [N*B, 3T]
        (tokens, mask)
    }

    /// Each run's dropout masks, drawn as its solo forward draws them (seed, then the sites in
    /// order at the run's own sequence length), in place into its rows of the stacked masks (a
    /// run with padding: at the end of its sequence, the padding keeps 1).
    fn dropout_masks(&self, batch: &PackedBatch, seeds: &DropoutSeeds, l: i64) -> Masks {
        let cfg = &self.cfg;
        let (b, h, nh) = (batch.batch, cfg.hidden_size as i64, cfg.n_head as i64);
        let rows = self.slots as i64 * b;
        // The sites in the solo forward's order.
        let sites = dropout_sites(cfg);
        if self.mask_draw == MaskDraw::PerRun {
            return self.masks_per_run(batch, seeds, l, &sites);
        }
        let f = (Kind::Float, self.device);
        let own_len = |slot: usize| 3 * (batch.prompt_lens[slot] + batch.k);
        // Rows that are not all drawn (padding, or a run without dropout) start at 1.
        let partial = seeds.0.iter().enumerate().any(|(s, seed)| seed.is_none() || own_len(s) < l);
        let stacked: Vec<Option<Tensor>> = sites
            .iter()
            .map(|&DropoutSite { p, attention: attn }| {
                let full: Vec<i64> = if attn { vec![rows, nh, l, l] } else { vec![rows, l, h] };
                (p > 0.0).then(|| {
                    if partial {
                        Tensor::ones(full.as_slice(), f)
                    } else {
                        Tensor::empty(full.as_slice(), f)
                    }
                })
            })
            .collect();
        for (slot, seed) in seeds.0.iter().enumerate() {
            let Some(seed) = seed else { continue };
            tch::manual_seed(*seed);
            let lj = own_len(slot);
            let off = l - lj;
            for (&DropoutSite { p, attention: attn }, mask) in sites.iter().zip(&stacked) {
                // `at::dropout` draws nothing at p = 0.
                let Some(mask) = mask else { continue };
                // `at::dropout` (CPU): noise = empty_like(x).bernoulli_(1 - p); noise.div_(1 - p).
                // A run's rows of the stacked mask are contiguous, so drawing into them draws
                // what a fresh tensor of their shape gets.
                let mut mine = mask.narrow(0, slot as i64 * b, b);
                if off == 0 {
                    draw_noise(&mut mine, p);
                    continue;
                }
                let own: Vec<i64> = if attn { vec![b, nh, lj, lj] } else { vec![b, lj, h] };
                let mut noise = Tensor::empty(own.as_slice(), f);
                draw_noise(&mut noise, p);
                let mut window = mine.narrow(attn as i64 + 1, off, lj);
                if attn {
                    window = window.narrow(3, off, lj);
                }
                window.copy_(&noise);
            }
        }
        // Drawn per sample; read in the activations' layout, `[N*B, L, H]` -> `[N, B*L, H]`.
        let n = self.slots as i64;
        Masks::from_sites(
            stacked
                .into_iter()
                .zip(&sites)
                .map(|(m, s)| m.map(|m| if s.attention { m } else { m.view([n, -1, h]) }))
                .collect(),
        )
    }

    /// [`MaskDraw::PerRun`]: each run's masks for every site in one draw into its row of one
    /// `[N, total]` buffer, at the pack's length `l` (a padded step's mask multiplies values
    /// nothing reads); each site a view, `[N, B*L, H]` or, the attention weights',
    /// `[N, B, nh, L, L]`.
    fn masks_per_run(
        &self,
        batch: &PackedBatch,
        seeds: &DropoutSeeds,
        l: i64,
        sites: &[DropoutSite],
    ) -> Masks {
        let cfg = &self.cfg;
        let (n, b, h, nh) =
            (self.slots as i64, batch.batch, cfg.hidden_size as i64, cfg.n_head as i64);
        let shape = |attn: bool| if attn { vec![n, b, nh, l, l] } else { vec![n, b * l, h] };
        let size = |attn: bool| shape(attn).iter().skip(1).product::<i64>();
        let drawn: Vec<(f64, bool)> =
            sites.iter().filter(|s| s.p > 0.0).map(|s| (s.p, s.attention)).collect();
        let total: i64 = drawn.iter().map(|&(_, a)| size(a)).sum();
        let f = (Kind::Float, self.device);
        // A run without inputs this step keeps 1 (its placeholder's values stay finite).
        let noise = if seeds.0.iter().any(Option::is_none) {
            Tensor::ones([n, total], f)
        } else {
            Tensor::empty([n, total], f)
        };
        let one_p = drawn.windows(2).all(|w| w[0].0 == w[1].0);
        for (slot, seed) in seeds.0.iter().enumerate() {
            let Some(seed) = seed else { continue };
            tch::manual_seed(*seed);
            let mut row = noise.get(slot as i64);
            match drawn.first() {
                Some(&(p, _)) if one_p => {
                    pdt_torch::bernoulli::bernoulli_(&mut row, 1.0 - p);
                }
                _ => {
                    let mut off = 0;
                    for &(p, attn) in &drawn {
                        pdt_torch::bernoulli::bernoulli_(
                            &mut row.narrow(0, off, size(attn)),
                            1.0 - p,
                        );
                        off += size(attn);
                    }
                }
            }
        }
        // `at::dropout`'s scaling, noise / (1 - p), for the whole pack at once.
        let mut off = 0;
        let mut views = Vec::with_capacity(drawn.len());
        for &(p, attn) in &drawn {
            let mut site = noise.narrow(1, off, size(attn));
            if !one_p {
                let _ = site.g_div_scalar_(1.0 - p);
            }
            views.push(site.view(shape(attn).as_slice()));
            off += size(attn);
        }
        if one_p {
            if let Some(&(p, _)) = drawn.first() {
                let mut all = noise.shallow_clone();
                let _ = all.g_div_scalar_(1.0 - p);
            }
        }
        let mut views = views.into_iter();
        Masks::from_sites(
            sites.iter().map(|s| (s.p > 0.0).then(|| views.next()).flatten()).collect(),
        )
    }

    /// `states`: the queries of the state tokens only ([`Self::block`]); `masks` are read at
    /// the rows computed.
    fn attention(
        &self,
        x: &Tensor,
        blk: &BlockIdx,
        causal: &Tensor,
        pad_bias: &Tensor,
        masks: Option<&[Option<Tensor>; 3]>,
        states: bool,
    ) -> Tensor {
        let hidden = self.cfg.hidden_size as i64;
        let nh = self.cfg.n_head as i64;
        let hd = hidden / nh;
        let (n_rows, l) = (pad_bias.size()[0], pad_bias.size()[3]); // N*B, L
        let qkv = self.conv1d(x, blk.c_attn).split(hidden, 2); // 3 x [N, B*L, H]
        let q = if states { state_rows(&qkv[0]) } else { qkv[0].shallow_clone() }; // [N, B*R, H]
        let r = if states { l / 3 } else { l };
        let q = self.heads(&q, n_rows, r); // [N*B*nh, R, hd]
        let k = self.heads(&qkv[1], n_rows, l).transpose(1, 2); // [N*B*nh, hd, L]
        let v = self.heads(&qkv[2], n_rows, l); // [N*B*nh, L, hd]
        let w = q.bmm(&k).view([n_rows, nh, r, l]) / (hd as f64).powf(0.5); // [N*B, nh, R, L]
        let w = w.where_self(causal, &self.masked_bias) + pad_bias;
        let w = drop(w.softmax(-1, None::<Kind>), masks.and_then(|m| m[0].as_ref()));
        let a = w.reshape([n_rows * nh, r, l]).bmm(&v); // [N*B*nh, R, hd]
        drop(
            self.conv1d(&self.merge_heads(a, n_rows), blk.attn_proj),
            masks.and_then(|m| m[1].as_ref()),
        )
    }

    /// Queries, keys or values `[N, B*T, H]` (a sample's T rows consecutive) as the batched
    /// matrices of their heads, `[N*B*nh, T, hd]`. What `matmul` of the 4-D heads `[N*B, nh, T,
    /// hd]` would reshape them to for its `bmm`, without its expands and reshapes (some ten host
    /// operators per product, forward and backward); with one head, a view with no permutation.
    fn heads(&self, x: &Tensor, rows: i64, t: i64) -> Tensor {
        let nh = self.cfg.n_head as i64;
        let hd = self.cfg.hidden_size as i64 / nh;
        if nh == 1 {
            return x.view([rows, t, hd]);
        }
        x.view([rows, t, nh, hd]).permute([0, 2, 1, 3]).reshape([rows * nh, t, hd])
    }

    /// [`Self::heads`] undone for the attention's output `[N*B*nh, T, hd]`: `[N, B*T, H]`.
    fn merge_heads(&self, a: Tensor, rows: i64) -> Tensor {
        let (n, nh) = (self.slots as i64, self.cfg.n_head as i64);
        let hidden = self.cfg.hidden_size as i64;
        if nh == 1 {
            return a.view([n, -1, hidden]);
        }
        let t = a.size()[1];
        a.view([rows, nh, t, hidden / nh]).permute([0, 2, 1, 3]).contiguous().view([n, -1, hidden])
    }

    /// Every run's tokens, prompt first in each sample, and their mask: `[N, B*3(P+K), H]`,
    /// `[N*B, 3(P+K)]`.
    fn embed(&self, batch: &PackedBatch) -> (Tensor, Tensor) {
        let (n, b) = (self.slots as i64, batch.batch);
        let hidden = self.cfg.hidden_size as i64;
        let (tokens, mask) = self.tokens(&self.idx.history, &batch.history, b);
        let tokens = self.layer_norm(&tokens, self.idx.embed_ln, 1e-5); // [N, B*3K, H]
        match &batch.prompt {
            Some(p) => {
                // [N, B*3P, H], no LayerNorm. A run without prompt gets zero prompt tokens (all
                // masked): none of its prompt layers' values or gradients enter.
                let (p_tokens, p_mask) = self.tokens(&self.idx.prompt, p, b);
                let keep: Vec<bool> = batch.prompt_lens.iter().map(|&lp| lp > 0).collect();
                let p_tokens = p_tokens.where_scalarother(&self.has_prompt(&keep), 0.0);
                let per_sample = |x: &Tensor| x.view([n * b, -1, hidden]); // [N*B, 3T, H]
                let x = Tensor::cat(&[per_sample(&p_tokens), per_sample(&tokens)], 1);
                (x.view([n, -1, hidden]), Tensor::cat(&[p_mask, mask], 1))
            }
            None => (tokens, mask),
        }
    }

    /// Predicted actions of every run at every step of its packed sequence, prompt steps first:
    /// `[N, B, P+K, da]` (run n's own steps are the last `prompt_lens[n] + K`). `dropout = None`
    /// is eval mode.
    pub fn forward_all_steps(&self, batch: &PackedBatch, dropout: Option<&DropoutSeeds>) -> Tensor {
        let cfg = &self.cfg;
        let (n, b) = (self.slots as i64, batch.batch);
        let (tokens, mask) = self.embed(batch); // [N, B*3(P+K), H], [N*B, 3(P+K)]
        let l = mask.size()[1]; // 3(P+K)
        let masks = dropout.map(|s| self.dropout_masks(batch, s, l));
        let causal = self.causal(l);
        let pad_bias = (1.0 - mask.unsqueeze(1).unsqueeze(1)) * -10000.0; // [N*B, 1, 1, L]
        let eps = cfg.layer_norm_epsilon;
        let mut x = drop(tokens, masks.as_ref().and_then(|m| m.embd.as_ref()));
        let Some((last, blocks)) = self.idx.blocks.split_last() else {
            // (A model of no layers: `PromptDtConfig::validate` refuses it.)
            return Tensor::zeros([n, b, batch.p + batch.k, 0], (Kind::Float, self.device));
        };
        for (i, blk) in blocks.iter().enumerate() {
            let site = masks.as_ref().map(|m| &m.layers[i]);
            x = self.block(&x, blk, &causal, &pad_bias, site, false);
        }
        // By default differs from the reference code (which runs the last block on every token,
        // then reads the state tokens' outputs): only the state tokens' outputs are read (the
        // action head), and nothing after the last block mixes positions, so its queries,
        // attention output and MLP run for the state tokens only (its keys and values still come
        // from every token). The same values in exact arithmetic, a third of the last block's
        // rows: the pack is a tolerance path, never bitwise (docs/implementation-details.md, C.9).
        let site = masks.as_ref().map(|m| &m.layers[blocks.len()]);
        let x = match self.last_block {
            // [N, B*(P+K), H]
            LastBlock::StateTokens => {
                self.block(&x, last, &state_rows(&causal), &pad_bias, site, true)
            }
            LastBlock::AllTokens => {
                state_rows(&self.block(&x, last, &causal, &pad_bias, site, false))
            }
        };
        let x = self.layer_norm(&x.contiguous(), self.idx.ln_f, eps);
        debug_assert_eq!(x.size()[1], b * (batch.p + batch.k));
        let actions = self.linear(&x, self.idx.predict_action); // [N, B*(P+K), da]
        let actions = if cfg.action_tanh { actions.tanh() } else { actions };
        actions.view([n, b, batch.p + batch.k, -1])
    }

    /// One transformer block (attention, then MLP, each residual) on every position, or with
    /// `states` its queries, attention output and MLP for the state tokens only (positions 1, 4,
    /// 7, ...): `[N, B*L/3, H]` from `x` `[N, B*L, H]` (a sample's L rows are consecutive and L is
    /// a multiple of 3, so its state tokens are every third row from the second), `causal`
    /// holding their rows (`[1, 1, L/3, L]`), the masks of `site` (the full forward's) read at
    /// their rows, so a state token's output is the full block's at its position.
    fn block(
        &self,
        x: &Tensor,
        blk: &BlockIdx,
        causal: &Tensor,
        pad_bias: &Tensor,
        site: Option<&[Option<Tensor>; 3]>,
        states: bool,
    ) -> Tensor {
        let eps = self.cfg.layer_norm_epsilon;
        let rows = |t: &Tensor| if states { state_rows(t) } else { t.shallow_clone() };
        let masks = site.map(|s| s.each_ref().map(|m| m.as_ref().map(rows)));
        let masks = masks.as_ref();
        let ln_1 = self.layer_norm(x, blk.ln_1, eps);
        let a = self.attention(&ln_1, blk, causal, pad_bias, masks, states);
        let h = rows(x) + a; // [N, B*R, H]: R = L/3 or L
        let inner = self.conv1d(&self.layer_norm(&h, blk.ln_2, eps), blk.c_fc).relu();
        let m = drop(self.conv1d(&inner, blk.mlp_proj), masks.and_then(|s| s[2].as_ref()));
        &h + m
    }

    /// The masked action MSE of each run (`PromptDt::action_loss` per run): `[N]`. Padded steps
    /// are selected out (`where`), so a non-finite prediction there cannot reach the loss.
    ///
    /// # Shapes
    /// `preds`, `targets`: `[N, B, T, da]`; `mask`: `[N, B, T]`.
    pub fn action_loss(preds: &Tensor, targets: &Tensor, mask: &Tensor) -> Tensor {
        let da = preds.size()[3];
        let keep = mask.gt(0.0).unsqueeze(-1); // [N, B, T, 1]
        let sq = (preds - targets).pow_tensor_scalar(2).where_scalarother(&keep, 0.0);
        let count = keep.sum_dim_intlist([1i64, 2, 3].as_slice(), false, Kind::Float) * da as f64; // [N]
        sq.sum_dim_intlist([1i64, 2, 3].as_slice(), false, Kind::Float) / count
    }
}
