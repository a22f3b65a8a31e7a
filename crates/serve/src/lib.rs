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
use pdt_policy::{Policy, PolicyError};
use pdt_rundir::config::Method;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::Duration;

pub mod auth;
pub mod conn;
mod wire;
mod worker;

use worker::{Msg, Reply, Worker};

pub use auth::{Auth, Token};
pub use worker::adapt::MAX_ADAPTATIONS;

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

pub use wire::{ActionReply, Info, OpenRequest, StepRequest};

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
fn check_adapt(method: Method, opts: &ServeOptions) -> Result<(), ServeError> {
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
             prompt or act through one ({} runs); serve it without --adapt",
            cfg.kind,
            method.name(),
            Method::names_where(Method::uses_prompt)
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
