//! Offline evaluation: the prompted model's action error on the held-out tasks' data, for runs
//! with no environment to act in (a task suite without `[environment]`, docs/your-own-tasks.md).
//!
//! What is measured, per task of the split, drawing from the evaluation's stream `rng` in this
//! order: the task's prompt, drawn as an evaluation in an environment draws it
//! (`BatchSampler::eval_prompt`, once per task, shared by all its segments; the methods without
//! a prompt draw it too and leave it out, as their evaluations do), then `segments` history
//! segments of K steps from the task's dataset, drawn as training draws its histories
//! (`BatchSampler::history_segments`: the data's own returns-to-go, zeroed where training zeroes
//! them). The model predicts every step's action from the prompt and the history before it (one
//! forward, no dropout: the training loss's forward in evaluation mode), and the error is the
//! mean over the valid (unpadded) steps and action dimensions of (predicted - data action)^2, in
//! the action's units: `train/action_loss` on held-out data. Deterministic for a seed: the draws
//! come from `rng` only, and the squared errors are summed on the host in f64, task by task.
//!
//! Lower is better; it is no return and is recorded apart from returns (`pdt_rundir::offline`).

use crate::{prompt_batch, to_segments, to_vec};
use pdt_model::prompt_dt::Sequence;
use pdt_model::PromptDt;
use pdt_prompt::{BatchSampler, Rng};
use pdt_rundir::offline::OfflineTaskResult;
use tch::Device;

/// Segments in one forward pass: a bound on memory, not on results (the sum is the same for any
/// chunking, the draws being sequential).
const CHUNK: usize = 256;

/// The action error of `model` on each task of `sampler` (the split's data with the run's
/// sampling settings), `segments` segments per task, with the task's prompt when `prompted`.
pub fn action_error(
    model: &PromptDt,
    sampler: &BatchSampler<'_>,
    prompted: bool,
    segments: usize,
    device: Device,
    rng: &mut Rng,
) -> Vec<OfflineTaskResult> {
    (0..sampler.num_tasks())
        .map(|i| {
            let prompt = sampler.eval_prompt(i, rng);
            let (mut sum, mut steps) = (0f64, 0usize);
            let mut left = segments;
            while left > 0 {
                let n = left.min(CHUNK);
                left -= n;
                let h = sampler.history_segments(i, n, rng);
                let p = prompted.then(|| prompt_batch(&vec![&prompt; n], device));
                let preds = tch::no_grad(|| {
                    model.forward(&to_segments(&h, device), Sequence::eval(p.as_ref()))
                });
                let preds = to_vec(&preds); // [n, K, da]
                let da = h.act_dim;
                for (j, &m) in h.mask.iter().enumerate() {
                    if m > 0.0 {
                        steps += 1;
                        let (p, a) =
                            (&preds[j * da..(j + 1) * da], &h.actions[j * da..(j + 1) * da]);
                        for (x, y) in p.iter().zip(a) {
                            sum += (f64::from(*x) - f64::from(*y)).powi(2);
                        }
                    }
                }
            }
            let t = sampler.task(i);
            let terms = (steps * sampler.act_dim()).max(1) as f64;
            OfflineTaskResult {
                task: t.id.to_string(),
                task_index: t.id.index,
                action_mse: sum / terms,
                segments,
                steps,
            }
        })
        .collect()
}
