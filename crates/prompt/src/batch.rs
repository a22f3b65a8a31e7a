//! The multi-task training batch (`get_prompt_batch`, `promptdt-reference.md` b.6) and evaluation
//! prompts (d).

use crate::config::{PromptPosition, SamplerConfig, SamplerError};
use crate::normalize::StateNorm;
use crate::ranking::Ranking;
use crate::segment::{write_segment, SegmentOut};
use crate::Rng;
use pdt_data::{TaskData, Trajectory};
use rand::Rng as _;

/// Segments of `batch` samples, each `steps` long, as flat row-major host arrays.
///
/// # Shapes
/// `states [batch, steps, state_dim]`, `actions [batch, steps, act_dim]`,
/// `returns_to_go [batch, steps]` (already divided by the scale), `timesteps [batch, steps]`,
/// `mask [batch, steps]` (1 real, 0 left padding).
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentBatch {
    pub batch: usize,
    pub steps: usize,
    pub state_dim: usize,
    pub act_dim: usize,
    pub states: Vec<f32>,
    pub actions: Vec<f32>,
    pub returns_to_go: Vec<f32>,
    pub timesteps: Vec<i64>,
    pub mask: Vec<f32>,
}

impl SegmentBatch {
    pub(crate) fn zeros(batch: usize, steps: usize, state_dim: usize, act_dim: usize) -> Self {
        let n = batch * steps;
        Self {
            batch,
            steps,
            state_dim,
            act_dim,
            states: vec![0.0; n * state_dim],
            actions: vec![0.0; n * act_dim],
            returns_to_go: vec![0.0; n],
            timesteps: vec![0; n],
            mask: vec![0.0; n],
        }
    }

    /// The output slots of rows `row .. row + n_rows` (each row is one segment of `steps` steps).
    fn rows(&mut self, row: usize, n_rows: usize) -> SegmentOut<'_> {
        let (t, ds, da) = (self.steps, self.state_dim, self.act_dim);
        let (a, b) = (row * t, (row + n_rows) * t);
        SegmentOut {
            states: &mut self.states[a * ds..b * ds],
            actions: &mut self.actions[a * da..b * da],
            returns_to_go: &mut self.returns_to_go[a..b],
            timesteps: &mut self.timesteps[a..b],
            mask: &mut self.mask[a..b],
        }
    }
}

/// A training batch: for every training task, M prompts (from that task's P_i) and M history
/// segments (from its D_i), tasks concatenated in order along the batch axis.
#[derive(Debug, Clone, PartialEq)]
pub struct PromptDtBatch {
    /// `[B, J*H, ...]`: sample b's prompt is J segments of H steps, concatenated along time.
    pub prompt: SegmentBatch,
    /// `[B, K, ...]`
    pub history: SegmentBatch,
    /// `[B]`: index (into the sampler's task list) of each sample's task.
    pub task_of_sample: Vec<usize>,
}

/// One task as the sampler sees it.
#[derive(Debug)]
struct TaskSampler<'a> {
    data: &'a TaskData,
    ranking: Ranking,
}

/// Samples batches and evaluation prompts from a set of tasks. All randomness comes from the `Rng`
/// passed in, so a seed fixes every batch.
#[derive(Debug)]
pub struct BatchSampler<'a> {
    cfg: SamplerConfig,
    norm: StateNorm,
    tasks: Vec<TaskSampler<'a>>,
    state_dim: usize,
    act_dim: usize,
}

impl<'a> BatchSampler<'a> {
    /// `tasks` are the tasks batches are drawn from (in the order their samples appear), `norm` the
    /// state statistics, `n_positions` the model's token limit.
    pub fn new(
        cfg: SamplerConfig,
        tasks: &[&'a TaskData],
        norm: StateNorm,
        n_positions: usize,
    ) -> Result<Self, SamplerError> {
        cfg.validate(n_positions)?;
        let first =
            tasks.first().ok_or(SamplerError::Config { field: "tasks", why: "is empty".into() })?;
        let (state_dim, act_dim) = (first.dataset.obs_dim, first.dataset.act_dim);
        if norm.mean.len() != state_dim || norm.std.len() != state_dim {
            return Err(SamplerError::Config {
                field: "norm",
                why: format!("has {} dims, the data has {state_dim}", norm.mean.len()),
            });
        }
        let mut samplers = Vec::with_capacity(tasks.len());
        for t in tasks {
            for (which, d) in [("dataset", &t.dataset), ("prompts", &t.prompts)] {
                if d.obs_dim != state_dim || d.act_dim != act_dim {
                    return Err(SamplerError::Task {
                        task: t.id.to_string(),
                        why: format!(
                            "{which} has obs/act dims {}/{}, expected {state_dim}/{act_dim}",
                            d.obs_dim, d.act_dim
                        ),
                    });
                }
                if d.trajectories.is_empty() {
                    return Err(SamplerError::Task {
                        task: t.id.to_string(),
                        why: format!("{which} is empty"),
                    });
                }
            }
            samplers.push(TaskSampler { data: t, ranking: Ranking::new(&t.dataset, cfg.ranking) });
        }
        Ok(Self { cfg, norm, tasks: samplers, state_dim, act_dim })
    }

    pub fn config(&self) -> &SamplerConfig {
        &self.cfg
    }

    pub fn norm(&self) -> &StateNorm {
        &self.norm
    }

    pub fn state_dim(&self) -> usize {
        self.state_dim
    }

    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// Writes one prompt segment (returns-to-go kept) with this sampler's settings.
    pub(crate) fn write_one(&self, traj: &Trajectory, si: usize, len: usize, out: SegmentOut<'_>) {
        self.write(traj, si, len, false, out);
    }

    /// Writes one segment with this sampler's normalisation, return scale and timestep clip.
    fn write(
        &self,
        traj: &Trajectory,
        si: usize,
        len: usize,
        zero_returns: bool,
        out: SegmentOut<'_>,
    ) {
        let (norm, cfg) = (&self.norm, &self.cfg);
        write_segment(traj, si, len, norm, cfg.rtg_scale, cfg.max_ep_len, zero_returns, out);
    }

    /// Start index of a prompt segment in a demonstration of length `t`.
    fn prompt_start(&self, t: usize, rng: &mut Rng) -> usize {
        let h = self.cfg.prompt_length;
        match self.cfg.prompt_position {
            PromptPosition::Tail => t.saturating_sub(h + 1),
            PromptPosition::Random => rng.random_range(0..=t.saturating_sub(h)),
        }
    }

    /// Writes `n` prompts (J segments each) of task `task` into rows `row ..` of `out`.
    fn write_prompts(
        &self,
        task: usize,
        n: usize,
        row: usize,
        out: &mut SegmentBatch,
        rng: &mut Rng,
    ) {
        let demos = &self.tasks[task].data.prompts.trajectories;
        let (h, j) = (self.cfg.prompt_length, self.cfg.prompt_episodes);
        for s in 0..n * j {
            // Reference: the demonstration is drawn uniformly (its `p_sample` is commented out).
            let traj: &Trajectory = &demos[rng.random_range(0..demos.len())];
            let si = self.prompt_start(traj.len(), rng);
            // Draw s is segment (s % J) of sample (s / J): the J segments of a sample are
            // concatenated along time, as `flatten_prompt` reshapes them.
            let slots = out.rows(row + s / j, 1);
            let (ds, da) = (self.state_dim, self.act_dim);
            let seg = s % j;
            let slot = SegmentOut {
                states: &mut slots.states[seg * h * ds..(seg + 1) * h * ds],
                actions: &mut slots.actions[seg * h * da..(seg + 1) * h * da],
                returns_to_go: &mut slots.returns_to_go[seg * h..(seg + 1) * h],
                timesteps: &mut slots.timesteps[seg * h..(seg + 1) * h],
                mask: &mut slots.mask[seg * h..(seg + 1) * h],
            };
            // Prompt returns-to-go are never zeroed, not even for Prompt-MT-BC (reference b.6).
            self.write(traj, si, h, false, slot);
        }
    }

    /// Writes `n` history segments of task `task` into rows `row ..` of `out`.
    fn write_histories(
        &self,
        task: usize,
        n: usize,
        row: usize,
        out: &mut SegmentBatch,
        rng: &mut Rng,
    ) {
        let ts = &self.tasks[task];
        let k = self.cfg.k;
        for s in 0..n {
            let traj = &ts.data.dataset.trajectories[ts.ranking.pick(rng.random::<f64>())];
            // Any step may start a segment, the last one included (`random.randint(0, T - 1)`).
            let si = rng.random_range(0..traj.len());
            let slot = out.rows(row + s, 1);
            self.write(traj, si, k, self.cfg.zero_history_returns, slot);
        }
    }

    /// A training batch: M = `batch_size_per_task` samples of every task, in task order; per task,
    /// the prompts are drawn before the histories, as in the reference.
    pub fn sample(&self, rng: &mut Rng) -> PromptDtBatch {
        let m = self.cfg.batch_size_per_task;
        let b = m * self.tasks.len();
        let (ds, da) = (self.state_dim, self.act_dim);
        let mut prompt = SegmentBatch::zeros(b, self.cfg.prompt_steps(), ds, da);
        let mut history = SegmentBatch::zeros(b, self.cfg.k, ds, da);
        for task in 0..self.tasks.len() {
            self.write_prompts(task, m, task * m, &mut prompt, rng);
            self.write_histories(task, m, task * m, &mut history, rng);
        }
        let task_of_sample = (0..b).map(|i| i / m).collect();
        PromptDtBatch { prompt, history, task_of_sample }
    }

    /// One evaluation prompt for task `task` (J segments), as the reference draws it once per task
    /// per evaluation call and shares it across that task's episodes.
    pub fn eval_prompt(&self, task: usize, rng: &mut Rng) -> SegmentBatch {
        let mut prompt =
            SegmentBatch::zeros(1, self.cfg.prompt_steps(), self.state_dim, self.act_dim);
        self.write_prompts(task, 1, 0, &mut prompt, rng);
        prompt
    }

    /// `n` history segments of K steps of task `task`'s dataset D_i, drawn as a training batch
    /// draws its histories (trajectory by the history ranking, any step a start; returns-to-go
    /// zeroed where training's are). What an offline evaluation measures the model's actions on
    /// (`pdt_eval::offline`); consecutive calls draw what one call of their total would.
    pub fn history_segments(&self, task: usize, n: usize, rng: &mut Rng) -> SegmentBatch {
        let mut out = SegmentBatch::zeros(n, self.cfg.k, self.state_dim, self.act_dim);
        self.write_histories(task, n, 0, &mut out, rng);
        out
    }

    /// `n` segments of `len` steps from the tails of task `task`'s trajectories, the reference's
    /// `get_batch_finetune`: trajectories of the main dataset D_i drawn with the history-sampling
    /// weights (the ranking above), segment `si = T - len - 1`. It is the data MT-BC-Finetune adapts
    /// on. Returns-to-go are kept (reference pitfall 10).
    pub fn tail_segments(&self, task: usize, n: usize, len: usize, rng: &mut Rng) -> SegmentBatch {
        let ts = &self.tasks[task];
        let mut out = SegmentBatch::zeros(n, len, self.state_dim, self.act_dim);
        for row in 0..n {
            let traj = &ts.data.dataset.trajectories[ts.ranking.pick(rng.random::<f64>())];
            let si = traj.len().saturating_sub(len + 1);
            let slot = out.rows(row, 1);
            self.write(traj, si, len, false, slot);
        }
        out
    }

    /// `n` history segments of K steps from task `task`'s demonstrations (its prompt set P_i,
    /// the data a test task has): per segment a uniformly drawn demonstration and a uniformly
    /// drawn start, as training draws histories. What the evaluation-time adaptations learn from
    /// (`pdt_eval::testtime::adapt`); returns-to-go zeroed where the sampler zeroes the history's.
    pub fn demo_segments(&self, task: usize, n: usize, rng: &mut Rng) -> SegmentBatch {
        let demos = &self.tasks[task].data.prompts.trajectories;
        let k = self.cfg.k;
        let mut out = SegmentBatch::zeros(n, k, self.state_dim, self.act_dim);
        for row in 0..n {
            let traj = &demos[rng.random_range(0..demos.len())];
            let si = rng.random_range(0..traj.len());
            let slot = out.rows(row, 1);
            self.write(traj, si, k, self.cfg.zero_history_returns, slot);
        }
        out
    }

    pub fn num_tasks(&self) -> usize {
        self.tasks.len()
    }

    pub fn task(&self, i: usize) -> &TaskData {
        self.tasks[i].data
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TrajectoryRanking;
    use pdt_data::{TaskDataset, TaskId};
    use rand::SeedableRng;

    /// A task whose observations encode (task, trajectory, step), so tests can see what was drawn.
    /// Trajectory `i` has return `10 * (i + 1)` (trajectory 0 is the worst).
    fn task(task: usize, n_traj: usize, len: usize) -> TaskData {
        let make = |kind: f32| {
            let trajs = (0..n_traj)
                .map(|i| {
                    let obs =
                        (0..len).flat_map(|t| [task as f32, i as f32 + kind, t as f32]).collect();
                    let act = (0..len).map(|t| t as f32 / 1000.0).collect();
                    let mut rew = vec![0.0; len];
                    rew[0] = 10.0 * (i + 1) as f32;
                    Trajectory::new(3, 1, obs, act, rew, vec![false; len], vec![false; len])
                        .unwrap()
                })
                .collect();
            TaskDataset::new(trajs).unwrap()
        };
        // prompts are marked with +100 in the trajectory slot
        TaskData {
            id: TaskId { env: "toy".into(), index: task },
            dataset: make(0.0),
            prompts: make(100.0),
        }
    }

    fn cfg(k: usize, j: usize, h: usize) -> SamplerConfig {
        SamplerConfig {
            k,
            prompt_episodes: j,
            prompt_length: h,
            batch_size_per_task: 4,
            ..SamplerConfig::reference(10.0, 1000)
        }
    }

    fn rng(seed: u64) -> Rng {
        Rng::seed_from_u64(seed)
    }

    /// (task, trajectory, step) of row `b`, step `t` of a segment batch (identity normalisation).
    fn id(seg: &SegmentBatch, b: usize, t: usize) -> (f32, f32, f32) {
        let o = (b * seg.steps + t) * seg.state_dim;
        (seg.states[o], seg.states[o + 1], seg.states[o + 2])
    }

    #[test]
    fn batch_has_m_samples_per_task_in_task_order_with_prompts_from_the_same_task() {
        let tasks = [task(0, 3, 50), task(1, 3, 50), task(2, 3, 50)];
        let refs: Vec<&TaskData> = tasks.iter().collect();
        let s = BatchSampler::new(cfg(20, 1, 5), &refs, StateNorm::identity(3), 1024).unwrap();
        let b = s.sample(&mut rng(0));
        assert_eq!(
            (b.history.batch, b.history.steps, b.prompt.batch, b.prompt.steps),
            (12, 20, 12, 5)
        );
        assert_eq!(b.task_of_sample, vec![0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]);
        for row in 0..12 {
            let want = (row / 4) as f32;
            assert_eq!(id(&b.prompt, row, 4).0, want);
            assert!(id(&b.prompt, row, 4).1 >= 100.0, "prompts come from P_i");
            let last = id(&b.history, row, 19);
            assert_eq!(last.0, want);
            assert!(last.1 < 100.0, "histories come from D_i");
        }
        assert_eq!(b.history.states.len(), 12 * 20 * 3);
        assert_eq!(b.history.returns_to_go.len(), 12 * 20);
    }

    #[test]
    fn prompt_is_the_tail_segment_by_default() {
        // Reference: si = max(0, T - H - 1): steps 194..198 of a 200-step demonstration.
        let tasks = [task(0, 5, 200)];
        let s =
            BatchSampler::new(cfg(20, 1, 5), &[&tasks[0]], StateNorm::identity(3), 1024).unwrap();
        let b = s.sample(&mut rng(1));
        for row in 0..4 {
            let steps: Vec<f32> = (0..5).map(|t| id(&b.prompt, row, t).2).collect();
            assert_eq!(steps, vec![194., 195., 196., 197., 198.]);
            assert_eq!(&b.prompt.timesteps[row * 5..row * 5 + 5], &[194, 195, 196, 197, 198]);
            assert_eq!(&b.prompt.mask[row * 5..row * 5 + 5], &[1.0; 5]);
            // prompt return-to-go = suffix return from step 194 (0 here: only step 0 is rewarded)
            assert_eq!(&b.prompt.returns_to_go[row * 5..row * 5 + 5], &[0.0; 5]);
        }
        let p = s.eval_prompt(0, &mut rng(2));
        assert_eq!((p.batch, p.steps), (1, 5));
        assert_eq!(p.timesteps, vec![194, 195, 196, 197, 198]);
    }

    #[test]
    fn random_prompt_position_stays_inside_the_trajectory_and_varies() {
        let tasks = [task(0, 5, 30)];
        let c = SamplerConfig { prompt_position: PromptPosition::Random, ..cfg(20, 1, 5) };
        let s = BatchSampler::new(c, &[&tasks[0]], StateNorm::identity(3), 1024).unwrap();
        let mut starts = std::collections::BTreeSet::new();
        let mut r = rng(3);
        for _ in 0..200 {
            let p = s.eval_prompt(0, &mut r);
            assert_eq!(p.mask, vec![1.0; 5]);
            let t0 = p.timesteps[0];
            assert_eq!(p.timesteps, (t0..t0 + 5).collect::<Vec<_>>());
            assert!((0..=25).contains(&t0));
            starts.insert(t0);
        }
        assert!(starts.len() > 20, "segments start anywhere in 0..=T-H, saw {starts:?}");
        assert!(starts.contains(&0) && starts.contains(&25));
    }

    #[test]
    fn j_prompt_segments_are_concatenated_along_time() {
        let tasks = [task(0, 7, 40)];
        let s =
            BatchSampler::new(cfg(20, 3, 4), &[&tasks[0]], StateNorm::identity(3), 1024).unwrap();
        let b = s.sample(&mut rng(4));
        assert_eq!(b.prompt.steps, 12);
        for row in 0..4 {
            let ts = &b.prompt.timesteps[row * 12..row * 12 + 12];
            assert_eq!(ts, &[35, 36, 37, 38, 35, 36, 37, 38, 35, 36, 37, 38]);
        }
        // each of the J segments draws its own demonstration: over a batch, they are not all equal
        let trajs: std::collections::BTreeSet<u32> =
            (0..4).flat_map(|r| [0, 4, 8].map(|t| id(&b.prompt, r, t).1 as u32)).collect();
        assert!(trajs.len() > 1);
    }

    #[test]
    fn history_segments_start_anywhere_pad_left_and_carry_suffix_returns() {
        let tasks = [task(0, 4, 30)];
        let s =
            BatchSampler::new(cfg(20, 1, 5), &[&tasks[0]], StateNorm::identity(3), 1024).unwrap();
        let mut r = rng(5);
        let (mut padded, mut saw_last_step_start) = (0, false);
        for _ in 0..300 {
            let b = s.sample(&mut r);
            for row in 0..4 {
                let mask = &b.history.mask[row * 20..row * 20 + 20];
                let tlen = mask.iter().filter(|&&m| m == 1.0).count();
                assert!(mask[..20 - tlen].iter().all(|&m| m == 0.0), "padding is on the left");
                let (_, traj, first) = id(&b.history, row, 20 - tlen);
                let si = first as usize;
                assert_eq!(tlen, 20.min(30 - si));
                assert_eq!(b.history.timesteps[row * 20 + 20 - tlen], si as i64);
                padded += usize::from(tlen < 20);
                saw_last_step_start |= si == 29;
                for p in 0..20 - tlen {
                    assert_eq!(b.history.actions[row * 20 + p], crate::segment::ACTION_PAD);
                    assert_eq!(b.history.returns_to_go[row * 20 + p], 0.0);
                }
                // return-to-go at the first real step: the trajectory's return if si == 0, else 0
                let want = if si == 0 { (traj + 1.0) * 10.0 / 10.0 } else { 0.0 };
                assert_eq!(b.history.returns_to_go[row * 20 + 20 - tlen], want);
            }
        }
        assert!(padded > 0 && saw_last_step_start);
    }

    #[test]
    fn reference_ranking_never_samples_the_lowest_return_trajectory() {
        let tasks = [task(0, 4, 10)];
        let mut seen = [0usize; 4];
        for (ranking, never) in
            [(TrajectoryRanking::ReferenceOffByOne, Some(0)), (TrajectoryRanking::All, None)]
        {
            seen = [0; 4];
            let c = SamplerConfig { ranking, ..cfg(5, 1, 2) };
            let s = BatchSampler::new(c, &[&tasks[0]], StateNorm::identity(3), 1024).unwrap();
            let mut r = rng(6);
            for _ in 0..500 {
                let b = s.sample(&mut r);
                for row in 0..4 {
                    seen[id(&b.history, row, 4).1 as usize] += 1;
                }
            }
            match never {
                Some(i) => assert_eq!(seen[i], 0, "{seen:?}"),
                None => assert!(seen.iter().all(|&n| n > 300), "{seen:?}"),
            }
        }
        assert!(seen.iter().all(|&n| n > 0));
    }

    #[test]
    fn states_are_normalised_and_prompt_mt_bc_zeroes_only_history_returns() {
        let tasks = [task(0, 3, 10)];
        let norm = StateNorm { mean: vec![0.0, 1.0, 2.0], std: vec![1.0, 2.0, 4.0] };
        let c = SamplerConfig { zero_history_returns: true, ..cfg(5, 1, 9) };
        let s = BatchSampler::new(c, &[&tasks[0]], norm, 1024).unwrap();
        let b = s.sample(&mut rng(7));
        assert!(b.history.returns_to_go.iter().all(|&r| r == 0.0));
        // prompt tail from step 0 (T - H - 1 = 0) keeps its return-to-go (the whole return)
        assert!(b.prompt.returns_to_go.iter().step_by(9).all(|&r| r > 0.0));
        let (_, _, step) = id(&b.prompt, 0, 3);
        assert_eq!(step, (3.0 - 2.0) / 4.0);
    }

    #[test]
    fn lengths_that_break_the_reference_work() {
        // JH = K (pitfall 6) and JH = 1, 11, 21 (pitfall 7), and prompts longer than demonstrations.
        let tasks = [task(0, 3, 15), task(1, 3, 15)];
        let refs: Vec<&TaskData> = tasks.iter().collect();
        for (k, j, h) in
            [(20, 1, 20), (20, 2, 10), (5, 1, 1), (20, 1, 11), (20, 3, 7), (1, 1, 21), (20, 1, 15)]
        {
            let s = BatchSampler::new(cfg(k, j, h), &refs, StateNorm::identity(3), 1024).unwrap();
            let b = s.sample(&mut rng(8));
            assert_eq!((b.prompt.steps, b.history.steps, b.prompt.batch), (j * h, k, 8));
            assert_eq!(b.prompt.returns_to_go.len(), 8 * j * h);
            // a prompt segment longer than the demonstration is left-padded
            if h > 14 {
                assert_eq!(b.prompt.mask[..h - 15].iter().sum::<f32>(), 0.0);
            }
        }
        // the token limit: 3 * (JH + K) <= n_positions
        assert!(BatchSampler::new(cfg(20, 1, 322), &refs, StateNorm::identity(3), 1024).is_err());
        assert!(BatchSampler::new(cfg(20, 1, 322), &refs, StateNorm::identity(3), 1026).is_ok());
    }

    #[test]
    fn finetune_segments_are_demonstration_tails() {
        let tasks = [task(0, 3, 50)];
        let s =
            BatchSampler::new(cfg(20, 1, 5), &[&tasks[0]], StateNorm::identity(3), 1024).unwrap();
        let b = s.tail_segments(0, 6, 5, &mut rng(11));
        assert_eq!((b.batch, b.steps), (6, 5));
        for row in 0..6 {
            assert_eq!(&b.timesteps[row * 5..row * 5 + 5], &[44, 45, 46, 47, 48]);
            let traj = id(&b, row, 0).1;
            assert!(
                (1.0..3.0).contains(&traj),
                "from D_i, never its lowest-return trajectory 0: {traj}"
            );
        }
    }

    #[test]
    fn same_seed_same_batch_different_seed_different_batch() {
        let tasks = [task(0, 5, 40), task(1, 5, 40)];
        let refs: Vec<&TaskData> = tasks.iter().collect();
        let c = SamplerConfig { prompt_position: PromptPosition::Random, ..cfg(20, 2, 5) };
        let s = BatchSampler::new(c, &refs, StateNorm::identity(3), 1024).unwrap();
        assert_eq!(s.sample(&mut rng(9)), s.sample(&mut rng(9)));
        assert_ne!(s.sample(&mut rng(9)), s.sample(&mut rng(10)));
    }

    #[test]
    fn bad_settings_and_data_are_rejected_with_the_field_named() {
        let tasks = [task(0, 3, 10)];
        let err = |c: SamplerConfig, n: StateNorm| {
            BatchSampler::new(c, &[&tasks[0]], n, 1024).unwrap_err().to_string()
        };
        assert!(err(cfg(0, 1, 5), StateNorm::identity(3)).contains("`k`"));
        assert!(err(SamplerConfig { rtg_scale: 0.0, ..cfg(5, 1, 5) }, StateNorm::identity(3))
            .contains("rtg_scale"));
        assert!(err(cfg(5, 1, 5), StateNorm::identity(2)).contains("norm"));
        assert!(BatchSampler::new(cfg(5, 1, 5), &[], StateNorm::identity(3), 1024).is_err());
    }
}
