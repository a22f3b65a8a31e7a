//! Speed of one training step and of inference, side by side with PyTorch running the same model
//! (`scripts/bench/bench_torch.py`) in the same invocation.
//!
//! Cases (state 20, action 6, K = 20, prompt 5 steps, the reference architecture):
//! `train_b560` / `train_b64` (forward in train mode, masked MSE, backward, clipping, AdamW; the
//! per-tensor AdamW, PyTorch's single-tensor path), `train_b560_flat` / `train_b64_flat` (the same
//! step as a run on CUDA takes it: the flat-buffer AdamW, `optim.flat = "on"`, and the last block
//! for the state tokens only, `LastBlock::StateTokens`; PyTorch's side is its default AdamW),
//! `train_b560_flat_all` (the same with the last block on every token, as before
//! `train.last_block`) and
//! `infer_b1` / `infer_b50` (eval-mode forward without autograd: one rollout step for 1 or 50
//! episodes). Inputs are random but shaped like the reference's batches: left-padded histories.

use cases::{is_eval, is_macaw, is_pack, is_render, is_rl, is_serve, pytorch_report, serve_cases};
use pdt_base::device::Matmul;
use pdt_base::table::{Rule, Table};
use pdt_model::prompt_dt::{Act, Sequence};
use pdt_model::{LastBlock, PromptDt, PromptDtConfig, Segments};
mod cases;
pub mod pack;
mod precision;
pub mod profile;
pub mod record;
pub mod render;
pub mod serve;

use pdt_rundir::config::{AdamWConfig, FlatOptim};
use pdt_train::optim::Optimizer;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;
use tch::{nn::VarStore, Device, Kind, Tensor};

/// What to measure.
#[derive(Debug, Clone)]
pub struct BenchConfig {
    /// libtorch intra-op threads (PyTorch gets the same).
    pub threads: usize,
    /// Timed iterations per case (after `warmup` untimed ones).
    pub iters: usize,
    pub warmup: usize,
    pub device: Device,
    /// How the model's products are computed (`--matmul`; PyTorch's baseline gets the same: TF32
    /// through its cuBLAS switch, bf16 through `torch.autocast`). With `bf16` the run also times
    /// both engines in fp32 on the same cases ([`BenchReport::fp32`]).
    pub matmul: Matmul,
    /// Also count what one iteration of each model, pack, RL and MACAW case runs (`profile`).
    pub profile: bool,
    /// Cases to run: any of `train_b560`, `train_b64`, `train_b560_flat`, `train_b64_flat`,
    /// `infer_b1`, `infer_b50` (and the other kinds `BenchError::UnknownCase` lists).
    pub cases: Vec<String>,
    /// Run the PyTorch baseline with this Python and script (None: promptdt only).
    pub pytorch: Option<PyTorchBaseline>,
    /// The reference's one-episode-at-a-time evaluation loop in PyTorch, for `eval_point_robot`.
    pub pytorch_eval_script: Option<PathBuf>,
    /// Episodes per task of `eval_point_robot`.
    pub eval_episodes: usize,
    /// The PyTorch SAC / TD3 script, for the `sac_h*_b*` / `td3_h*_b*` cases.
    pub pytorch_rl_script: Option<PathBuf>,
    /// The PyTorch MACAW script, for the `macaw_w<W>_t<T>` cases.
    pub pytorch_macaw_script: Option<PathBuf>,
    /// The run `serve_c<N>` cases serve.
    pub serve_run: Option<PathBuf>,
    /// Steps per served episode (and episodes per client) of `serve_c<N>`.
    pub serve_steps: usize,
    pub serve_episodes: usize,
}

/// One `serve_c<N>` case: N episodes at once against `promptdt serve` on loopback.
#[derive(Debug, Clone, Serialize)]
pub struct ServeCase {
    pub name: String,
    pub clients: usize,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub actions_per_s: f64,
    pub requests: usize,
}

#[derive(Debug, Clone)]
pub struct PyTorchBaseline {
    pub python: PathBuf,
    pub script: PathBuf,
}

/// Timing of one case (milliseconds per iteration).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaseTiming {
    pub name: String,
    pub median_ms: f64,
    pub p10_ms: f64,
    pub p90_ms: f64,
    pub iters: usize,
    /// The PyTorch baseline's count of what one iteration runs, with `--profile`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<profile::OpCounts>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EngineReport {
    pub engine: String,
    #[serde(default)]
    pub torch_version: Option<String>,
    pub threads: usize,
    pub results: Vec<CaseTiming>,
}

/// Both engines' numbers, and PyTorch's median divided by promptdt's (above 1: promptdt is faster).
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub device: String,
    /// With `--matmul tf32` on a CUDA device: how far a product computed with TF32 lies from the
    /// same product in fp32 (`tf32_effect`), which shows that cuBLAS took the switch.
    pub tf32_effect: Option<f64>,
    /// With `--profile`: what one iteration of each profiled case runs.
    pub profiles: Vec<profile::CaseProfile>,
    pub serve: Vec<ServeCase>,
    pub promptdt: EngineReport,
    pub pytorch: Option<EngineReport>,
    pub speedup: Vec<(String, f64)>,
    /// With `--matmul bf16`: the same cases in fp32, in the same run (both engines), for the
    /// bf16-over-fp32 ratios.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fp32: Option<Box<BenchReport>>,
    /// With `--matmul bf16` on hardware without native bf16 (`PROMPTDT_BF16_EMULATED=1`): the
    /// timings are of libtorch's emulation, not of bf16 hardware (never recorded as such).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub bf16_emulated: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("unknown benchmark case `{0}` (expected train_b<N>[_flat|_flat_all], infer_b<N>, act_b<N>, eval_<family>[_full][_b<N>], sac_h<H>_b<B>, td3_h<H>_b<B>, macaw_w<W>_t<T>, pack<N>_b<B>[_flat|_pt] or solo<N>_b<B>[_flat|_pt])")]
    UnknownCase(String),
    #[error("running the PyTorch baseline `{cmd}` failed: {why}")]
    Baseline { cmd: String, why: String },
    #[error("pack case `{case}`: {why}")]
    Pack { case: String, why: String },
    #[error("render case `{case}`: {why}")]
    Render { case: String, why: String },
    #[error(transparent)]
    Matmul(#[from] pdt_torch::device::MatmulError),
    #[error(transparent)]
    Profiler(#[from] pdt_torch::profiler::ProfilerError),
}

/// The evaluation case: the whole few-shot protocol on the point robot's 5 held-out goals.
pub const EVAL_CASE: &str = "eval_point_robot";

/// What a model case times.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    /// `train_b<N>`: one training step (per-tensor AdamW).
    Train,
    /// `train_b<N>_flat`: one training step in the CUDA configuration (the flat-buffer AdamW, the
    /// last block for the state tokens only).
    TrainFlat,
    /// `train_b<N>_flat_all`: the same with the last block on every token (the CUDA
    /// configuration before `train.last_block`), to time what the state tokens save.
    TrainFlatAll,
    /// `infer_b<N>`: one rollout step by the reference's path, the full forward.
    Infer,
    /// `act_b<N>`: one rollout step by `PromptDt::forward` (`Act`) with the prompt's keys and
    /// values cached (promptdt only; compare with `infer_b<N>` of the same run).
    Act,
}

fn parse_case(name: &str) -> Result<(Mode, i64), BenchError> {
    let bad = || BenchError::UnknownCase(name.to_string());
    let (mode, b) = if let Some(b) = name.strip_prefix("train_b") {
        if let Some(b) = b.strip_suffix("_flat_all") {
            (Mode::TrainFlatAll, b)
        } else if let Some(b) = b.strip_suffix("_flat") {
            (Mode::TrainFlat, b)
        } else {
            (Mode::Train, b)
        }
    } else if let Some(b) = name.strip_prefix("infer_b") {
        (Mode::Infer, b)
    } else if let Some(b) = name.strip_prefix("act_b") {
        (Mode::Act, b)
    } else {
        return Err(bad());
    };
    b.parse::<i64>().ok().filter(|&b| b > 0).map(|b| (mode, b)).ok_or_else(bad)
}

/// An evaluation-protocol case: `eval_<family>[_full][_b<N>]` (e.g. `eval_point_robot`,
/// `eval_cheetah_vel`). `_full` uses the
/// reference's full forward at every step (default: the cached path); `_b<N>` steps at most N
/// episodes together (default: all of them).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct EvalCase {
    env: &'static str,
    inference: pdt_rundir::config::Inference,
    max_batch: usize,
}

fn parse_eval_case(name: &str) -> Option<EvalCase> {
    let rest = name.strip_prefix("eval_")?;
    // Any family: the longest name that prefixes the rest (no family name prefixes another's
    // today, but `_full` must not be read as part of one).
    let (env, rest) = pdt_envs::FAMILY_NAMES
        .iter()
        .filter_map(|&f| rest.strip_prefix(f).map(|r| (f, r)))
        .max_by_key(|(f, _)| f.len())?;
    let (inference, rest) = match rest.strip_prefix("_full") {
        Some(r) => (pdt_rundir::config::Inference::Full, r),
        None => (pdt_rundir::config::Inference::Cached, rest),
    };
    let max_batch = match rest {
        "" => 1 << 20,
        r => r.strip_prefix("_b")?.parse().ok().filter(|&b| b > 0)?,
    };
    Some(EvalCase { env, inference, max_batch })
}

/// Random segments of `b` samples x `t` steps; histories left-padded to a random length.
pub(crate) fn random_segments(
    b: i64,
    t: i64,
    ds: i64,
    da: i64,
    full: bool,
    dev: Device,
) -> Segments {
    let opts = (Kind::Float, dev);
    let tlen = if full {
        Tensor::full([b], t, (Kind::Int64, dev))
    } else {
        Tensor::randint_low(1, t + 1, [b], (Kind::Int64, dev))
    };
    let pos = Tensor::arange(t, (Kind::Int64, dev));
    let mask = pos.unsqueeze(0).ge_tensor(&(t - tlen).unsqueeze(1)); // [b, t] bool
    let start = Tensor::randint_low(0, 1000 - t, [b, 1], (Kind::Int64, dev));
    let timesteps =
        (start + pos.unsqueeze(0)).where_self(&mask, &Tensor::zeros([1], (Kind::Int64, dev)));
    Segments {
        states: Tensor::randn([b, t, ds], opts),
        actions: Tensor::rand([b, t, da], opts) * 2.0 - 1.0,
        returns_to_go: Tensor::rand([b, t, 1], opts),
        timesteps,
        mask: mask.to_kind(Kind::Float),
    }
}

/// Median and 10th/90th percentiles of per-iteration milliseconds.
fn timing(name: &str, mut ms: Vec<f64>) -> CaseTiming {
    ms.sort_by(f64::total_cmp);
    let iters = ms.len();
    if ms.is_empty() {
        ms.push(f64::NAN);
    }
    CaseTiming {
        name: name.to_string(),
        median_ms: percentile(&ms, 0.5),
        p10_ms: percentile(&ms, 0.1),
        p90_ms: percentile(&ms, 0.9),
        iters,
        profile: None,
    }
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i]
}

fn time_case(
    model: &mut PromptDt,
    opts: &mut Optimizers<'_>,
    name: &str,
    cfg: &BenchConfig,
) -> Result<CaseTiming, BenchError> {
    let (mode, b) = parse_case(name)?;
    let opt = opts.get(matches!(mode, Mode::TrainFlat | Mode::TrainFlatAll));
    // The other cases keep the reference's ops, as PyTorch's side runs them.
    model.set_last_block(if mode == Mode::TrainFlat {
        LastBlock::StateTokens
    } else {
        LastBlock::AllTokens
    });
    let model = &*model;
    let dev = cfg.device;
    let history = random_segments(b, 20, 20, 6, false, dev);
    let prompt = random_segments(b, 5, 20, 6, true, dev);
    // As in an evaluation: the prompts' keys and values once (5 tasks), then rows per step.
    let tasks = random_segments(5, 5, 20, 6, true, dev);
    let cache = tch::no_grad(|| model.prefix(&tasks, None));
    let rows = Tensor::arange(b, (Kind::Int64, dev)).remainder(5);
    let mut run = || {
        if mode == Mode::Act {
            let a = tch::no_grad(|| {
                model.forward(&history, Act { prompt: Some(&cache.select(&rows)), lora: None })
            });
            let _ = a.to_device(Device::Cpu);
        } else if matches!(mode, Mode::Train | Mode::TrainFlat | Mode::TrainFlatAll) {
            let preds = model.forward(&history, Sequence::train(Some(&prompt)));
            let loss = PromptDt::action_loss(&preds, &history.actions, &history.mask);
            let mut grads = opt.backward(&loss);
            // The norm is not read (as PyTorch's bench: reading would wait for the device).
            let _ = opt.clip_grad_norm(&mut grads, 0.25);
            opt.step(&grads, 1e-4);
        } else {
            let preds = tch::no_grad(|| model.forward(&history, Sequence::eval(Some(&prompt))));
            // Acting needs the action on the host: include the copy, as a rollout would.
            let _ = preds.select(1, -1).to_device(Device::Cpu);
        }
        if let Device::Cuda(_) = dev {
            tch::Cuda::synchronize(0);
        }
    };
    for _ in 0..cfg.warmup {
        run();
    }
    let mut ms: Vec<f64> = (0..cfg.iters)
        .map(|_| {
            let t0 = Instant::now();
            run();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    ms.sort_by(f64::total_cmp);
    Ok(CaseTiming {
        name: name.to_string(),
        median_ms: percentile(&ms, 0.5),
        p10_ms: percentile(&ms, 0.1),
        p90_ms: percentile(&ms, 0.9),
        iters: cfg.iters,
        profile: None,
    })
}

/// The model's two optimisers, each built the first time a case needs it (building the flat one
/// re-points the model's variables at its buffer; the per-tensor one shares those variables).
struct Optimizers<'a> {
    vs: &'a VarStore,
    names: Vec<String>,
    per_tensor: Option<Optimizer>,
    flat: Option<Optimizer>,
}

impl Optimizers<'_> {
    fn get(&mut self, flat: bool) -> &mut Optimizer {
        let (slot, mode) = if flat {
            (&mut self.flat, FlatOptim::On)
        } else {
            (&mut self.per_tensor, FlatOptim::Off)
        };
        slot.get_or_insert_with(|| {
            Optimizer::new(
                self.vs,
                &self.names,
                AdamWConfig { flat: mode, ..AdamWConfig::default() },
            )
        })
    }
}

/// The `--device` value of the PyTorch baseline scripts for `dev`.
fn torch_device_arg(dev: Device) -> &'static str {
    if dev.is_cuda() {
        "cuda"
    } else {
        "cpu"
    }
}

fn run_pytorch(base: &PyTorchBaseline, cfg: &BenchConfig) -> Result<EngineReport, BenchError> {
    let device = torch_device_arg(cfg.device);
    let mut cmd = Command::new(&base.python);
    cmd.arg(&base.script)
        .args(["--threads", &cfg.threads.to_string(), "--iters", &cfg.iters.to_string()])
        .args([
            "--warmup",
            &cfg.warmup.to_string(),
            "--device",
            device,
            "--matmul",
            cfg.matmul.as_str(),
            "--cases",
            &cfg.cases.join(","),
        ]);
    if cfg.profile {
        cmd.arg("--profile");
    }
    let shown = format!("{cmd:?}");
    let out = cmd
        .output()
        .map_err(|e| BenchError::Baseline { cmd: shown.clone(), why: e.to_string() })?;
    if !out.status.success() {
        let why = format!("{}: {}", out.status, String::from_utf8_lossy(&out.stderr).trim());
        return Err(BenchError::Baseline { cmd: shown, why });
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().rev().find(|l| l.trim_start().starts_with('{')).unwrap_or("");
    serde_json::from_str(line).map_err(|e| BenchError::Baseline {
        cmd: shown,
        why: format!("unreadable output ({e}): {text}"),
    })
}

/// Times the whole evaluation protocol of `case`: the family's default test tasks x
/// `eval_episodes` episodes (point robot: 5 tasks of 20 steps, goals 2, 10, 18, 26, 34;
/// Cheetah-Vel: 5 tasks of 200 steps), K = 20, a 5-step prompt per task, the reference
/// architecture with the family's dims.
fn time_eval(name: &str, case: EvalCase, cfg: &BenchConfig) -> Result<CaseTiming, BenchError> {
    use pdt_eval::{evaluate, EvalReturns, EvalSettings, EvalTask};
    use pdt_prompt::{SegmentBatch, StateNorm};
    let err = |why: String| BenchError::Baseline { cmd: case.env.into(), why };
    let family = pdt_envs::family(case.env).map_err(|e| err(e.to_string()))?;
    let preset = family.preset();
    let (ds, da) = (preset.obs_dim, preset.act_dim);
    tch::manual_seed(0);
    let vs = VarStore::new(cfg.device);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(ds, da));
    let (_, test) = family.split("default").map_err(|e| err(e.to_string()))?;
    // The family's default test tasks (the point robot's are goals 2, 10, 18, 26, 34).
    let task_ids = test;
    let tasks = || -> Result<Vec<EvalTask>, BenchError> {
        task_ids
            .iter()
            .map(|&i| {
                // A deterministic demonstration-like prompt: the point robot's walks to its goal.
                let goal = pdt_envs::point_robot::goal(i).unwrap_or([0.0, 1.0]);
                let states: Vec<f32> = (0..5)
                    .flat_map(|t| {
                        (0..ds).map(move |j| {
                            let g = if j % 2 == 0 { goal[0] } else { goal[1] };
                            g * (15 + t) as f32 / 20.0 + 0.01 * j as f32
                        })
                    })
                    .collect();
                let actions: Vec<f32> =
                    (0..5 * da).map(|j| 0.1 * if j % 2 == 0 { goal[0] } else { goal[1] }).collect();
                let prompt = SegmentBatch {
                    batch: 1,
                    steps: 5,
                    state_dim: ds,
                    act_dim: da,
                    states,
                    actions,
                    returns_to_go: vec![-0.05; 5],
                    timesteps: (14..19).collect(),
                    mask: vec![1.0; 5],
                };
                let envs =
                    (0..cfg.eval_episodes).map(|_| family.make(i)).collect::<Result<Vec<_>, _>>();
                let envs = envs.map_err(|e| err(e.to_string()))?;
                Ok(EvalTask {
                    name: format!("{}-{i}", case.env),
                    index: i,
                    envs,
                    seeds: (0..cfg.eval_episodes as u64).collect(),
                    prompt: Some(prompt),
                    target_return: None,
                })
            })
            .collect()
    };
    let settings = EvalSettings {
        k: 20,
        horizon: preset.horizon,
        rtg_scale: preset.rtg_scale,
        target_return: preset.target_return,
        returns: EvalReturns::Decreasing,
        norm: StateNorm::identity(ds),
        max_batch: case.max_batch,
        device: cfg.device,
        env_threads: 1,
        inference: case.inference,
    };
    let mut secs = Vec::new();
    for i in 0..cfg.iters.min(5) + 1 {
        let t = tasks()?;
        let t0 = Instant::now();
        evaluate(&model, t, &settings).map_err(|e| err(e.to_string()))?;
        if i > 0 {
            secs.push(t0.elapsed().as_secs_f64() * 1e3);
        }
    }
    secs.sort_by(f64::total_cmp);
    Ok(CaseTiming {
        name: name.into(),
        median_ms: percentile(&secs, 0.5),
        p10_ms: percentile(&secs, 0.1),
        p90_ms: percentile(&secs, 0.9),
        iters: secs.len(),
        profile: None,
    })
}

/// The reference's one-episode-at-a-time loop in PyTorch (`scripts/bench/bench_eval_torch.py`).
fn run_pytorch_eval(
    python: &std::path::Path,
    script: &std::path::Path,
    cfg: &BenchConfig,
) -> Result<CaseTiming, BenchError> {
    let device = torch_device_arg(cfg.device);
    let mut cmd = Command::new(python);
    cmd.arg(script).args([
        "--threads",
        &cfg.threads.to_string(),
        "--episodes",
        &cfg.eval_episodes.to_string(),
        "--repeats",
        "3",
        "--device",
        device,
    ]);
    let shown = format!("{cmd:?}");
    let out = cmd
        .output()
        .map_err(|e| BenchError::Baseline { cmd: shown.clone(), why: e.to_string() })?;
    if !out.status.success() {
        return Err(BenchError::Baseline {
            cmd: shown,
            why: String::from_utf8_lossy(&out.stderr).trim().to_string(),
        });
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().rev().find(|l| l.trim_start().starts_with('{')).unwrap_or("");
    let v: serde_json::Value = serde_json::from_str(line)
        .map_err(|e| BenchError::Baseline { cmd: shown.clone(), why: format!("{e}: {text}") })?;
    let f = |k: &str| v[k].as_f64().unwrap_or(f64::NAN) * 1e3;
    Ok(CaseTiming {
        name: EVAL_CASE.into(),
        median_ms: f("median_s"),
        p10_ms: f("p10_s"),
        p90_ms: f("p90_s"),
        iters: 3,
        profile: None,
    })
}

/// Runs the benchmark: promptdt first, then (if asked) PyTorch on the same cases.
pub fn run(cfg: &BenchConfig) -> Result<BenchReport, BenchError> {
    for c in cfg.cases.iter().filter(|c| {
        !is_eval(c) && !is_rl(c) && !is_serve(c) && !is_macaw(c) && !is_pack(c) && !is_render(c)
    }) {
        parse_case(c)?;
    }
    // bf16: first the same cases in fp32 (refused before anything is timed where bf16 is).
    let fp32 = match cfg.matmul {
        Matmul::Bf16 => {
            pdt_torch::device::bf16_allowed(cfg.device)?;
            let fp32 = BenchConfig { matmul: Matmul::Fp32, profile: false, ..cfg.clone() };
            Some(Box::new(run(&fp32)?))
        }
        _ => None,
    };
    let bf16_emulated =
        cfg.matmul == Matmul::Bf16 && pdt_torch::autocast::native(cfg.device).is_err();
    let serve = serve_cases(cfg)?;
    tch::set_num_threads(cfg.threads as i32);
    // (The model below takes the setting: built after it.)
    pdt_torch::device::set_matmul(cfg.device, cfg.matmul)?;
    tch::manual_seed(0);
    let mcfg = PromptDtConfig::reference(20, 6);
    let vs = VarStore::new(cfg.device);
    let mut model = PromptDt::new(&vs.root(), &mcfg);
    let mut opts =
        Optimizers { vs: &vs, names: mcfg.parameter_names(), per_tensor: None, flat: None };
    let mut results = Vec::new();
    for c in cfg.cases.iter().filter(|c| !is_serve(c)) {
        results.push(time_one(c, cfg, &mut model, &mut opts)?);
    }
    // After the timings, so each case's lazily built parts (its optimiser) exist in both profiled
    // runs alike. The evaluation and rendering cases are whole protocols or no libtorch at all.
    let mut profiles = Vec::new();
    for c in
        cfg.cases.iter().filter(|c| cfg.profile && !is_serve(c) && !is_eval(c) && !is_render(c))
    {
        profiles.push(profile::profile_case(c, cfg, |short| {
            time_one(c, short, &mut model, &mut opts)
        })?);
    }
    let promptdt = EngineReport {
        engine: "promptdt".into(),
        torch_version: Some("libtorch 2.11.0 (tch 0.24)".into()),
        threads: cfg.threads,
        results,
    };
    let pytorch = pytorch_report(cfg)?;
    let speedup = match &pytorch {
        Some(p) => promptdt
            .results
            .iter()
            .filter_map(|r| {
                p.results
                    .iter()
                    .find(|q| q.name == r.name)
                    .map(|q| (r.name.clone(), q.median_ms / r.median_ms))
            })
            .collect(),
        None => Vec::new(),
    };
    let device = match cfg.matmul {
        Matmul::Fp32 => format!("{:?}", cfg.device),
        Matmul::Bf16 if bf16_emulated => format!("{:?} (bf16 matmuls, emulated)", cfg.device),
        m => format!("{:?} ({} matmuls)", cfg.device, m.as_str()),
    };
    let tf32_effect = match cfg.matmul {
        Matmul::Tf32 if cfg.device.is_cuda() => Some(tf32_effect(cfg.device)?),
        _ => None,
    };
    Ok(BenchReport {
        device,
        tf32_effect,
        profiles,
        serve,
        promptdt,
        pytorch,
        speedup,
        fp32,
        bf16_emulated,
    })
}

/// Times case `c` with `cfg`'s warm-up and iterations.
fn time_one(
    c: &str,
    cfg: &BenchConfig,
    model: &mut PromptDt,
    opts: &mut Optimizers<'_>,
) -> Result<CaseTiming, BenchError> {
    Ok(if let Some(case) = parse_eval_case(c) {
        time_eval(c, case, cfg)?
    } else if let Some((family, w, h)) = render::parse_case(c) {
        let ms = render::time_frames(family, w, h, cfg.warmup, cfg.iters)
            .map_err(|why| BenchError::Render { case: c.to_string(), why })?;
        timing(c, ms)
    } else if let Some(case) = pack::parse_case(c) {
        let ms = pack::time_pack(case, cfg.warmup, cfg.iters, cfg.device)
            .map_err(|why| BenchError::Pack { case: c.to_string(), why })?;
        timing(c, ms)
    } else if let Some((w, t)) = pdt_macaw::bench::parse_case(c) {
        let ms = pdt_macaw::bench::time_meta_steps(w, t, cfg.warmup, cfg.iters, cfg.device);
        timing(c, ms)
    } else if let Some((alg, h, b)) = pdt_rl::bench::parse_case(c) {
        let ms = pdt_rl::bench::time_updates(alg, h, b, cfg.warmup, cfg.iters, cfg.device);
        timing(c, ms)
    } else {
        time_case(model, opts, c, cfg)?
    })
}

/// The largest difference between a `[512, 1024] x [1024, 512]` product computed with cuBLAS's TF32
/// switch on and off, relative to the product's largest magnitude: about 1e-3 where TF32 is used
/// (its 10-bit mantissa), 0 where the switch changes nothing (the CPU). Leaves the switch on.
pub fn tf32_effect(device: Device) -> Result<f64, BenchError> {
    let gen = |n: i64, m: i64, seed: i64| {
        tch::manual_seed(seed);
        Tensor::randn([n, m], (Kind::Float, Device::Cpu)).to_device(device)
    };
    let (a, b) = (gen(512, 1024, 1), gen(1024, 512, 2));
    pdt_torch::device::set_cublas_tf32(false)?;
    let exact = a.mm(&b);
    pdt_torch::device::set_cublas_tf32(true)?;
    let tf32 = a.mm(&b);
    let diff = (&tf32 - &exact).abs().max().double_value(&[]);
    Ok(diff / exact.abs().max().double_value(&[]))
}

/// A Markdown table of the report.
pub fn render_markdown(r: &BenchReport) -> String {
    let header = [
        "case",
        "promptdt median (p10-p90) ms",
        "PyTorch median (p10-p90) ms",
        "PyTorch / promptdt",
    ];
    let mut cases = Table::new(header.map(String::from).to_vec());
    for c in &r.promptdt.results {
        let theirs = r.pytorch.as_ref().and_then(|p| p.results.iter().find(|q| q.name == c.name));
        let fmt = |t: &CaseTiming| format!("{:.2} ({:.2}-{:.2})", t.median_ms, t.p10_ms, t.p90_ms);
        let ratio = r
            .speedup
            .iter()
            .find(|(n, _)| n == &c.name)
            .map_or("-".into(), |(_, x)| format!("{x:.2}x"));
        cases.push(vec![c.name.clone(), fmt(c), theirs.map_or("not run".into(), fmt), ratio]);
    }
    let mut s = cases.markdown(Rule::Tight);
    if let Some(fp32) = &r.fp32 {
        s.push_str(&precision::render_bf16(r, fp32));
    }
    s.push_str(&profile::render(&r.profiles, r.pytorch.as_ref()));
    if let Some(e) = r.tf32_effect {
        s.push_str(&format!(
            "\nTF32 check: a product computed with TF32 differs from fp32 by {e:.2e} of its \
             largest magnitude (about 1e-3 when cuBLAS uses TF32, 0 when it does not).\n"
        ));
    }
    if !r.serve.is_empty() {
        let header = [
            "serve case",
            "concurrent episodes",
            "p50 ms per step",
            "p99 ms per step",
            "actions/s",
            "requests",
        ];
        let mut serve = Table::new(header.map(String::from).to_vec());
        for c in &r.serve {
            serve.push(vec![
                c.name.clone(),
                c.clients.to_string(),
                format!("{:.3}", c.p50_ms),
                format!("{:.3}", c.p99_ms),
                format!("{:.0}", c.actions_per_s),
                c.requests.to_string(),
            ]);
        }
        s.push('\n');
        s += &serve.markdown(Rule::Tight);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tf32_check_sees_no_effect_on_the_cpu() {
        // cuBLAS's switch leaves CPU products alone (crates/torch/tests/it/matmul.rs checks more).
        let e = tf32_effect(Device::Cpu).unwrap();
        pdt_torch::device::set_cublas_tf32(false).unwrap();
        assert_eq!(e, 0.0);
    }

    #[test]
    fn train_cases_name_the_optimiser() {
        assert_eq!(parse_case("train_b560").ok(), Some((Mode::Train, 560)));
        assert_eq!(parse_case("train_b64_flat").ok(), Some((Mode::TrainFlat, 64)));
        assert_eq!(parse_case("train_b560_flat_all").ok(), Some((Mode::TrainFlatAll, 560)));
        for bad in ["train_b64_flatx", "train_b_flat", "infer_b1_flat", "train_b0_flat"] {
            assert!(parse_case(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn eval_cases_name_any_family() {
        let case = |n: &str| parse_eval_case(n).map(|c| (c.env, c.inference, c.max_batch));
        use pdt_rundir::config::Inference::{Cached, Full};
        assert_eq!(case("eval_point_robot"), Some(("point_robot", Cached, 1 << 20)));
        assert_eq!(case("eval_cheetah_vel_full_b1"), Some(("cheetah_vel", Full, 1)));
        assert_eq!(case("eval_dial_b4"), Some(("dial", Cached, 4)));
        for bad in ["eval_walker", "eval_point_robot_b0", "eval_dial_x", "eval_"] {
            assert_eq!(case(bad), None, "{bad}");
        }
    }
}
