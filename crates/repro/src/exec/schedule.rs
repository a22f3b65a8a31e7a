//! The loop of [`super::execute`]: up to `jobs` child processes at once, each one run or a pack of
//! compatible runs, started in plan order; a run another process holds waits and is tried again
//! every poll; a finished child's runs are counted, and a failed one's named with its log's tail.

use super::{claim, command, iterations_done, pack_command, parent_pipe, write_atomic};
use super::{Job, Member};
use crate::exec_types::{ExecOptions, ExecSummary, Progress, Stage};
use crate::plan::{self, Plan, RunSpec, RunState};
use crate::ReproError;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// The runs of one `execute` and where each stands.
pub(super) struct Scheduler<'p> {
    plan: &'p Plan,
    opts: &'p ExecOptions,
    runs_total: usize,
    iterations_total: u64,
    pub summary: ExecSummary,
    /// Iterations done per run: read once, then only for the runs in progress (a paper sweep has
    /// dozens of metrics files of thousands of lines; the finished ones do not change).
    done: Vec<u64>,
    /// Runs to do, in plan order.
    queue: VecDeque<(usize, &'p RunSpec)>,
    /// Runs another process held when last tried.
    waiting: Vec<(usize, &'p RunSpec)>,
    /// Every run that ever waited, by key.
    waited: Vec<String>,
    running: Vec<Job<'p>>,
    finished: usize,
}

impl<'p> Scheduler<'p> {
    /// `runs` (with their states, read before) to do; `done`: their iterations done.
    pub fn new(
        plan: &'p Plan,
        opts: &'p ExecOptions,
        runs: &[&'p RunSpec],
        states: &[RunState],
        done: Vec<u64>,
    ) -> Self {
        let mut summary = ExecSummary::default();
        let mut queue = VecDeque::new();
        for (i, (r, s)) in runs.iter().zip(states).enumerate() {
            match s {
                RunState::Finished => summary.already_finished += 1,
                RunState::Partial { .. } | RunState::New => queue.push_back((i, *r)),
            }
        }
        Self {
            plan,
            opts,
            runs_total: runs.len(),
            iterations_total: runs.iter().map(|r| r.config.train.iterations).sum(),
            finished: summary.already_finished,
            summary,
            done,
            queue,
            waiting: Vec::new(),
            waited: Vec::new(),
            running: Vec::new(),
        }
    }

    /// What the progress callback sees now.
    pub fn progress(&self, stage: Stage) -> Progress {
        let members = self.running.iter().flat_map(|j| &j.members);
        Progress {
            stage,
            runs_total: self.runs_total,
            runs_finished: self.finished,
            iterations_done: self.done.iter().sum(),
            iterations_total: self.iterations_total,
            running: members.map(|m| m.spec.key.clone()).collect(),
            waiting: self.waiting.iter().map(|(_, s)| s.key.clone()).collect(),
        }
    }

    /// Runs every run to its end (or failure), polling the children.
    pub fn run(&mut self, progress: &mut dyn FnMut(&Progress)) -> Result<(), ReproError> {
        let mut last = Instant::now() - Duration::from_secs(10);
        loop {
            self.start_jobs()?;
            if self.running.is_empty() && self.waiting.is_empty() && self.queue.is_empty() {
                break;
            }
            self.reap()?;
            if last.elapsed() >= Duration::from_secs(2) {
                for m in self.running.iter().flat_map(|j| &j.members) {
                    self.done[m.index] = iterations_done(m.spec);
                }
                progress(&self.progress(Stage::Training));
                last = Instant::now();
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        self.summary.waited = std::mem::take(&mut self.waited);
        Ok(())
    }

    /// Starts jobs while a slot is free: the runs that waited first (they are the older ones in
    /// plan order), then the queue's. Runs not reached (every slot busy) wait their turn again.
    fn start_jobs(&mut self) -> Result<(), ReproError> {
        let mut candidates: VecDeque<(usize, &RunSpec)> = self.waiting.drain(..).collect();
        while self.running.len() < self.opts.jobs.max(1) {
            let Some(next) = candidates.pop_front().or_else(|| self.queue.pop_front()) else {
                break;
            };
            let picked = self.pack_with(next, &mut candidates);
            let members = self.claim_all(picked)?;
            if !members.is_empty() {
                self.spawn(members)?;
            }
        }
        self.waiting.extend(candidates);
        Ok(())
    }

    /// The run, then (with packs) the compatible runs after it.
    fn pack_with(
        &mut self,
        first: (usize, &'p RunSpec),
        candidates: &mut VecDeque<(usize, &'p RunSpec)>,
    ) -> Vec<(usize, &'p RunSpec)> {
        let mut picked = vec![first];
        let Some(key) = crate::packs::pack_key(first.1).filter(|_| self.opts.pack > 1) else {
            return picked;
        };
        for deque in [candidates, &mut self.queue] {
            let mut i = 0;
            while i < deque.len() && picked.len() < self.opts.pack {
                if crate::packs::pack_key(deque[i].1).as_ref() == Some(&key) {
                    picked.extend(deque.remove(i));
                } else {
                    i += 1;
                }
            }
        }
        picked
    }

    /// Each picked run claimed and read again now that it is ours (another process may have
    /// finished or advanced it); a run another process holds goes to `waiting`.
    fn claim_all(
        &mut self,
        picked: Vec<(usize, &'p RunSpec)>,
    ) -> Result<Vec<Member<'p>>, ReproError> {
        let mut members = Vec::new();
        for (index, spec) in picked {
            let Some(claimed) = claim(spec)? else {
                if !self.waited.contains(&spec.key) {
                    self.waited.push(spec.key.clone());
                }
                self.waiting.push((index, spec));
                continue;
            };
            let state = match plan::state(spec) {
                Ok(s) => s,
                Err(e) => {
                    self.summary.failed.push((spec.key.clone(), e.to_string()));
                    self.finished += 1;
                    continue;
                }
            };
            match state {
                RunState::Finished => {
                    self.summary.finished_elsewhere += 1;
                    self.finished += 1;
                    self.done[index] = iterations_done(spec);
                    continue;
                }
                RunState::Partial { .. } => self.summary.resumed += 1,
                RunState::New => {
                    self.summary.started += 1;
                    let text = spec
                        .config
                        .to_toml()
                        .map_err(|e| ReproError::Invalid(format!("run {}: {e}", spec.key)))?;
                    write_atomic(&spec.config_path, &text)?;
                }
            }
            members.push(Member { index, spec, state, _claim: claimed });
        }
        Ok(members)
    }

    /// Starts the child that trains `members` (one run, or a pack), its output appended to the
    /// first run's log.
    fn spawn(&mut self, members: Vec<Member<'p>>) -> Result<(), ReproError> {
        let opts = self.opts;
        let log_path = members[0].spec.log_path.clone();
        let io = |path: &std::path::Path| {
            let path = path.to_path_buf();
            move |source| ReproError::Io { path, source }
        };
        if let Some(p) = log_path.parent() {
            std::fs::create_dir_all(p).map_err(io(p))?;
        }
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .map_err(io(log_path.as_path()))?;
        let err = log.try_clone().map_err(io(log_path.as_path()))?;
        let (stdin, parent_end) = parent_pipe(&opts.exe)?;
        let mut cmd = match members.as_slice() {
            [one] => command(one.spec, one.state, opts)?,
            many => pack_command(&self.plan.out, many, opts)?,
        };
        let child =
            cmd.stdin(stdin).stdout(log).stderr(err).spawn().map_err(io(opts.exe.as_path()))?;
        self.running.push(Job { members, child, log_path, _parent_end: parent_end });
        Ok(())
    }

    /// Counts the children that ended; a failed one's runs (in a pack, those that did not
    /// finish) are named with the last lines of its log.
    fn reap(&mut self) -> Result<(), ReproError> {
        let mut i = 0;
        while i < self.running.len() {
            let status = match self.running[i].child.try_wait() {
                Ok(Some(status)) => status,
                Ok(None) => {
                    i += 1;
                    continue;
                }
                Err(e) => {
                    let dir = self.running[i].members.first().map(|m| m.spec.dir.clone());
                    return Err(ReproError::Io { path: dir.unwrap_or_default(), source: e });
                }
            };
            let job = self.running.swap_remove(i);
            for m in &job.members {
                self.done[m.index] = iterations_done(m.spec);
                self.finished += 1;
            }
            if status.success() {
                continue;
            }
            let tail = std::fs::read_to_string(&job.log_path).unwrap_or_default();
            let tail: Vec<&str> = tail.lines().rev().take(5).collect();
            let message = format!(
                "{status}; last lines of {}: {}",
                job.log_path.display(),
                tail.into_iter().rev().collect::<Vec<_>>().join(" | ")
            );
            for m in &job.members {
                let whole = job.members.len() == 1;
                if whole || !matches!(plan::state(m.spec), Ok(RunState::Finished)) {
                    self.summary.failed.push((m.spec.key.clone(), message.clone()));
                }
            }
        }
        Ok(())
    }
}
