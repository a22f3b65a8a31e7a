//! `promptdt serve`: a trained prompted policy behind HTTP+JSON (`docs/serve.md`).
//!
//! A client opens an episode with a prompt (arrays it sends, or a task of the run whose prompt the
//! server draws as the evaluation does) and its first observation, and gets the first action; then
//! it sends each reward and next observation and gets the next action; it closes the episode (or
//! the server does after an idle timeout). Many episodes run at once: the HTTP side (tokio + axum)
//! only parses and validates; one model thread owns the policy and every episode's history, takes
//! the requests that arrived within a bounded wait (at most `max_batch`), and answers them with one
//! batched forward. Each episode acts exactly as `promptdt eval` would (`pdt_eval::History`,
//! `PromptDt::act`, the prompt's keys and values computed once when the episode opens).

use axum::extract::rejection::{JsonRejection, PathRejection};
use axum::extract::{DefaultBodyLimit, Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use pdt_eval::{first_rtg, History};
use pdt_model::PrefixCache;
use pdt_prompt::{SegmentBatch, StateNorm};
use pdt_train::run::ServedRun;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::mpsc;
use std::time::{Duration, Instant};

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
    /// Largest request body (413 beyond).
    pub max_body_bytes: usize,
    /// Requests waiting for the model thread at most (503 beyond).
    pub queue: usize,
    /// libtorch intra-op threads of the model thread (0: libtorch's default, all cores). With 1,
    /// an episode gets the same bits alone or batched with others on AVX2 CPUs (within 1e-6 on
    /// AVX-512 ones, whose kernels depend on the batch size).
    pub threads: usize,
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
            queue: 4096,
            threads: 0,
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
}

// ------------------------------------------------------------------------------------------------
// The wire format
// ------------------------------------------------------------------------------------------------

/// A prompt sent by the client (the same arrays a Python `Policy` takes).
pub use pdt_train::run::PromptArrays;

/// `POST /v1/episodes`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpenRequest {
    /// The prompt as arrays; or
    #[serde(default)]
    pub prompt: Option<PromptArrays>,
    /// a task of the run, whose prompt the server draws as the evaluation does
    #[serde(default)]
    pub task: Option<usize>,
    /// with this seed (default 0).
    #[serde(default)]
    pub prompt_seed: Option<u64>,
    /// G* (default: the run's).
    #[serde(default)]
    pub target_return: Option<f64>,
    /// The first observation (raw).
    pub observation: Vec<f64>,
}

/// `POST /v1/episodes/{id}/step`: the reward of the last action and the observation after it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepRequest {
    pub reward: f64,
    pub observation: Vec<f64>,
}

/// The action to take at step `t` of episode `episode`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionReply {
    pub episode: u64,
    pub t: usize,
    pub action: Vec<f32>,
}

/// `GET /v1/info`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Info {
    pub method: String,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub k: usize,
    pub prompt_steps: usize,
    pub uses_prompt: bool,
    pub target_return: f32,
    pub rtg_scale: f32,
    pub max_ep_len: usize,
    pub iteration: u64,
    /// Tasks `task` may name (empty when the run's data were not readable).
    pub prompt_tasks: Vec<usize>,
    pub max_episodes: usize,
    pub max_batch: usize,
    pub open_episodes: usize,
}

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
    h: History,
    /// The prompt's keys and values (one row), `None` for methods without a prompt.
    prefix: Option<PrefixCache>,
    /// The action returned last (recorded with the next reward and observation).
    last_action: Vec<f32>,
    seen: Instant,
}

/// What the model thread owns: the policy and every open episode.
struct Worker {
    run: ServedRun,
    opts: ServeOptions,
    norm: StateNorm,
    episodes: HashMap<u64, Episode>,
    next_id: u64,
}

/// An action to compute in this batch, and where its answer goes.
struct Pending {
    id: u64,
    reply: Reply<ActionReply>,
}

impl Worker {
    fn new(run: ServedRun, opts: ServeOptions) -> Self {
        let norm = run.norm();
        Self { run, opts, norm, episodes: HashMap::new(), next_id: 1 }
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
                        Ok(id) => pending.push(Pending { id, reply }),
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
                            Ok(()) => pending.push(Pending { id, reply }),
                            Err(e) => {
                                let _ = reply.send(Err(e));
                            }
                        }
                    }
                    Msg::Close(id, reply) => {
                        let r = match self.episodes.remove(&id) {
                            Some(_) => Ok(()),
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
            max_ep_len: r.model.cfg.max_ep_len,
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

    fn observation(&self, obs: &[f64]) -> Result<Vec<f32>, ApiError> {
        self.run.observation(obs).map_err(ApiError::bad)
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
        let obs = self.observation(&req.observation)?;
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
            (true, Some(p), None) => Some(self.prompt_from_arrays(&p)?),
            (true, None, Some(task)) => Some(
                self.run.task_prompt(task, req.prompt_seed.unwrap_or(0)).map_err(ApiError::bad)?,
            ),
            (true, None, None) => {
                return Err(ApiError::bad(
                    "this run's method takes a prompt: send `prompt` (arrays) or `task`",
                ))
            }
        };
        let target = match req.target_return {
            Some(g) if !g.is_finite() || g.abs() > 1e30 => {
                return Err(ApiError::bad(format!("target_return {g} is not a finite return")))
            }
            Some(g) => g as f32,
            None => self.run.stats.target_return,
        };
        let prefix = match &prompt {
            Some(p) => Some(self.run.prefix(&[p]).map_err(ApiError::bad)?),
            None => None,
        };
        let rtg0 = first_rtg(self.run.returns, target, self.run.stats.rtg_scale);
        let id = self.next_id;
        self.next_id += 1;
        self.episodes.insert(
            id,
            Episode {
                h: History::start(&self.norm, &obs, rtg0),
                prefix,
                last_action: Vec::new(),
                seen: Instant::now(),
            },
        );
        Ok(id)
    }

    fn prompt_from_arrays(&self, p: &PromptArrays) -> Result<SegmentBatch, ApiError> {
        self.run.prompt_from_arrays(p).map_err(ApiError::bad)
    }

    fn step(&mut self, id: u64, req: StepRequest) -> Result<(), ApiError> {
        let obs = self.observation(&req.observation)?;
        if !req.reward.is_finite() || req.reward.abs() > 1e30 {
            return Err(ApiError::bad(format!("reward {} is not a finite reward", req.reward)));
        }
        let max_t = self.run.model.cfg.max_ep_len;
        let (returns, scale) = (self.run.returns, self.run.stats.rtg_scale);
        let norm = &self.norm;
        let e = self.episodes.get_mut(&id).ok_or_else(|| unknown(id))?;
        if e.h.t + 1 >= max_t {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                format!(
                    "episode {id} has reached the model's max_ep_len ({max_t} steps); close it"
                ),
            ));
        }
        e.seen = Instant::now();
        let last = std::mem::take(&mut e.last_action);
        e.h.record(&last, req.reward as f32, &obs, norm, returns, scale);
        Ok(())
    }

    /// Answers every pending action: one forward per group of episodes with prompts of the same
    /// length (in practice: all of them).
    fn act(&mut self, pending: Vec<Pending>) {
        let mut groups: Vec<(i64, Vec<Pending>)> = Vec::new();
        for p in pending {
            let len = self
                .episodes
                .get(&p.id)
                .and_then(|e| e.prefix.as_ref())
                .map_or(-1, PrefixCache::len);
            match groups.iter_mut().find(|(l, _)| *l == len) {
                Some((_, g)) => g.push(p),
                None => groups.push((len, vec![p])),
            }
        }
        let da = self.run.stats.act_dim;
        for (_, group) in groups {
            let eps: Vec<&Episode> =
                group.iter().filter_map(|p| self.episodes.get(&p.id)).collect();
            if eps.len() != group.len() {
                for p in group {
                    let _ = p.reply.send(Err(ApiError::new(
                        StatusCode::INTERNAL_SERVER_ERROR,
                        "episode vanished",
                    )));
                }
                continue;
            }
            let hs: Vec<&History> = eps.iter().map(|e| &e.h).collect();
            let prefixes: Option<Vec<&PrefixCache>> =
                eps.iter().map(|e| e.prefix.as_ref()).collect();
            let prefix = prefixes.and_then(|p| PrefixCache::cat(&p));
            let flat = self.run.act(&hs, prefix.as_ref()); // [A * da]
            for (p, a) in group.into_iter().zip(flat.chunks_exact(da)) {
                if let Some(e) = self.episodes.get_mut(&p.id) {
                    e.last_action = a.to_vec();
                    let _ = p.reply.send(Ok(ActionReply {
                        episode: p.id,
                        t: e.h.t,
                        action: a.to_vec(),
                    }));
                }
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
        "unknown route: GET /v1/info, POST /v1/episodes, POST /v1/episodes/{id}/step, DELETE /v1/episodes/{id}",
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
    pub fn start(run: ServedRun, opts: ServeOptions) -> Result<Self, ServeError> {
        if run.method == pdt_train::config::Method::MtBcFinetune {
            // Its evaluation fine-tunes on each task's demonstrations before acting; served as is
            // it would be another policy than the one evaluated.
            return Err(ServeError::Invalid(
                "an mt-bc-finetune run adapts to each task by fine-tuning before it acts; serving \
                 it is not supported (serve prompt-dt, prompt-mt-bc or mt-orl runs)"
                    .into(),
            ));
        }
        if opts.max_batch == 0 || opts.max_episodes == 0 || opts.queue == 0 {
            return Err(ServeError::Invalid(
                "max_batch, max_episodes and the queue must be at least 1".into(),
            ));
        }
        let listener = std::net::TcpListener::bind(opts.listen)
            .map_err(|source| ServeError::Bind { addr: opts.listen, source })?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let (tx, rx) = mpsc::sync_channel::<Msg>(opts.queue);
        let body_limit = opts.max_body_bytes;
        let worker = Worker::new(run, opts);
        std::thread::Builder::new().name("pdt-serve-model".into()).spawn(move || worker.run(rx))?;
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let app = Router::new()
            .route("/v1/info", get(info))
            .route("/v1/episodes", post(open))
            .route("/v1/episodes/{id}/step", post(step))
            .route("/v1/episodes/{id}", axum::routing::delete(close))
            .fallback(not_found)
            .layer(DefaultBodyLimit::max(body_limit))
            .with_state(AppState { tx });
        let thread =
            std::thread::Builder::new().name("pdt-serve-http".into()).spawn(move || {
                let rt = tokio::runtime::Builder::new_multi_thread()
                    .enable_all()
                    .worker_threads(2)
                    .build()?;
                rt.block_on(async move {
                    let listener = tokio::net::TcpListener::from_std(listener)?;
                    axum::serve(listener, app)
                        .with_graceful_shutdown(async {
                            let _ = stop_rx.await;
                        })
                        .await?;
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

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.shutdown();
    }
}
