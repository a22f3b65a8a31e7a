//! `promptdt serve`: a trained prompted policy behind HTTP+JSON (`docs/serve.md`).
//!
//! A client opens an episode with a prompt (arrays it sends, or a task of the run whose prompt the
//! server draws as the evaluation does) and its first observation, and gets the first action; then
//! it sends each reward and next observation and gets the next action; it closes the episode (or
//! the server does after an idle timeout). Many episodes run at once: the HTTP side (tokio + axum)
//! only parses and validates; one model thread owns the policy and every episode's history, takes
//! the requests that arrived within a bounded wait (at most `max_batch`), and answers them with one
//! batched forward. Each episode acts exactly as `promptdt eval` would: the policy and episodes are
//! `pdt-policy`'s (`Policy`, `Episode`: the history, its checks and the undo of a refused step),
//! the prompt's keys and values computed once when the episode opens.

use axum::extract::rejection::{JsonRejection, PathRejection};
use axum::extract::{DefaultBodyLimit, Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use pdt_model::PrefixCache;
use pdt_policy::{Policy, PolicyError};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

mod adapt;
pub mod auth;
pub mod conn;
mod wire;

pub use adapt::MAX_ADAPTATIONS;
pub use auth::{Auth, Token};

/// The longest `batch_wait` (a longer one would only hold every request back).
pub const MAX_BATCH_WAIT: Duration = Duration::from_secs(10);
/// The longest header and body timeouts.
pub const MAX_IO_TIMEOUT: Duration = Duration::from_secs(3600);

/// Limits and batching of a server.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Address to listen on (`127.0.0.1:0` picks a free port).
    pub listen: SocketAddr,
    /// Episodes open at once; opening one more is refused (429).
    pub max_episodes: usize,
    /// Requests answered by one forward at most.
    pub max_batch: usize,
    /// How long the model thread waits for more requests after the first one of a batch.
    pub batch_wait: Duration,
    /// An episode without a request for this long is closed.
    pub idle_timeout: Duration,
    /// Largest request body (413 beyond; a larger declared `Content-Length` is refused before
    /// the body is read).
    pub max_body_bytes: usize,
    /// How long a connection may take to send a request's headers (and how long a kept-alive
    /// connection may stay idle) before it is closed.
    pub header_timeout: Duration,
    /// How long a request's body may take to arrive after its headers (408 beyond).
    pub body_timeout: Duration,
    /// Connections open at once (each holds a descriptor); one more is answered 503 and closed.
    /// `None`: [`conn::DEFAULT_MAX_CONNECTIONS`], or fewer where the process's descriptor limit
    /// leaves less room ([`conn::connection_budget`]).
    pub max_connections: Option<usize>,
    /// Requests waiting for the model thread at most (503 beyond).
    pub queue: usize,
    /// The prompt strategy of episodes opened with a `task` and no `prompt_strategy` of their own
    /// (`promptdt serve --prompt-strategy`; default `reference`).
    pub prompt_strategy: pdt_prompt::PromptStrategy,
    /// The evaluation-time adaptation of episodes opened with a `task` (docs/prompt-control.md;
    /// `promptdt serve --adapt`): its kind (a request's `adapt` names another) and budget.
    /// Default: none.
    pub adapt: pdt_rundir::config::AdaptConfig,
    /// libtorch intra-op threads of the model thread (0: libtorch's default, all cores). With 1,
    /// an episode gets the same bits alone or batched with others on AVX2 CPUs (within 1e-6 on
    /// AVX-512 ones, whose kernels depend on the batch size).
    pub threads: usize,
    /// Who may use the server: by default no token, on a loopback `listen` only ([`Auth`]).
    pub auth: Auth,
}

impl Default for ServeOptions {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 8000)),
            max_episodes: 1024,
            max_batch: 256,
            batch_wait: Duration::from_millis(2),
            idle_timeout: Duration::from_secs(300),
            max_body_bytes: 1 << 20,
            header_timeout: Duration::from_secs(10),
            body_timeout: Duration::from_secs(10),
            max_connections: None,
            queue: 4096,
            prompt_strategy: pdt_prompt::PromptStrategy::default(),
            adapt: pdt_rundir::config::AdaptConfig::default(),
            threads: 0,
            auth: Auth::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cannot listen on {addr}: {source}")]
    Bind { addr: SocketAddr, source: std::io::Error },
    #[error("server: {0}")]
    Io(#[from] std::io::Error),
    #[error("{0}")]
    Invalid(String),
    #[error("{from}: {why}")]
    Token { from: String, why: String },
    #[error(
        "refusing to serve {0} without authentication: it is not a loopback address, so anyone \
         who can reach the port could open episodes and use the model's compute. Give a token \
         (--token-file PATH, or the environment variable {env}; --generate-token makes one and \
         prints it once), or pass --no-auth to serve without one (behind a proxy that \
         authenticates, say)",
        env = auth::TOKEN_ENV
    )]
    Unauthenticated(SocketAddr),
}

// ------------------------------------------------------------------------------------------------
// The wire format
// ------------------------------------------------------------------------------------------------

/// A prompt sent by the client (the same arrays a Python `Policy` takes).
pub use wire::PromptArrays;
pub use wire::{ActionReply, Info, OpenRequest, StepRequest, MAX_RETURN};

/// An error reply: `{"error": "..."}` with its status.
#[derive(Debug, Clone)]
pub struct ApiError {
    pub status: StatusCode,
    pub message: String,
}

impl ApiError {
    fn new(status: StatusCode, message: impl Into<String>) -> Self {
        Self { status, message: message.into() }
    }
    fn bad(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.status, Json(serde_json::json!({ "error": self.message }))).into_response()
    }
}

impl From<JsonRejection> for ApiError {
    fn from(r: JsonRejection) -> Self {
        Self::new(r.status(), r.body_text())
    }
}

impl From<PolicyError> for ApiError {
    /// A refused input or a policy that cannot do what was asked: the request's fault (400).
    fn from(e: PolicyError) -> Self {
        Self::bad(e.to_string())
    }
}

impl From<PathRejection> for ApiError {
    fn from(r: PathRejection) -> Self {
        Self::new(r.status(), format!("episode id: {}", r.body_text()))
    }
}

// ------------------------------------------------------------------------------------------------
// The model thread
// ------------------------------------------------------------------------------------------------

type Reply<T> = tokio::sync::oneshot::Sender<Result<T, ApiError>>;

enum Msg {
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
struct Worker {
    run: Policy,
    opts: ServeOptions,
    episodes: HashMap<u64, Episode>,
    next_id: u64,
    /// `bandit` prompts: one bandit per task, across its episodes.
    bandits: HashMap<usize, pdt_policy::TaskBandit>,
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
    fn new(run: Policy, opts: ServeOptions) -> Self {
        Self {
            run,
            opts,
            episodes: HashMap::new(),
            next_id: 1,
            bandits: HashMap::new(),
            adaptations: adapt::Adaptations::default(),
        }
    }

    fn run(mut self, rx: mpsc::Receiver<Msg>) {
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
        if let Some(cfg) = self.adaptation(&req)? {
            return self.open_adapted(req, obs, strategy, cfg);
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
                    let (chosen, choice) = b.choose(&self.run)?;
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

// ------------------------------------------------------------------------------------------------
// The HTTP side
// ------------------------------------------------------------------------------------------------

#[derive(Clone)]
struct AppState {
    tx: mpsc::SyncSender<Msg>,
    /// Whether the model thread still runs (false once it has ended, as after a panic).
    alive: Arc<AtomicBool>,
}

/// Sets its flag to false when dropped: the model thread's end, however it ends.
struct AliveGuard(Arc<AtomicBool>);

impl Drop for AliveGuard {
    fn drop(&mut self) {
        self.0.store(false, Ordering::SeqCst);
    }
}

impl AppState {
    async fn ask<T>(&self, make: impl FnOnce(Reply<T>) -> Msg) -> Result<T, ApiError> {
        let (reply, rx) = tokio::sync::oneshot::channel();
        self.tx.try_send(make(reply)).map_err(|e| match e {
            mpsc::TrySendError::Full(_) => ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the model thread's queue is full; retry shortly",
            ),
            mpsc::TrySendError::Disconnected(_) => {
                ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "the model thread has stopped")
            }
        })?;
        rx.await.map_err(|_| {
            ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "the model thread dropped the request")
        })?
    }
}

/// `GET /v1/health`, open without a token: 200 while the model thread runs. It does not queue
/// anything for the model thread, so calling it costs no model time.
async fn health(State(s): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    if s.alive.load(Ordering::SeqCst) {
        Ok(Json(serde_json::json!({ "status": "ok" })))
    } else {
        Err(ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "the model thread has stopped"))
    }
}

async fn info(State(s): State<AppState>) -> Result<Json<Info>, ApiError> {
    s.ask(Msg::Info).await.map(Json)
}

async fn open(
    State(s): State<AppState>,
    body: Result<Json<OpenRequest>, JsonRejection>,
) -> Result<(StatusCode, Json<ActionReply>), ApiError> {
    let Json(req) = body?;
    s.ask(|r| Msg::Open(Box::new(req), r)).await.map(|a| (StatusCode::CREATED, Json(a)))
}

async fn step(
    State(s): State<AppState>,
    id: Result<Path<u64>, PathRejection>,
    body: Result<Json<StepRequest>, JsonRejection>,
) -> Result<Json<ActionReply>, ApiError> {
    let Path(id) = id?;
    let Json(req) = body?;
    s.ask(|r| Msg::Step(id, req, r)).await.map(Json)
}

async fn close(
    State(s): State<AppState>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<StatusCode, ApiError> {
    let Path(id) = id?;
    s.ask(|r| Msg::Close(id, r)).await.map(|()| StatusCode::NO_CONTENT)
}

async fn not_found() -> ApiError {
    ApiError::new(
        StatusCode::NOT_FOUND,
        "unknown route: GET /v1/health, GET /v1/info, POST /v1/episodes, POST /v1/episodes/{id}/step, DELETE /v1/episodes/{id}",
    )
}

/// A running server: its address, and a handle to stop it.
pub struct Server {
    pub addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<(), ServeError>>>,
}

impl Server {
    /// Starts serving `run` on a thread of its own; returns once the socket is bound.
    pub fn start(run: Policy, opts: ServeOptions) -> Result<Self, ServeError> {
        // Served as saved, an MT-BC-Finetune checkpoint would be another policy than the one
        // evaluated (the check `promptdt render` makes too).
        run.check_acts_as_evaluated("serve").map_err(|e| ServeError::Invalid(e.to_string()))?;
        check_adapt(run.method, &opts)?;
        auth::check(&opts.listen, &opts.auth)?;
        let max_connections = check(&opts)?;
        let listener = std::net::TcpListener::bind(opts.listen)
            .map_err(|source| ServeError::Bind { addr: opts.listen, source })?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let (tx, rx) = mpsc::sync_channel::<Msg>(opts.queue);
        let body = conn::BodyLimits { max_bytes: opts.max_body_bytes, timeout: opts.body_timeout };
        let limits = conn::ConnLimits { max_connections, header_timeout: opts.header_timeout };
        let grace = opts.body_timeout + Duration::from_secs(1);
        let token = match &opts.auth {
            Auth::Token(t) => Some(Arc::new(t.clone())),
            Auth::LoopbackOnly | Auth::Disabled => None,
        };
        let worker = Worker::new(run, opts);
        let alive = Arc::new(AtomicBool::new(true));
        let guard = AliveGuard(Arc::clone(&alive));
        std::thread::Builder::new().name("pdt-serve-model".into()).spawn(move || {
            let _guard = guard;
            worker.run(rx);
        })?;
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let app = Router::new()
            .route(auth::HEALTH_PATH, get(health))
            .route("/v1/info", get(info))
            .route("/v1/episodes", post(open))
            .route("/v1/episodes/{id}/step", post(step))
            .route("/v1/episodes/{id}", axum::routing::delete(close))
            .fallback(not_found)
            .layer(DefaultBodyLimit::max(body.max_bytes))
            .layer(axum::middleware::from_fn_with_state(body, conn::read_body));
        // The token is checked first (the outermost layer): a request without it is refused
        // before its body is read.
        let app = match token {
            Some(t) => app.layer(axum::middleware::from_fn_with_state(t, auth::require_token)),
            None => app,
        };
        let app = app.with_state(AppState { tx, alive });
        let thread =
            std::thread::Builder::new().name("pdt-serve-http".into()).spawn(move || {
                let rt = tokio::runtime::Builder::new_multi_thread()
                    .enable_all()
                    .worker_threads(2)
                    .build()?;
                rt.block_on(async move {
                    let listener = tokio::net::TcpListener::from_std(listener)?;
                    conn::accept_loop(listener, app, limits, grace, stop_rx).await;
                    Ok(())
                })
            })?;
        Ok(Self { addr, stop: Some(stop_tx), thread: Some(thread) })
    }

    /// Serves until the process is interrupted (Ctrl-C).
    pub fn wait_for_ctrl_c(mut self) -> Result<(), ServeError> {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        rt.block_on(async {
            let _ = tokio::signal::ctrl_c().await;
        });
        self.shutdown()
    }

    /// Stops accepting, finishes the requests in flight, and joins the server thread.
    pub fn shutdown(&mut self) -> Result<(), ServeError> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        match self.thread.take().map(std::thread::JoinHandle::join) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(ServeError::Invalid("the server thread panicked".into())),
            None => Ok(()),
        }
    }
}

/// Refuses the server adaptation settings (`--adapt` and its flags) that would refuse, or
/// silently skip, every episode opened with a `task`, naming the flags.
fn check_adapt(method: pdt_rundir::config::Method, opts: &ServeOptions) -> Result<(), ServeError> {
    let cfg = &opts.adapt;
    if cfg.ptdt.score == pdt_rundir::config::PtdtScore::Return {
        // Any episode adapted by PTDT would be refused (a request may name `adapt: ptdt`).
        return Err(ServeError::Invalid(
            "--ptdt-score return ranks PTDT's candidate prompts by episodes in the task's \
             environment, which only `promptdt eval` steps (a served episode's environment is \
             the client's); serve with --ptdt-score action-loss (the default)"
                .into(),
        ));
    }
    if cfg.is_none() {
        return Ok(());
    }
    if !method.uses_prompt() {
        return Err(ServeError::Invalid(format!(
            "--adapt {}: this run's method ({}) takes no prompt, and the adaptations adapt a \
             prompt or act through one (prompt-dt and prompt-mt-bc runs); serve it without --adapt",
            cfg.kind,
            method.name()
        )));
    }
    let s = opts.prompt_strategy.strategy;
    if s.per_episode() || s.learns_from_returns() {
        return Err(ServeError::Invalid(format!(
            "--adapt {} with --prompt-strategy {s}: an adaptation starts from one prompt per \
             task, and {s} picks one per episode or learns across them; use --prompt-strategy \
             reference, random-segment or best-return, or no --adapt",
            cfg.kind
        )));
    }
    Ok(())
}

/// Checks the limits of `opts` (each named as its `promptdt serve` flag); returns the connection
/// limit to apply.
fn check(opts: &ServeOptions) -> Result<usize, ServeError> {
    let bad = |m: String| Err(ServeError::Invalid(m));
    if opts.max_batch == 0 || opts.max_episodes == 0 || opts.queue == 0 {
        return bad("max_batch, max_episodes and the queue must be at least 1".into());
    }
    if opts.batch_wait > MAX_BATCH_WAIT {
        return bad(format!(
            "batch wait (--batch-wait-ms) of {:?} is over {MAX_BATCH_WAIT:?}",
            opts.batch_wait
        ));
    }
    if let Err(e) = opts.prompt_strategy.validate() {
        return bad(format!("--prompt-strategy: {e}"));
    }
    if let Err(e) = opts.adapt.validate() {
        return bad(format!("--adapt: {e}"));
    }
    if opts.idle_timeout.is_zero() {
        // 0 would close every episode at once.
        return bad("idle timeout (--idle-timeout-s) must be more than 0".into());
    }
    for (name, t) in [("header", opts.header_timeout), ("body", opts.body_timeout)] {
        if t.is_zero() || t > MAX_IO_TIMEOUT {
            return bad(format!(
                "{name} timeout (--{name}-timeout-s) of {t:?} is outside (0 s, {MAX_IO_TIMEOUT:?}]"
            ));
        }
    }
    let budget = conn::connection_budget();
    match (opts.max_connections, budget) {
        (Some(n), _) if n == 0 || n > conn::MAX_CONNECTIONS => bad(format!(
            "max connections (--max-connections) must be between 1 and {}, got {n}",
            conn::MAX_CONNECTIONS
        )),
        (Some(n), Some(room)) if n > room => bad(format!(
            "{n} connections (--max-connections) need more descriptors than this process may \
             open: its limit (ulimit -n) is {}, of which {} are kept for the server, so at most \
             {room}; raise the limit or lower --max-connections",
            room + conn::RESERVED_DESCRIPTORS,
            conn::RESERVED_DESCRIPTORS
        )),
        (Some(n), _) => Ok(n),
        (None, Some(0)) => bad(format!(
            "this process may open only {} descriptors (ulimit -n), fewer than the {} the server \
             keeps for itself; raise the limit",
            conn::descriptor_limit().unwrap_or(0),
            conn::RESERVED_DESCRIPTORS
        )),
        (None, Some(room)) => Ok(room.min(conn::DEFAULT_MAX_CONNECTIONS)),
        (None, None) => Ok(conn::DEFAULT_MAX_CONNECTIONS),
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.shutdown();
    }
}
