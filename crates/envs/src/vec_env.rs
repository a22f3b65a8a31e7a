//! [`VecEnv`]: N environments stepped together on a pool of persistent worker threads.
//!
//! Each environment owns its simulator state and draws its reset noise from its own RNG, seeded by
//! the seed given for it; environments share nothing mutable. So the results depend only on the
//! environments, seeds and actions, never on the number of threads or on scheduling.
//!
//! Threads. `VecEnv::new(envs, threads)` deals the environments round-robin into
//! `t = min(threads, N)` chunks (environment `i` goes to chunk `i % t`). Chunk 0 stays on the
//! calling thread; every other chunk is moved, once, to its own worker thread (`promptdt-env-{c}`),
//! which owns it and waits on a channel for commands (reset, step). A call sends each worker its
//! part, steps chunk 0 meanwhile, then collects the workers' replies in chunk order. Starting
//! threads once instead of on every call matters: a scoped thread start cost about 100 µs per step
//! against about 370 µs of physics for a batch of HalfCheetahs. Dealing round-robin instead of in
//! contiguous chunks keeps the threads evenly loaded when only a window of the environments is
//! stepped (the batched evaluation steps one batch of episodes at a time).
//!
//! Elsewhere. A `VecEnv` made by [`VecEnv::external`] has no threads: its environments live behind
//! a [`Backend`] (a Python worker process, [`crate::worker`]), which gets one call per vector reset
//! or step (all the environments concerned at once), not one per environment. The same methods
//! step either kind, so the rollouts and evaluations above do not know where the environments are.
//!
//! Panics. An environment that panics on a worker thread ends that thread. The caller sees its
//! reply channel disconnect, joins it and re-raises its panic (`resume_unwind`) once the other
//! workers have answered; a panic in chunk 0 is re-raised the same way. The `VecEnv` is then broken
//! (some environments are lost or half-stepped): its later calls return an error.

use std::any::Any;
use std::iter::StepBy;
use std::ops::Range;
use std::panic::{self, AssertUnwindSafe};
use std::sync::mpsc::{self, Receiver, Sender};
use std::thread::JoinHandle;

use crate::render::{Frame, FrameSize, RenderError};
use crate::{Env, EnvError, StepResult};

/// One environment's outcome in a masked step: `None` where it was not stepped.
pub type StepSlot = Option<Result<StepResult, EnvError>>;

/// An environment's sizes, read at construction (the environments themselves may live on worker
/// threads, out of the caller's reach).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EnvDims {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Time limit: `step` reports `truncated` at this many steps.
    pub horizon: usize,
}

/// Environments that live outside this process's threads, stepped by one call per vector reset or
/// step. Each call answers one slot per environment, in order (`None` where the environment was not
/// concerned); a failure of one environment goes in its slot, a failure of the whole backend (it
/// died, hung, or answered nonsense) is the call's error, after which the backend is unusable.
pub trait Backend: Send {
    /// Resets environment `i` with `seeds[i]` where that is given (one entry per environment);
    /// answers its first observation there.
    fn reset(&mut self, seeds: &[Option<u64>]) -> Result<Vec<Option<Vec<f32>>>, EnvError>;

    /// Steps the environments whose `mask` entry is true, each with its slice
    /// ([`VecEnv::action_range`]) of `actions`.
    fn step(&mut self, actions: &[f32], mask: &[bool]) -> Result<Vec<StepSlot>, EnvError>;
}

/// Where a [`VecEnv`]'s environments are.
enum Envs {
    /// On this process's threads.
    Pool(Pool),
    /// Behind a [`Backend`].
    External(Box<dyn Backend>),
}

/// A batch of environments (possibly of different tasks) stepped in parallel.
pub struct VecEnv {
    envs: Envs,
    dims: Vec<EnvDims>,
    /// `act_offsets[i]..act_offsets[i + 1]`: environment `i`'s action in a flat action buffer.
    act_offsets: Vec<usize>,
}

impl VecEnv {
    /// Spreads the environments over `min(threads, envs.len())` threads, the calling one included
    /// (0 or 1: everything on the calling thread, no worker started). Should the system refuse to
    /// start a thread, the environments are spread over the threads that did start (a warning is
    /// logged): the results are the same either way.
    pub fn new(envs: Vec<Box<dyn Env>>, threads: usize) -> Self {
        let dims: Vec<EnvDims> = envs
            .iter()
            .map(|e| EnvDims { obs_dim: e.obs_dim(), act_dim: e.act_dim(), horizon: e.horizon() })
            .collect();
        let act_offsets = offsets(&dims);
        Self { envs: Envs::Pool(Pool::new(envs, threads)), dims, act_offsets }
    }

    /// Environments of sizes `dims` (in order) that live behind `backend`.
    pub fn external(backend: Box<dyn Backend>, dims: Vec<EnvDims>) -> Self {
        Self { envs: Envs::External(backend), act_offsets: offsets(&dims), dims }
    }

    pub fn len(&self) -> usize {
        self.dims.len()
    }

    pub fn is_empty(&self) -> bool {
        self.dims.is_empty()
    }

    /// Threads stepping the environments, the calling thread included (1 to `len()`; 1 for
    /// environments behind a [`Backend`]).
    pub fn threads(&self) -> usize {
        match &self.envs {
            Envs::Pool(pool) => pool.threads(),
            Envs::External(_) => 1,
        }
    }

    /// Each environment's sizes, in order.
    pub fn dims(&self) -> &[EnvDims] {
        &self.dims
    }

    /// Length of the flat action buffer [`VecEnv::step_flat`] takes: the sum of the action sizes.
    pub fn flat_action_len(&self) -> usize {
        self.act_offsets.last().copied().unwrap_or(0)
    }

    /// Where environment `i`'s action goes in the flat action buffer (`None`: no such environment).
    pub fn action_range(&self, i: usize) -> Option<Range<usize>> {
        Some(*self.act_offsets.get(i)?..*self.act_offsets.get(i + 1)?)
    }

    /// Resets environment `i` with `seeds[i]`; returns the first observations, in order.
    pub fn reset(&mut self, seeds: &[u64]) -> Result<Vec<Vec<f32>>, EnvError> {
        self.check_len("seeds", seeds.len())?;
        let obs = self.reset_with(|i| seeds.get(i).copied())?;
        obs.into_iter().collect::<Option<Vec<_>>>().ok_or_else(|| missing("reset"))
    }

    /// Resets only the environments named, each `(index, seed)` once; returns their first
    /// observations in the order given. The other environments are left as they are.
    pub fn reset_some(&mut self, resets: &[(usize, u64)]) -> Result<Vec<Vec<f32>>, EnvError> {
        let mut seeds: Vec<Option<u64>> = vec![None; self.len()];
        for &(i, seed) in resets {
            match seeds.get_mut(i) {
                None => {
                    return Err(vec_error(format!(
                        "no environment {i} to reset (there are {})",
                        self.len()
                    )))
                }
                Some(Some(_)) => {
                    return Err(vec_error(format!("environment {i} is reset twice in one call")))
                }
                Some(slot) => *slot = Some(seed),
            }
        }
        let mut obs = self.reset_with(|i| seeds.get(i).copied().flatten())?;
        resets
            .iter()
            .map(|&(i, _)| obs.get_mut(i).and_then(Option::take))
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| missing("reset"))
    }

    /// Steps environment `i` with `actions[i]`. Each environment's outcome is its own: an
    /// environment that refuses its action (wrong size, not finite, episode over) is left as it
    /// was and reports the error in its slot, while the others step.
    pub fn step(
        &mut self,
        actions: &[Vec<f32>],
    ) -> Result<Vec<Result<StepResult, EnvError>>, EnvError> {
        self.check_len("actions", actions.len())?;
        let out = match &mut self.envs {
            Envs::Pool(pool) => pool.step_with(|i| actions.get(i).map(Vec::as_slice))?,
            Envs::External(_) => self.step_external_each(actions)?,
        };
        out.into_iter().collect::<Option<Vec<_>>>().ok_or_else(|| missing("stepped"))
    }

    /// Steps the environments whose `mask` entry is true (all of them without a mask), each with
    /// its slice [`VecEnv::action_range`] of `actions` (`flat_action_len()` values; the slices of
    /// masked-out environments are ignored). Returns one slot per environment: `None` where it was
    /// not stepped, otherwise its own outcome as in [`VecEnv::step`]. No per-environment action
    /// vectors are needed, and masked-out environments are not touched.
    pub fn step_flat(
        &mut self,
        actions: &[f32],
        mask: Option<&[bool]>,
    ) -> Result<Vec<StepSlot>, EnvError> {
        if actions.len() != self.flat_action_len() {
            return Err(vec_error(format!(
                "{} action values for environments taking {}",
                actions.len(),
                self.flat_action_len()
            )));
        }
        if let Some(mask) = mask {
            self.check_len("mask entries", mask.len())?;
        }
        let offsets = &self.act_offsets;
        match &mut self.envs {
            Envs::Pool(pool) => pool.step_with(|i| {
                let wanted = mask.is_none_or(|m| m.get(i) == Some(&true));
                let range = *offsets.get(i)?..*offsets.get(i + 1)?;
                wanted.then(|| actions.get(range)).flatten()
            }),
            Envs::External(backend) => {
                let all;
                let mask = match mask {
                    Some(m) => m,
                    None => {
                        all = vec![true; self.dims.len()];
                        &all
                    }
                };
                let out = backend.step(actions, mask)?;
                check_answer(out, self.dims.len(), |i| mask[i], "stepped")
            }
        }
    }

    /// Renders environment `i`'s current state ([`crate::render::render`]), on the thread that owns
    /// it (each thread keeps its own GL context).
    pub fn render(&mut self, i: usize, size: FrameSize) -> Result<Frame, RenderError> {
        if i >= self.len() {
            return Err(RenderError::Env(vec_error(format!(
                "render: environment {i} of {}",
                self.len()
            ))));
        }
        let Envs::Pool(pool) = &mut self.envs else {
            let env = "an environment outside this process".to_owned();
            return Err(RenderError::Env(EnvError::Unsupported { env, what: "rendering" }));
        };
        let mut out = pool.render_one(i, size)?;
        out.swap_remove(i).ok_or_else(|| RenderError::Env(missing("rendered")))?
    }

    fn reset_with(
        &mut self,
        seed_of: impl Fn(usize) -> Option<u64>,
    ) -> Result<Vec<Option<Vec<f32>>>, EnvError> {
        match &mut self.envs {
            Envs::Pool(pool) => pool.reset_with(seed_of),
            Envs::External(backend) => {
                let seeds: Vec<Option<u64>> = (0..self.dims.len()).map(&seed_of).collect();
                let out = backend.reset(&seeds)?;
                check_answer(out, self.dims.len(), |i| seeds[i].is_some(), "reset")
            }
        }
    }

    /// [`VecEnv::step`] behind a [`Backend`]: the actions packed into one buffer; an action of the
    /// wrong size is refused in its environment's slot, as the thread pool's environments do.
    fn step_external_each(&mut self, actions: &[Vec<f32>]) -> Result<Vec<StepSlot>, EnvError> {
        let mut flat = vec![0f32; self.flat_action_len()];
        let mut mask = vec![true; self.len()];
        let mut refused: Vec<Option<EnvError>> = (0..self.len()).map(|_| None).collect();
        for (i, a) in actions.iter().enumerate() {
            let range = self.action_range(i).ok_or_else(|| missing("stepped"))?;
            if a.len() == range.len() {
                flat[range].copy_from_slice(a);
            } else {
                let (got, expected) = (a.len(), range.len());
                refused[i] =
                    Some(EnvError::ActionDim { env: format!("environment {i}"), got, expected });
                mask[i] = false;
            }
        }
        let mut out = self.step_flat(&flat, Some(&mask))?;
        for (slot, error) in out.iter_mut().zip(refused) {
            if let Some(e) = error {
                *slot = Some(Err(e));
            }
        }
        Ok(out)
    }

    fn check_len(&self, what: &str, got: usize) -> Result<(), EnvError> {
        if got == self.len() {
            Ok(())
        } else {
            Err(vec_error(format!("{got} {what} for {} environments", self.len())))
        }
    }
}

/// `act_offsets` of environments of sizes `dims`: where each one's action starts, then the end.
fn offsets(dims: &[EnvDims]) -> Vec<usize> {
    let mut out = Vec::with_capacity(dims.len() + 1);
    out.push(0);
    let mut end = 0;
    for d in dims {
        end += d.act_dim;
        out.push(end);
    }
    out
}

/// A [`Backend`]'s answer checked: one slot per environment, filled exactly where `asked`.
fn check_answer<T>(
    out: Vec<Option<T>>,
    len: usize,
    asked: impl Fn(usize) -> bool,
    what: &str,
) -> Result<Vec<Option<T>>, EnvError> {
    if out.len() != len {
        return Err(vec_error(format!("{} answers {what} for {len} environments", out.len())));
    }
    match out.iter().enumerate().find(|(i, slot)| slot.is_some() != asked(*i)) {
        None => Ok(out),
        Some((i, _)) => Err(vec_error(format!("environment {i}: answer {what} out of turn"))),
    }
}

/// How long a thread polls a channel before it blocks on it.
///
/// A blocked thread is woken through the kernel (a futex), which costs tens of microseconds each
/// way; a step of 16 HalfCheetahs takes only about 400 µs, so that latency alone cost a quarter of
/// the two-thread speed-up. Polling briefly first catches the answer (or the next command, when
/// steps follow each other back to back) without the round trip; beyond the window the thread
/// sleeps, so an idle `VecEnv` (e.g. while a policy network runs) costs no CPU.
const SPIN: std::time::Duration = std::time::Duration::from_micros(100);

/// `rx.recv()`, polling for up to [`SPIN`] first. `None` when the sender is gone.
fn recv_spinning<T>(rx: &Receiver<T>) -> Option<T> {
    let start = std::time::Instant::now();
    loop {
        match rx.try_recv() {
            Ok(v) => return Some(v),
            Err(std::sync::mpsc::TryRecvError::Disconnected) => return None,
            Err(std::sync::mpsc::TryRecvError::Empty) if start.elapsed() < SPIN => {
                std::hint::spin_loop()
            }
            Err(std::sync::mpsc::TryRecvError::Empty) => return rx.recv().ok(),
        }
    }
}

fn vec_error(message: String) -> EnvError {
    EnvError::Simulation { env: "VecEnv".into(), message }
}

/// A slot left empty although its environment was asked for: a broken invariant of the pool.
fn missing(what: &str) -> EnvError {
    vec_error(format!("an environment was not {what} (internal error)"))
}

/// What a worker is asked to do with its chunk; `Vec` entries follow the chunk's order.
enum Command {
    /// Reset the environments that have a seed.
    Reset(Vec<Option<u64>>),
    /// Step the environments that have a slot: `actions[slot]` is the environment's action.
    Step {
        actions: Vec<f32>,
        slots: Vec<Option<Range<usize>>>,
    },
    /// Render the environment at this place of the chunk.
    Render {
        place: usize,
        size: FrameSize,
    },
    Shutdown,
}

/// A chunk of environments, as owned by one thread.
type Chunk = Vec<Box<dyn Env>>;

/// A worker's answer to a `Reset` or `Step`, one entry per environment of its chunk.
enum Reply {
    Reset(Vec<Option<Vec<f32>>>),
    Step(Vec<StepSlot>),
    Render(Vec<Option<Result<Frame, RenderError>>>),
}

/// What a call sent a worker.
enum Sent {
    /// Nothing: none of its environments is concerned.
    Nothing,
    /// A command, to be answered.
    Command,
    /// The command could not be sent: the worker is gone.
    Failed,
}

/// Why a call could not collect every chunk's result.
enum Failure {
    /// An environment panicked; re-raised on the caller.
    Panic(Box<dyn Any + Send>),
    /// A worker stopped or answered out of turn without panicking.
    Lost(String),
}

/// The environments and the threads that own them.
struct Pool {
    /// Chunk 0, stepped on the calling thread.
    local: Chunk,
    /// Chunks 1.., one worker each.
    workers: Vec<Worker>,
    /// Number of environments over all chunks.
    len: usize,
    /// Set once a call failed: some environments are lost or in an unknown state.
    broken: Option<String>,
}

struct Worker {
    commands: Sender<Command>,
    replies: Receiver<Reply>,
    /// Taken when the thread is joined (after it stopped answering, or on drop).
    handle: Option<JoinHandle<()>>,
}

impl Pool {
    fn new(envs: Vec<Box<dyn Env>>, threads: usize) -> Self {
        let len = envs.len();
        let wanted = threads.clamp(1, len.max(1));
        let mut workers = Vec::with_capacity(wanted - 1);
        let mut inboxes = Vec::with_capacity(wanted - 1);
        for c in 1..wanted {
            match Worker::spawn(c) {
                Ok((worker, inbox)) => {
                    workers.push(worker);
                    inboxes.push(inbox);
                }
                Err(e) => {
                    log::warn!("VecEnv: could not start thread {c} ({e}); stepping on {c} threads");
                    break;
                }
            }
        }
        // The environments are dealt only now that the number of threads is known, so that a
        // failed start loses none of them.
        let t = workers.len() + 1;
        let mut chunks: Vec<Chunk> = (0..t).map(|_| Vec::new()).collect();
        for (i, env) in envs.into_iter().enumerate() {
            chunks[i % t].push(env);
        }
        let mut chunks = chunks.into_iter();
        let local = chunks.next().unwrap_or_default();
        for (inbox, chunk) in inboxes.into_iter().zip(chunks) {
            // A worker cannot have stopped yet; if it had, the first call would report it lost.
            let _ = inbox.send(chunk);
        }
        Self { local, workers, len, broken: None }
    }

    fn threads(&self) -> usize {
        self.workers.len() + 1
    }

    fn reset_with(
        &mut self,
        seed_of: impl Fn(usize) -> Option<u64>,
    ) -> Result<Vec<Option<Vec<f32>>>, EnvError> {
        self.dispatch(
            |members| {
                let seeds: Vec<Option<u64>> = members.map(&seed_of).collect();
                seeds.iter().any(Option::is_some).then_some(Command::Reset(seeds))
            },
            |envs, members| reset_chunk(envs, members.map(&seed_of)),
            |reply| match reply {
                Reply::Reset(obs) => Some(obs),
                _ => None,
            },
        )
    }

    fn step_with<'a>(
        &mut self,
        action_of: impl Fn(usize) -> Option<&'a [f32]>,
    ) -> Result<Vec<StepSlot>, EnvError> {
        self.dispatch(
            |members| {
                // The chunk's actions, packed into one buffer (the worker needs them owned).
                let mut actions = Vec::new();
                let slots: Vec<Option<Range<usize>>> = members
                    .map(|i| {
                        action_of(i).map(|a| {
                            let start = actions.len();
                            actions.extend_from_slice(a);
                            start..actions.len()
                        })
                    })
                    .collect();
                slots.iter().any(Option::is_some).then_some(Command::Step { actions, slots })
            },
            |envs, members| step_chunk(envs, members.map(&action_of)),
            |reply| match reply {
                Reply::Step(out) => Some(out),
                _ => None,
            },
        )
    }

    /// Renders environment `i` alone: only the thread owning it is woken.
    fn render_one(
        &mut self,
        i: usize,
        size: FrameSize,
    ) -> Result<Vec<Option<Result<Frame, RenderError>>>, EnvError> {
        self.dispatch(
            |mut members| members.position(|m| m == i).map(|place| Command::Render { place, size }),
            |envs, mut members| render_chunk(envs, members.position(|m| m == i), size),
            |reply| match reply {
                Reply::Render(out) => Some(out),
                _ => None,
            },
        )
    }

    /// Runs one operation on every chunk: sends each worker its command (`command`, given the
    /// chunk's environment indices; `None` when none of them is concerned, which leaves the worker
    /// asleep), runs chunk 0 here meanwhile (`local`), then collects the workers' results
    /// (`unpack`). Returns one slot per environment, in environment order (`None` where untouched).
    fn dispatch<T>(
        &mut self,
        command: impl Fn(StepBy<Range<usize>>) -> Option<Command>,
        local: impl FnOnce(&mut [Box<dyn Env>], StepBy<Range<usize>>) -> Vec<Option<T>>,
        unpack: fn(Reply) -> Option<Vec<Option<T>>>,
    ) -> Result<Vec<Option<T>>, EnvError> {
        if let Some(why) = &self.broken {
            return Err(vec_error(format!("unusable since an earlier failure: {why}")));
        }
        let (t, len) = (self.threads(), self.len);
        let members = |c: usize| (c..len).step_by(t);
        let sent: Vec<Sent> = (self.workers.iter().enumerate())
            .map(|(w, worker)| match command(members(w + 1)) {
                None => Sent::Nothing,
                Some(cmd) => match worker.commands.send(cmd) {
                    Ok(()) => Sent::Command,
                    Err(_) => Sent::Failed,
                },
            })
            .collect();

        let mut out: Vec<Option<T>> = (0..len).map(|_| None).collect();
        let place = |out: &mut Vec<Option<T>>, c: usize, part: Vec<Option<T>>| {
            for (i, value) in members(c).zip(part) {
                out[i] = value;
            }
        };
        let mut failure = None;
        // Caught so that the workers' replies to this call are still collected; the pool is then
        // marked broken, so the environments a panic may have left half-stepped are never used.
        match panic::catch_unwind(AssertUnwindSafe(|| local(&mut self.local, members(0)))) {
            Ok(part) => place(&mut out, 0, part),
            Err(payload) => failure = Some((0, Failure::Panic(payload))),
        }
        for (w, worker) in self.workers.iter_mut().enumerate() {
            let c = w + 1;
            let reply = match sent[w] {
                Sent::Nothing => continue,
                Sent::Command => recv_spinning(&worker.replies),
                Sent::Failed => None,
            };
            match reply.map(unpack) {
                Some(Some(part)) => place(&mut out, c, part),
                Some(None) => {
                    let lost = Failure::Lost(format!("thread {c} answered another command"));
                    failure.get_or_insert((c, lost));
                }
                None => {
                    let f = worker.stopped(c);
                    failure.get_or_insert((c, f));
                }
            }
        }
        match failure {
            None => Ok(out),
            Some((c, Failure::Panic(payload))) => {
                self.broken = Some(format!("an environment panicked on thread {c}"));
                panic::resume_unwind(payload)
            }
            Some((_, Failure::Lost(why))) => {
                let e = vec_error(why.clone());
                self.broken = Some(why);
                Err(e)
            }
        }
    }
}

impl Drop for Pool {
    fn drop(&mut self) {
        // Ask all to stop first, so that they wind down together, then wait for each.
        for worker in &self.workers {
            let _ = worker.commands.send(Command::Shutdown);
        }
        for worker in &mut self.workers {
            if let Some(handle) = worker.handle.take() {
                // A worker panics only inside a call, which re-raised the panic already.
                let _ = handle.join();
            }
        }
    }
}

impl Worker {
    /// Starts worker thread `c`; its chunk is to be sent on the returned inbox.
    fn spawn(c: usize) -> std::io::Result<(Self, Sender<Chunk>)> {
        let (inbox, chunk) = mpsc::channel();
        let (commands, command_rx) = mpsc::channel();
        let (reply_tx, replies) = mpsc::channel();
        let handle = std::thread::Builder::new()
            .name(format!("promptdt-env-{c}"))
            .spawn(move || work(chunk, command_rx, reply_tx))?;
        Ok((Self { commands, replies, handle: Some(handle) }, inbox))
    }

    /// The worker stopped answering: its panic, or why it is lost.
    fn stopped(&mut self, c: usize) -> Failure {
        match self.handle.take().map(JoinHandle::join) {
            Some(Err(payload)) => Failure::Panic(payload),
            _ => Failure::Lost(format!("thread {c} stopped without answering")),
        }
    }
}

/// A worker thread's loop: owns its chunk and answers each command, until told to stop or the
/// `VecEnv` is gone (its channels disconnected).
fn work(chunk: Receiver<Chunk>, commands: Receiver<Command>, replies: Sender<Reply>) {
    let Ok(mut envs) = chunk.recv() else { return };
    while let Some(command) = recv_spinning(&commands) {
        let reply = match command {
            Command::Reset(seeds) => Reply::Reset(reset_chunk(&mut envs, seeds.into_iter())),
            Command::Step { actions, slots } => {
                // A slot is always inside `actions` (both are built together); were it not, the
                // environment would get an empty action and report the wrong size.
                let acts = slots.into_iter().map(|s| s.map(|r| actions.get(r).unwrap_or(&[])));
                Reply::Step(step_chunk(&mut envs, acts))
            }
            Command::Render { place, size } => {
                Reply::Render(render_chunk(&mut envs, Some(place), size))
            }
            Command::Shutdown => return,
        };
        if replies.send(reply).is_err() {
            return;
        }
    }
}

fn reset_chunk(
    envs: &mut [Box<dyn Env>],
    seeds: impl Iterator<Item = Option<u64>>,
) -> Vec<Option<Vec<f32>>> {
    envs.iter_mut().zip(seeds).map(|(env, seed)| seed.map(|s| env.reset(s))).collect()
}

fn render_chunk(
    envs: &mut [Box<dyn Env>],
    place: Option<usize>,
    size: FrameSize,
) -> Vec<Option<Result<Frame, RenderError>>> {
    (0..envs.len())
        .map(|j| (Some(j) == place).then(|| crate::render::render(envs[j].as_mut(), size)))
        .collect()
}

fn step_chunk<'a>(
    envs: &mut [Box<dyn Env>],
    actions: impl Iterator<Item = Option<&'a [f32]>>,
) -> Vec<StepSlot> {
    envs.iter_mut().zip(actions).map(|(env, a)| a.map(|a| env.step(a))).collect()
}
