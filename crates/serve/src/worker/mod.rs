//! The model thread of `promptdt serve`: it owns the policy and every open episode, takes the
//! requests that arrived within a bounded wait and answers them with one batched forward.

pub(crate) mod adapt;

use crate::{ActionReply, ApiError, Info, OpenRequest, ServeOptions, StepRequest};
use axum::http::StatusCode;
use pdt_model::PrefixCache;
use pdt_policy::{Policy, PolicyError};
use std::collections::HashMap;
use std::sync::mpsc;
use std::time::{Duration, Instant};

// ------------------------------------------------------------------------------------------------
// The model thread
// ------------------------------------------------------------------------------------------------

pub(crate) type Reply<T> = tokio::sync::oneshot::Sender<Result<T, ApiError>>;

pub(crate) enum Msg {
    Open(Box<OpenRequest>, Reply<ActionReply>),
    Step(u64, StepRequest, Reply<ActionReply>),
    Close(u64, Reply<()>),
    Info(Reply<Info>),
}

struct Episode {
    /// The history, last action and undo of the episode.
    e: pdt_policy::Episode,
    /// The prompt's keys and values (one row), `None` for methods without a prompt.
    prefix: Option<PrefixCache>,
    seen: Instant,
    /// The segments a strategy chose, sent with the first action.
    segments: Option<Vec<pdt_prompt::SegmentChoice>>,
    /// `bandit`: the task and the arms pulled, reported with the return when it closes.
    bandit: Option<(usize, pdt_prompt::bandit::BanditChoice)>,
    /// The adaptation it acts with (its prefix is the adaptation's; LoRA's adapters are used in
    /// every forward).
    adapted: Option<adapt::AdaptKey>,
    /// The adaptation's log, sent with the first action.
    adapt_log: Option<pdt_rundir::config::AdaptLog>,
}

impl Episode {
    /// An episode just started, with its prompt's keys and values.
    fn new(e: pdt_policy::Episode, prefix: Option<PrefixCache>) -> Self {
        let (segments, bandit, adapted, adapt_log) = (None, None, None, None);
        Self { e, prefix, seen: Instant::now(), segments, bandit, adapted, adapt_log }
    }
}

/// What the model thread owns: the policy and every open episode.
pub(crate) struct Worker {
    run: Policy,
    opts: ServeOptions,
    episodes: HashMap<u64, Episode>,
    next_id: u64,
    /// `bandit` prompts: one bandit per task, across its episodes.
    bandits: HashMap<usize, pdt_eval::testtime::TaskBandit>,
    /// Adapted tasks, kept for their next episodes.
    adaptations: adapt::Adaptations,
}

/// An action to compute in this batch, and where its answer goes.
struct Pending {
    id: u64,
    /// The episode's first action: if it is not finite, the episode is not opened.
    opening: bool,
    reply: Reply<ActionReply>,
}

impl Worker {
    pub(crate) fn new(run: Policy, opts: ServeOptions) -> Self {
        Self {
            run,
            opts,
            episodes: HashMap::new(),
            next_id: 1,
            bandits: HashMap::new(),
            adaptations: adapt::Adaptations::default(),
        }
    }

    pub(crate) fn run(mut self, rx: mpsc::Receiver<Msg>) {
        // The thread count is a setting of the calling thread (OpenMP), so it is set here.
        if self.opts.threads > 0 {
            tch::set_num_threads(self.opts.threads as i32);
        }
        loop {
            let first = match rx.recv_timeout(Duration::from_millis(500)) {
                Ok(m) => m,
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    self.sweep();
                    continue;
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => return,
            };
            // Gather what arrives within the batch window, up to max_batch actions.
            let deadline = Instant::now() + self.opts.batch_wait;
            let mut msgs = vec![first];
            let actions =
                |m: &[Msg]| m.iter().filter(|m| matches!(m, Msg::Open(..) | Msg::Step(..))).count();
            while actions(&msgs) < self.opts.max_batch {
                let now = Instant::now();
                if now >= deadline {
                    break;
                }
                match rx.recv_timeout(deadline - now) {
                    Ok(m) => msgs.push(m),
                    Err(_) => break,
                }
            }
            let mut pending: Vec<Pending> = Vec::new();
            for m in msgs {
                match m {
                    Msg::Open(req, reply) => match self.open(*req) {
                        Ok(id) => pending.push(Pending { id, opening: true, reply }),
                        Err(e) => {
                            let _ = reply.send(Err(e));
                        }
                    },
                    Msg::Step(id, req, reply) => {
                        if pending.iter().any(|p| p.id == id) {
                            let e = ApiError::new(
                                StatusCode::CONFLICT,
                                format!("episode {id}: a step is already in flight; wait for its action"),
                            );
                            let _ = reply.send(Err(e));
                            continue;
                        }
                        match self.step(id, req) {
                            Ok(()) => pending.push(Pending { id, opening: false, reply }),
                            Err(e) => {
                                let _ = reply.send(Err(e));
                            }
                        }
                    }
                    Msg::Close(id, reply) => {
                        let r = match self.episodes.remove(&id) {
                            Some(ep) => {
                                // A bandit learns the return of each episode it prompted.
                                if let Some((task, choice)) = &ep.bandit {
                                    if let Some(b) = self.bandits.get_mut(task) {
                                        b.update(choice, ep.e.ret());
                                    }
                                }
                                Ok(())
                            }
                            None => Err(unknown(id)),
                        };
                        let _ = reply.send(r);
                    }
                    Msg::Info(reply) => {
                        let _ = reply.send(Ok(self.info()));
                    }
                }
            }
            self.act(pending);
            self.sweep();
        }
    }

    fn info(&self) -> Info {
        let r = &self.run;
        Info {
            method: r.method.name().into(),
            obs_dim: r.stats.obs_dim,
            act_dim: r.stats.act_dim,
            k: r.k,
            prompt_steps: r.prompt_steps,
            uses_prompt: r.method.uses_prompt(),
            target_return: r.stats.target_return,
            rtg_scale: r.stats.rtg_scale,
            max_ep_len: r.max_ep_len(),
            iteration: r.iteration,
            prompt_tasks: r.prompt_tasks().unwrap_or_default(),
            max_episodes: self.opts.max_episodes,
            max_batch: self.opts.max_batch,
            open_episodes: self.episodes.len(),
        }
    }

    /// Closes the episodes idle for longer than the timeout.
    fn sweep(&mut self) {
        let limit = self.opts.idle_timeout;
        self.episodes.retain(|_, e| e.seen.elapsed() < limit);
    }

    fn open(&mut self, req: OpenRequest) -> Result<u64, ApiError> {
        if self.episodes.len() >= self.opts.max_episodes {
            return Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!(
                    "{} episodes are open, the limit (--max-episodes); close some first",
                    self.opts.max_episodes
                ),
            ));
        }
        let mut obs = self.run.observation(&req.observation)?;
        let strategy = self.strategy(&req)?;
        if let Some(test_time) = self.adaptation(&req, &strategy)? {
            return self.open_adapted(req, obs, test_time);
        }
        let (mut segments, mut bandit) = (None, None);
        let prompt = match (self.run.method.uses_prompt(), req.prompt, req.task) {
            (false, None, None) => None,
            (false, ..) => {
                return Err(ApiError::bad(format!(
                    "this run's method ({}) takes no prompt; send neither `prompt` nor `task`",
                    self.run.method.name()
                )))
            }
            (true, Some(_), Some(_)) => {
                return Err(ApiError::bad("give either `prompt` or `task`, not both"))
            }
            (true, Some(p), None) => Some(self.run.prompt_from_arrays(&p, obs.inputs_mut())?),
            (true, None, Some(task)) if strategy.is_default() => {
                Some(self.run.task_prompt(task, req.prompt_seed.unwrap_or(0))?)
            }
            (true, None, Some(task)) => {
                let seed = req.prompt_seed.unwrap_or(0);
                let chosen = if strategy.strategy.learns_from_returns() {
                    let b = match self.bandits.entry(task) {
                        std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                        std::collections::hash_map::Entry::Vacant(v) => {
                            v.insert(self.run.task_bandit(task, seed, &strategy)?)
                        }
                    };
                    if b.strategy() != &strategy {
                        return Err(ApiError::bad(format!(
                            "task {task} has a bandit with other settings ({:?}); its episodes \
                             share it, so open them with the same prompt settings",
                            b.strategy()
                        )));
                    }
                    let (chosen, choice) = self.run.bandit_prompt(b)?;
                    bandit = Some((task, choice));
                    chosen
                } else {
                    let first: Vec<f32> = req.observation.iter().map(|&x| x as f32).collect();
                    self.run.strategy_prompt(task, seed, &strategy, Some(&first))?
                };
                segments = Some(chosen.segments);
                Some(chosen.prompt)
            }
            (true, None, None) => {
                return Err(ApiError::bad(
                    "this run's method takes a prompt: send `prompt` (arrays) or `task`",
                ))
            }
        };
        let target = self.run.target(req.target_return)?;
        let prefix = match &prompt {
            Some(p) => Some(self.run.prefix(&[p])?),
            None => None,
        };
        let e = self.run.start(obs, target);
        Ok(self.insert(Episode { segments, bandit, ..Episode::new(e, prefix) }))
    }

    /// Opens `ep` under the next id.
    fn insert(&mut self, ep: Episode) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        self.episodes.insert(id, ep);
        id
    }

    /// The prompt strategy of an opening request: the server's, with what the request names.
    fn strategy(&self, req: &OpenRequest) -> Result<pdt_prompt::PromptStrategy, ApiError> {
        let mut s = self.opts.prompt_strategy.clone();
        if let Some(name) = &req.prompt_strategy {
            s.strategy = name.parse().map_err(|e: pdt_prompt::StrategyError| {
                ApiError::bad(format!("prompt_strategy: {e}"))
            })?;
        }
        s.episodes = req.prompt_episodes.or(s.episodes);
        s.length = req.prompt_length.or(s.length);
        let named = req.prompt_strategy.is_some()
            || req.prompt_episodes.is_some()
            || req.prompt_length.is_some();
        if named && req.task.is_none() {
            return Err(ApiError::bad(
                "prompt_strategy, prompt_episodes and prompt_length choose a `task`'s prompt; \
                 send a `task`",
            ));
        }
        s.validate().map_err(|e| ApiError::bad(e.to_string()))?;
        Ok(s)
    }

    fn step(&mut self, id: u64, req: StepRequest) -> Result<(), ApiError> {
        let obs = self.run.observation(&req.observation)?;
        let step = self.run.step(req.reward, obs)?;
        let ep = self.episodes.get_mut(&id).ok_or_else(|| unknown(id))?;
        match self.run.record(&mut ep.e, step) {
            Ok(()) => {
                ep.seen = Instant::now();
                Ok(())
            }
            Err(PolicyError::EpisodeFull { max_ep_len }) => Err(ApiError::new(
                StatusCode::CONFLICT,
                format!(
                    "episode {id} has reached the model's max_ep_len ({max_ep_len} steps); close it"
                ),
            )),
            Err(e) => Err(ApiError::bad(format!("episode {id}: {e}"))),
        }
    }

    /// Answers every pending action: one forward per group of episodes with prompts of the same
    /// length (in practice: all of them).
    fn act(&mut self, pending: Vec<Pending>) {
        // Episodes acting through LoRA adapters go with those of the same adaptation only.
        type Group = (i64, Option<adapt::AdaptKey>, Vec<Pending>);
        let mut groups: Vec<Group> = Vec::new();
        for p in pending {
            let ep = self.episodes.get(&p.id);
            let len = ep.and_then(|e| e.prefix.as_ref()).map_or(-1, PrefixCache::len);
            let lora = ep
                .and_then(|e| e.adapted.as_ref())
                .filter(|k| self.adaptations.get(k).is_some_and(|a| a.adaptation.lora().is_some()));
            match groups.iter_mut().find(|(l, k, _)| *l == len && k.as_ref() == lora) {
                Some((.., g)) => g.push(p),
                None => groups.push((len, lora.cloned(), vec![p])),
            }
        }
        let da = self.run.stats.act_dim;
        for (_, lora, group) in groups {
            // An episode closed (DELETE) in the same batch as its step was recorded: the close
            // won, and the step is answered as any step of a closed episode is (404). The others
            // of the group act as usual.
            let (group, closed): (Vec<Pending>, Vec<Pending>) =
                group.into_iter().partition(|p| self.episodes.contains_key(&p.id));
            for p in closed {
                let _ = p.reply.send(Err(unknown(p.id)));
            }
            if group.is_empty() {
                continue;
            }
            let eps: Vec<&Episode> =
                group.iter().filter_map(|p| self.episodes.get(&p.id)).collect();
            let states: Vec<&pdt_policy::Episode> = eps.iter().map(|e| &e.e).collect();
            let prefixes: Option<Vec<&PrefixCache>> =
                eps.iter().map(|e| e.prefix.as_ref()).collect();
            let prefix = prefixes.and_then(|p| PrefixCache::cat(&p));
            let adapters = lora
                .as_ref()
                .and_then(|k| self.adaptations.get(k))
                .and_then(|a| a.adaptation.lora());
            let flat = self.run.act_with(&states, prefix.as_ref(), adapters); // [A * da]
            for (p, a) in group.into_iter().zip(flat.chunks_exact(da)) {
                let Some(ep) = self.episodes.get_mut(&p.id) else { continue };
                let why = match ep.e.accept(a) {
                    Ok(()) => {
                        let segments = if p.opening { ep.segments.take() } else { None };
                        let adaptation = if p.opening { ep.adapt_log.take() } else { None };
                        let reply = ActionReply {
                            episode: p.id,
                            t: ep.e.t(),
                            action: a.to_vec(),
                            prompt_segments: segments,
                            adaptation,
                        };
                        let _ = p.reply.send(Ok(reply));
                        continue;
                    }
                    Err(why) => why,
                };
                // Nothing of a refused request is kept (`accept` took the step back), so the
                // client can go on with sane values.
                let msg = if p.opening {
                    self.episodes.remove(&p.id);
                    format!("{why}. The episode is not opened")
                } else {
                    format!(
                        "episode {} step {}: {why}. The step is refused and the episode is as it \
                         was before it",
                        p.id,
                        ep.e.t() + 1
                    )
                };
                let _ = p.reply.send(Err(ApiError::bad(msg)));
            }
        }
    }
}

fn unknown(id: u64) -> ApiError {
    ApiError::new(
        StatusCode::NOT_FOUND,
        format!("no open episode {id} (closed, timed out, or never opened)"),
    )
}
