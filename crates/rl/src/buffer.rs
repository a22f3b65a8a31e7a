//! The replay buffer shared by SAC and TD3: flat host arrays in insertion order, never overwritten
//! (capacity = the training budget), sampled uniformly into one reused set of host vectors.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Tensor};

/// One transition, as the agent sees it (observations already task-conditioned).
#[derive(Debug, Clone, Copy)]
pub struct Transition<'a> {
    pub obs: &'a [f32],
    pub action: &'a [f32],
    pub reward: f32,
    pub next_obs: &'a [f32],
    /// The MDP ended: no bootstrapping from `next_obs`. A time-limit cut is *not* terminal.
    pub terminated: bool,
}

/// A sampled minibatch on the training device.
#[derive(Debug)]
pub struct Batch {
    /// `[B, obs_dim]`
    pub obs: Tensor,
    /// `[B, act_dim]`
    pub actions: Tensor,
    /// `[B, 1]`
    pub rewards: Tensor,
    /// `[B, obs_dim]`
    pub next_obs: Tensor,
    /// `[B, 1]`: 1 - terminated.
    pub not_done: Tensor,
}

/// A buffer's contents as stored in a checkpoint (row-major, insertion order).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BufferArrays {
    pub obs: Vec<f32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub next_obs: Vec<f32>,
    pub terminated: Vec<f32>,
}

/// Transitions in insertion order (which dataset extraction and checkpoints rely on).
#[derive(Debug, Clone, PartialEq)]
pub struct ReplayBuffer {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub capacity: usize,
    pub obs: Vec<f32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub next_obs: Vec<f32>,
    pub terminated: Vec<f32>,
    scratch: Scratch,
}

#[derive(Debug, Clone, PartialEq, Default)]
struct Scratch {
    obs: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    next_obs: Vec<f32>,
    not_done: Vec<f32>,
}

impl ReplayBuffer {
    pub fn new(obs_dim: usize, act_dim: usize, capacity: usize) -> Self {
        Self {
            obs_dim,
            act_dim,
            capacity,
            obs: Vec::with_capacity(capacity * obs_dim),
            actions: Vec::with_capacity(capacity * act_dim),
            rewards: Vec::with_capacity(capacity),
            next_obs: Vec::with_capacity(capacity * obs_dim),
            terminated: Vec::with_capacity(capacity),
            scratch: Scratch::default(),
        }
    }

    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// Appends a transition; `false` (and nothing stored) when the buffer is full or the sizes
    /// are wrong.
    pub fn push(&mut self, t: Transition<'_>) -> bool {
        if self.len() >= self.capacity
            || t.obs.len() != self.obs_dim
            || t.next_obs.len() != self.obs_dim
            || t.action.len() != self.act_dim
        {
            return false;
        }
        self.obs.extend_from_slice(t.obs);
        self.actions.extend_from_slice(t.action);
        self.rewards.push(t.reward);
        self.next_obs.extend_from_slice(t.next_obs);
        self.terminated.push(if t.terminated { 1.0 } else { 0.0 });
        true
    }

    /// `batch` transitions drawn uniformly with replacement (the buffer must not be empty).
    pub fn sample(&mut self, batch: usize, rng: &mut ChaCha8Rng, device: Device) -> Batch {
        self.sample_recent(batch, 0, rng, device)
    }

    /// Like [`sample`](Self::sample), from the most recent `window` transitions only (all of them
    /// when `window` is 0 or at least the buffer's length).
    pub fn sample_recent(
        &mut self,
        batch: usize,
        window: usize,
        rng: &mut ChaCha8Rng,
        device: Device,
    ) -> Batch {
        let (n, d, a) = (self.len().max(1), self.obs_dim, self.act_dim);
        let lo = if window == 0 { 0 } else { n.saturating_sub(window) };
        let s = &mut self.scratch;
        s.obs.clear();
        s.actions.clear();
        s.rewards.clear();
        s.next_obs.clear();
        s.not_done.clear();
        for _ in 0..batch {
            let i = lo + rng.random_range(0..n - lo);
            s.obs.extend_from_slice(&self.obs[i * d..(i + 1) * d]);
            s.actions.extend_from_slice(&self.actions[i * a..(i + 1) * a]);
            s.rewards.push(self.rewards[i]);
            s.next_obs.extend_from_slice(&self.next_obs[i * d..(i + 1) * d]);
            s.not_done.push(1.0 - self.terminated[i]);
        }
        let b = batch as i64;
        let up =
            |v: &[f32], cols: usize| Tensor::from_slice(v).view([b, cols as i64]).to_device(device);
        Batch {
            obs: up(&s.obs, d),
            actions: up(&s.actions, a),
            rewards: up(&s.rewards, 1),
            next_obs: up(&s.next_obs, d),
            not_done: up(&s.not_done, 1),
        }
    }

    /// Restores from stored arrays, checking that their lengths agree.
    pub fn from_parts(
        obs_dim: usize,
        act_dim: usize,
        capacity: usize,
        arrays: BufferArrays,
    ) -> Result<Self, String> {
        let BufferArrays { obs, actions, rewards, next_obs, terminated } = arrays;
        let n = rewards.len();
        let checks = [
            ("obs", obs.len(), n * obs_dim),
            ("actions", actions.len(), n * act_dim),
            ("next_obs", next_obs.len(), n * obs_dim),
            ("terminated", terminated.len(), n),
        ];
        for (name, got, want) in checks {
            if got != want {
                return Err(format!("replay buffer `{name}` has {got} values, expected {want}"));
            }
        }
        if n > capacity {
            return Err(format!("replay buffer holds {n} transitions, capacity is {capacity}"));
        }
        let mut buf = Self::new(obs_dim, act_dim, capacity);
        buf.obs = obs;
        buf.actions = actions;
        buf.rewards = rewards;
        buf.next_obs = next_obs;
        buf.terminated = terminated;
        Ok(buf)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn sample_recent_draws_from_the_window_and_whole_buffer_draws_are_unchanged() {
        let mut b = ReplayBuffer::new(1, 1, 100);
        for i in 0..100 {
            let x = [i as f32];
            b.push(Transition {
                obs: &x,
                action: &x,
                reward: i as f32,
                next_obs: &x,
                terminated: false,
            });
        }
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let r = b.sample_recent(500, 10, &mut rng, Device::Cpu).rewards;
        let v: Vec<f32> = Vec::<f32>::try_from(r.view([-1])).unwrap();
        assert!(v.iter().all(|&x| (90.0..100.0).contains(&x)), "{v:?}");
        assert!(v.contains(&90.0) && v.contains(&99.0));
        // Window 0 and a window larger than the buffer are the plain sample, draw for draw.
        for w in [0, 100, 1000] {
            let (mut r1, mut r2) = (ChaCha8Rng::seed_from_u64(2), ChaCha8Rng::seed_from_u64(2));
            let a = b.sample(64, &mut r1, Device::Cpu).rewards;
            let c = b.sample_recent(64, w, &mut r2, Device::Cpu).rewards;
            assert!(a.equal(&c), "window {w}");
        }
    }

    #[test]
    fn push_keeps_order_and_refuses_bad_sizes_and_overflow() {
        let mut b = ReplayBuffer::new(2, 1, 2);
        let push = |b: &mut ReplayBuffer, x: f32, obs: &[f32]| {
            b.push(Transition {
                obs,
                action: &[x],
                reward: x,
                next_obs: &[x + 1.0, x + 1.0],
                terminated: x > 1.0,
            })
        };
        assert!(push(&mut b, 0.0, &[0.0, 0.0]));
        assert!(!push(&mut b, 0.0, &[0.0]), "wrong obs size");
        assert!(push(&mut b, 2.0, &[2.0, 2.0]));
        assert!(!push(&mut b, 3.0, &[3.0, 3.0]), "full");
        assert_eq!(b.rewards, vec![0.0, 2.0]);
        assert_eq!(b.terminated, vec![0.0, 1.0]);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let batch = b.sample(64, &mut rng, Device::Cpu);
        assert_eq!(batch.obs.size(), vec![64, 2]);
        // Rows stay consistent: next_obs = obs + 1, not_done = 1 - (reward > 1).
        let diff = (&batch.next_obs - &batch.obs - 1.0).abs().max().double_value(&[]);
        assert_eq!(diff, 0.0);
        let nd = (&batch.not_done - (batch.rewards.le(1.0)).to_kind(tch::Kind::Float))
            .abs()
            .max()
            .double_value(&[]);
        assert_eq!(nd, 0.0);
    }
}
