//! One gradient step (the reference's `train_step_mix`): forward in train mode, masked MSE on the
//! history actions, backward, global clipping, AdamW at the scheduled learning rate.

use crate::optim::Optimizer;
use pdt_model::dropout::Dropout;
use pdt_model::{PromptDt, Segments};
use pdt_prompt::PromptDtBatch;
use tch::{Device, Kind, Tensor};

pub use pdt_eval::to_segments;

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

pub use pdt_rundir::config::{LastBlockChoice, LossOn};

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

/// One training step at gradient step index `step` (0-based; it sets the warm-up learning rate).
pub fn train_step(
    model: &PromptDt,
    opt: &mut Optimizer,
    batch: &DeviceBatch,
    loss_on: LossOn,
    step: u64,
) -> StepStats {
    train_step_with(model, opt, batch, loss_on, step, Dropout::Draw)
}

/// [`train_step`] with its dropout as given: [`Dropout::Given`] masks drawn beforehand
/// (`PromptDt::draw_dropout` for this batch) make the step draw nothing from libtorch's generator,
/// so steps of several models can run at once in threads (the pack's solo engine).
pub fn train_step_with(
    model: &PromptDt,
    opt: &mut Optimizer,
    batch: &DeviceBatch,
    loss_on: LossOn,
    step: u64,
    dropout: Dropout<'_>,
) -> StepStats {
    let (h, p) = (&batch.history, batch.prompt.as_ref());
    let loss = match (loss_on, p) {
        (LossOn::PromptAndHistory, Some(p)) => {
            let preds = model.forward_all_steps_with(h, Some(p), dropout); // [B, Lp+K, da]
            let targets = Tensor::cat(&[&p.actions, &h.actions], 1);
            let mask = Tensor::cat(&[&p.mask, &h.mask], 1);
            PromptDt::action_loss(&preds, &targets, &mask)
        }
        _ => PromptDt::action_loss(&model.forward_with(h, p, dropout), &h.actions, &h.mask),
    };
    let mut grads = opt.backward(&loss);
    let grad_norm = opt.clip_grad_norm(&mut grads, opt.cfg().grad_clip_norm);
    let lr = opt.cfg().lr_at(step);
    opt.step(&grads, lr);
    StepStats { loss: loss.to_kind(Kind::Double).double_value(&[]), grad_norm, lr }
}
