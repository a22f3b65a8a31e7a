//! MACAW's per-task offline buffers, built from promptdt's trajectories with the fields the official
//! writer derives (spec 2.2), and its two ways of drawing a batch (spec 2.4).

use crate::MacawError;
use pdt_data::TaskDataset;
use tch::{Device, Kind, Tensor};

/// How a task's buffer is cut from its dataset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BufferSpec {
    /// Keep the last `rows` transitions (0 = all), as the official `end` mode does.
    pub rows: usize,
    /// Then every `skip`-th, starting with the first kept (`[::skip]`).
    pub skip: usize,
    /// Each episode in reverse time order (the official `add_trajectory`).
    pub reverse_episodes: bool,
    pub discount: f64,
}

/// One batch of transitions, as tensors: the columns of the official batch matrix that the losses
/// read (spec 2.4), each named.
#[derive(Debug)]
pub struct Batch {
    /// `[B, O]` raw observations (MACAW normalises nothing).
    pub obs: Tensor,
    /// `[B, A]` dataset actions.
    pub act: Tensor,
    /// `[B, O]` s_T, the episode's final observation.
    pub terminal_obs: Tensor,
    /// `[B, 1]` kappa_t = gamma^(T - t).
    pub terminal_discount: Tensor,
    /// `[B, 1]` G_t, the discounted reward-to-go truncated at the episode end.
    pub mc_return: Tensor,
}

/// A task's transitions with MACAW's derived fields, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskBuffer {
    pub task: String,
    pub obs_dim: usize,
    pub act_dim: usize,
    obs: Vec<f32>,
    act: Vec<f32>,
    terminal_obs: Vec<f32>,
    terminal_discount: Vec<f32>,
    mc_return: Vec<f32>,
}

impl TaskBuffer {
    /// Builds the buffer of task `task` (its name, for errors) from its dataset.
    ///
    /// DIFFERENCE: promptdt's datasets do not store the observation after an episode's last step,
    /// so s_T is the episode's last stored observation s_{T-1} (the official writer uses
    /// next_obs[T-1]); it only enters the bootstrap terms kappa V(s_T), where kappa <= gamma.
    pub fn from_dataset(
        task: &str,
        ds: &TaskDataset,
        spec: &BufferSpec,
    ) -> Result<Self, MacawError> {
        let err = |message: String| MacawError::Data { task: task.to_string(), message };
        if spec.skip == 0 {
            return Err(err("buffer skip 0".into()));
        }
        let (o, a) = (ds.obs_dim, ds.act_dim);
        let mut b = Self {
            task: task.to_string(),
            obs_dim: o,
            act_dim: a,
            obs: Vec::new(),
            act: Vec::new(),
            terminal_obs: Vec::new(),
            terminal_discount: Vec::new(),
            mc_return: Vec::new(),
        };
        let gamma = spec.discount;
        for (e, t) in ds.trajectories.iter().enumerate() {
            let n = t.len();
            if n == 0 {
                continue;
            }
            let last = &t.observations[(n - 1) * o..n * o];
            // G_t by the backward recursion, in f64 (the official writer works in Python floats).
            let mut g = vec![0f64; n];
            let mut acc = 0f64;
            for i in (0..n).rev() {
                acc = f64::from(t.rewards[i]) + gamma * acc;
                g[i] = acc;
            }
            // Checked as stored (f32): a finite f64 return may still overflow f32.
            if let Some(i) = g.iter().position(|&v| !(v as f32).is_finite()) {
                return Err(err(format!(
                    "episode {e}: the discounted return at step {i} is not finite ({}); the \
                     rewards are too large or not numbers",
                    g[i]
                )));
            }
            let order: Box<dyn Iterator<Item = usize>> =
                if spec.reverse_episodes { Box::new((0..n).rev()) } else { Box::new(0..n) };
            for i in order {
                b.obs.extend_from_slice(&t.observations[i * o..(i + 1) * o]);
                b.act.extend_from_slice(&t.actions[i * a..(i + 1) * a]);
                b.terminal_obs.extend_from_slice(last);
                b.terminal_discount.push(gamma.powi((n - i) as i32) as f32);
                b.mc_return.push(g[i] as f32);
            }
        }
        let total = b.len();
        if total == 0 {
            return Err(err("no transitions in its dataset".into()));
        }
        // The official `end` mode: the last rows, then every skip-th.
        let start = if spec.rows == 0 { 0 } else { total.saturating_sub(spec.rows) };
        if start > 0 || spec.skip > 1 {
            let keep: Vec<usize> = (start..total).step_by(spec.skip).collect();
            let pick = |v: &[f32], w: usize| -> Vec<f32> {
                keep.iter().flat_map(|&r| v[r * w..(r + 1) * w].iter().copied()).collect()
            };
            b = Self {
                obs: pick(&b.obs, o),
                act: pick(&b.act, a),
                terminal_obs: pick(&b.terminal_obs, o),
                terminal_discount: pick(&b.terminal_discount, 1),
                mc_return: pick(&b.mc_return, 1),
                ..b
            };
        }
        Ok(b)
    }

    pub fn len(&self) -> usize {
        self.mc_return.len()
    }

    pub fn is_empty(&self) -> bool {
        self.mc_return.is_empty()
    }

    fn check(&self, n: usize, contiguous: bool) -> Result<(), MacawError> {
        // The official contiguous start is randint(0, len - B): it needs len > B.
        let need = if contiguous { n + 1 } else { n };
        if self.len() < need {
            return Err(MacawError::Data {
                task: self.task.clone(),
                message: format!(
                    "{} transitions in its buffer, but a {} batch of {n} needs at least {need} \
                     (more data, or smaller macaw batches / buffer_skip)",
                    self.len(),
                    if contiguous { "contiguous" } else { "uniform" }
                ),
            });
        }
        Ok(())
    }

    /// `n` consecutive rows from a start drawn uniformly in [0, len - n) (the official
    /// `contiguous=True`), or `n` distinct rows drawn uniformly (`random.sample`).
    pub fn sample<R: rand::Rng>(
        &self,
        n: usize,
        contiguous: bool,
        rng: &mut R,
        device: Device,
    ) -> Result<Batch, MacawError> {
        self.check(n, contiguous)?;
        let rows: Vec<usize> = if contiguous {
            let start = rng.random_range(0..self.len() - n);
            (start..start + n).collect()
        } else {
            rand::seq::index::sample(rng, self.len(), n).into_vec()
        };
        Ok(self.rows(&rows, device))
    }

    /// The batch of the given rows.
    pub fn rows(&self, rows: &[usize], device: Device) -> Batch {
        let (o, a, n) = (self.obs_dim as i64, self.act_dim as i64, rows.len() as i64);
        let take = |v: &[f32], w: usize| -> Vec<f32> {
            rows.iter().flat_map(|&r| v[r * w..(r + 1) * w].iter().copied()).collect()
        };
        let t = |v: Vec<f32>, w: i64| Tensor::from_slice(&v).view([n, w]).to_device(device);
        Batch {
            obs: t(take(&self.obs, self.obs_dim), o),
            act: t(take(&self.act, self.act_dim), a),
            terminal_obs: t(take(&self.terminal_obs, self.obs_dim), o),
            terminal_discount: t(take(&self.terminal_discount, 1), 1),
            mc_return: t(take(&self.mc_return, 1), 1),
        }
    }

    /// Row `r`: (obs, action, s_T, kappa, G), for tests and inspection.
    pub fn row(&self, r: usize) -> (&[f32], &[f32], &[f32], f32, f32) {
        let (o, a) = (self.obs_dim, self.act_dim);
        (
            &self.obs[r * o..(r + 1) * o],
            &self.act[r * a..(r + 1) * a],
            &self.terminal_obs[r * o..(r + 1) * o],
            self.terminal_discount[r],
            self.mc_return[r],
        )
    }
}

impl Batch {
    /// The batch in another precision (the parity tests run in f64).
    pub fn to_kind(&self, kind: Kind) -> Batch {
        Batch {
            obs: self.obs.to_kind(kind),
            act: self.act.to_kind(kind),
            terminal_obs: self.terminal_obs.to_kind(kind),
            terminal_discount: self.terminal_discount.to_kind(kind),
            mc_return: self.mc_return.to_kind(kind),
        }
    }
}
