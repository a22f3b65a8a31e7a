//! One gradient step (the reference's `train_step_mix`): forward in train mode, masked MSE on the
//! history actions, backward, global clipping, AdamW at the scheduled learning rate.

use crate::optim::Optimizer;
use pdt_eval::to_segments;
use pdt_model::dropout::Dropout;
use pdt_model::prompt_dt::Sequence;
use pdt_model::{PromptDt, Segments};
use pdt_prompt::PromptDtBatch;
use pdt_rundir::config::{LastBlockChoice, LossOn};
use tch::{Device, Kind, Tensor};

/// What one step measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepStats {
    /// Mean squared action error over the supervised steps, before the update.
    pub loss: f64,
    /// Global gradient L2 norm before clipping.
    pub grad_norm: f64,
    /// Learning rate used for this update.
    pub lr: f64,
}

/// A step's loss and gradient norm left where the step computed them, read later
/// ([`Self::read_all`]): reading a value of a CUDA step waits for its kernels, so a loop that read
/// each step's values at once would let the device idle while the host prepares the next step.
/// The run loops read an iteration's steps together, once, after its last step. (Reading later
/// changes no value: the same two `f32` numbers, widened to `f64` as `double_value` did.)
#[derive(Debug)]
pub struct PendingStats {
    /// `[2]`: the loss and the gradient norm (the step's own `f32` scalars stacked, or values
    /// already on the host); or a pack's `[2, N]`, of which this step's is column `column`.
    values: Tensor,
    column: Option<i64>,
    lr: f64,
}

impl PendingStats {
    /// `values` `[2]` (loss, gradient norm) as the step left them.
    pub fn new(values: Tensor, lr: f64) -> Self {
        Self { values, column: None, lr }
    }

    /// Column `column` of a pack step's `[2, N]` (every run's loss, then every run's norm),
    /// taken when read: the pack's step makes no view per run.
    pub fn column(values: &Tensor, column: usize, lr: f64) -> Self {
        Self { values: values.shallow_clone(), column: Some(column as i64), lr }
    }

    /// Statistics already on the host.
    pub fn ready(st: StepStats) -> Self {
        Self::new(Tensor::from_slice(&[st.loss, st.grad_norm]), st.lr)
    }

    /// This step's statistics (waits for the step).
    pub fn read(self) -> Result<StepStats, tch::TchError> {
        Ok(Self::read_all(vec![self])?.remove(0))
    }

    /// The statistics of `steps`, in their order: one copy to the host for all of them, so one
    /// wait for the device.
    pub fn read_all(steps: Vec<PendingStats>) -> Result<Vec<StepStats>, tch::TchError> {
        let Some(first) = steps.first() else { return Ok(Vec::new()) };
        let device = first.values.device();
        let parts: Vec<Tensor> = steps
            .iter()
            .map(|p| {
                let v = match p.column {
                    Some(c) => p.values.f_select(1, c)?, // [2]
                    None => p.values.shallow_clone(),
                };
                v.f_to_device(device)?.f_to_kind(Kind::Double)
            })
            .collect::<Result<_, _>>()?;
        let host = Tensor::f_stack(&parts, 0)?.f_to_device(Device::Cpu)?.f_view([-1])?; // [S*2]
        let host = Vec::<f64>::try_from(&host)?;
        Ok(steps
            .iter()
            .enumerate()
            .map(|(i, p)| StepStats { loss: host[2 * i], grad_norm: host[2 * i + 1], lr: p.lr })
            .collect())
    }

    /// The statistics of a pack step's slots (`None` where a slot was not stepped), read together.
    pub fn read_slots(
        slots: Vec<Option<PendingStats>>,
    ) -> Result<Vec<Option<StepStats>>, tch::TchError> {
        let stepped: Vec<bool> = slots.iter().map(Option::is_some).collect();
        let mut read = Self::read_all(slots.into_iter().flatten().collect())?.into_iter();
        Ok(stepped.into_iter().map(|s| if s { read.next() } else { None }).collect())
    }
}

/// A failed read of step statistics, as a run's error.
pub(crate) fn unreadable(e: tch::TchError) -> crate::error::RunError {
    crate::error::RunError::Internal(format!("reading the steps' losses from the device: {e}"))
}

/// The model's last block for a run's `train.last_block` on `device` (`batched`: in a batched
/// pack, where `auto` means the state tokens on any device; docs/implementation-details.md, C.9).
pub fn last_block(choice: LastBlockChoice, device: Device, batched: bool) -> pdt_model::LastBlock {
    if choice.state_tokens(device.is_cuda(), batched) {
        pdt_model::LastBlock::StateTokens
    } else {
        pdt_model::LastBlock::AllTokens
    }
}

/// Tensors of a batch on the device, ready for [`train_step`].
#[derive(Debug)]
pub struct DeviceBatch {
    pub history: Segments,
    pub prompt: Option<Segments>,
}

impl DeviceBatch {
    /// A second handle on the same tensors.
    pub fn shallow_clone(&self) -> Self {
        Self {
            history: self.history.shallow_clone(),
            prompt: self.prompt.as_ref().map(Segments::shallow_clone),
        }
    }

    /// `use_prompt = false` drops the prompt (MT-ORL, MT-BC: the reference's `--no-prompt`).
    pub fn new(batch: &PromptDtBatch, use_prompt: bool, device: Device) -> Self {
        Self {
            history: to_segments(&batch.history, device),
            prompt: use_prompt.then(|| to_segments(&batch.prompt, device)),
        }
    }
}

/// One training step at gradient step index `step` (0-based; it sets the warm-up learning rate),
/// its statistics read at once.
pub fn train_step(
    model: &PromptDt,
    opt: &mut Optimizer,
    batch: &DeviceBatch,
    loss_on: LossOn,
    step: u64,
) -> Result<StepStats, tch::TchError> {
    train_step_with(model, opt, batch, loss_on, step, Dropout::Draw).read()
}

/// [`train_step`] with its dropout as given: [`Dropout::Given`] masks drawn beforehand
/// (`DropoutMasks::draw` for this batch's `PromptDt::token_count`) make the step draw nothing from
/// libtorch's generator, so steps of several models can run at once in threads (the pack's solo
/// engine).
pub fn train_step_with(
    model: &PromptDt,
    opt: &mut Optimizer,
    batch: &DeviceBatch,
    loss_on: LossOn,
    step: u64,
    dropout: Dropout<'_>,
) -> PendingStats {
    let (h, p) = (&batch.history, batch.prompt.as_ref());
    let loss = match (loss_on, p) {
        (LossOn::PromptAndHistory, Some(p)) => {
            let preds = model.forward(h, Sequence::new(Some(p), dropout).all_steps()); // [B, Lp+K, da]
            let targets = Tensor::cat(&[&p.actions, &h.actions], 1);
            let mask = Tensor::cat(&[&p.mask, &h.mask], 1);
            PromptDt::action_loss(&preds, &targets, &mask)
        }
        _ => {
            PromptDt::action_loss(&model.forward(h, Sequence::new(p, dropout)), &h.actions, &h.mask)
        }
    };
    let mut grads = opt.backward(&loss);
    let grad_norm = opt.clip_grad_norm(&mut grads, opt.cfg().grad_clip_norm); // [] (not read)
    let lr = opt.cfg().lr_at(step);
    opt.step(&grads, lr);
    // (The norm is the loss's kind and device but when no parameter has a gradient.)
    let norm = if grad_norm.device() == loss.device() && grad_norm.kind() == loss.kind() {
        grad_norm
    } else {
        grad_norm.to_device(loss.device()).to_kind(loss.kind())
    };
    PendingStats::new(Tensor::stack(&[loss.detach(), norm], 0), lr) // [2]
}
