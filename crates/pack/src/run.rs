//! Training a pack: its runs checked to fit one pack, their data loaded once per data setting, the
//! engine built, then each run's ordinary run loop in its own thread with a [`PackMember`] whose
//! gradient steps meet the others' in the [`Hub`].

use crate::batched::{BatchedEngine, PackLayout};
use crate::engine::{PackEngine, SlotSpec};
use crate::hub::Hub;
use crate::member::PackMember;
use crate::solo::SoloEngine;
use pdt_run::RunData;
use pdt_rundir::config::TrainConfig;
use pdt_rundir::pack::Engine;
use pdt_rundir::PackInfo;
use pdt_train::methods::Learner;
use pdt_train::run::{
    run_config_for, train_learner, Progress, ResumeWith, RunError, TrainOptions, TrainSummary,
};
use pdt_train::setup::{absolute, Setup};
use pdt_train::streams::torch_rng_lock;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

/// One run of a pack: its configuration (used to start it; a run being resumed reads its
/// `config.toml`, which is authoritative) and its run directory.
#[derive(Debug, Clone)]
pub struct PackRun {
    pub config: TrainConfig,
    pub dir: PathBuf,
}

/// How a call to [`train_pack`] runs.
pub struct PackOptions<'a> {
    /// Continue each run that has something to resume (its `config.toml`) from its last
    /// checkpoint, and start the others (a pack killed before they were created) from their
    /// configuration. Without it, a run directory that already holds a run is refused.
    pub resume: bool,
    /// With `resume`: what may change, for every run (as [`ResumeWith`] for one run).
    pub resume_with: ResumeWith,
    /// Stop each run after this many iterations of this call (an interruption, in tests).
    pub stop_after_iterations: Option<u64>,
    /// `None`: [`Engine::default_for`] the runs' device.
    pub engine: Option<Engine>,
    /// Progress of the run in the given slot, after each of its iterations (called from the
    /// run's thread).
    pub progress: &'a (dyn Fn(usize, &Progress) + Sync),
}

/// A run of the pack ready to train: its configuration, data, and whether it resumes.
struct Member {
    cfg: TrainConfig,
    data: Arc<RunData>,
    dir: PathBuf,
    resume: bool,
}

/// Trains the runs of a pack together, each into its own run directory, and returns each run's
/// outcome in order: a run that fails (its data, its directory, a divergence) ends with its error
/// while the others go on. The pack itself is refused, before anything is written, when its runs
/// cannot share one pack (another family, model shape or device; MACAW; one directory twice) or a
/// run's configuration or data is bad.
pub fn train_pack(
    runs: Vec<PackRun>,
    opts: PackOptions<'_>,
) -> Result<Vec<Result<TrainSummary, RunError>>, RunError> {
    let ready = prepare_pack(runs, &opts)?;
    Ok(run_pack(ready, opts))
}

/// A pack checked, its data loaded and its engine built: nothing written yet.
pub(crate) struct ReadyPack {
    members: Vec<Member>,
    engine: Box<dyn PackEngine + Send>,
    engine_kind: Engine,
    /// libtorch's intra-op threads for every thread of the pack (its runs' loops and the
    /// stepper: the first run's `run.threads`): one count for all, since a thread's first
    /// parallel op takes the process's count as its own.
    libtorch_threads: usize,
}

/// Everything [`train_pack`] checks and builds before it writes anything.
pub(crate) fn prepare_pack(
    runs: Vec<PackRun>,
    opts: &PackOptions<'_>,
) -> Result<ReadyPack, RunError> {
    let members = members(runs, opts)?;
    let device = pdt_torch::device::resolve(members[0].cfg.run.device)?;
    // One setting for the process: the runs agree on it (checked where their configurations are).
    pdt_torch::device::set_matmul(device, members[0].cfg.run.matmul)?;
    let engine_kind =
        opts.engine.unwrap_or_else(|| Engine::default_for(device != tch::Device::Cpu));
    // The batched engine's model is its own (stacked weights, its own products): bf16 autocast is
    // entered by `PromptDt::forward` only, so a batched pack would run fp32 under a bf16 label.
    if members[0].cfg.run.matmul == pdt_base::device::Matmul::Bf16 && engine_kind == Engine::Batched
    {
        return Err(RunError::invalid(
            "pack",
            "run.matmul = bf16 runs on the solo engine only (--engine solo): the batched engine \
             has no bf16 path yet",
        ));
    }
    let specs: Vec<SlotSpec> = members
        .iter()
        .map(|m| SlotSpec {
            model: m.data.model_cfg.clone(),
            uses_prompt: m.cfg.run.method.uses_prompt(),
            loss_on: m.cfg.train.loss_on,
            optim: m.cfg.optim.clone(),
            last_block: m.cfg.train.last_block,
            seed: m.cfg.run.seed,
        })
        .collect();
    // The batched engine's fixed shapes: the largest batch, history and prompt of the pack (a
    // run with less is padded and masked).
    let layout = PackLayout {
        batch_size: members
            .iter()
            .map(|m| m.data.sampler_cfg.batch_size_per_task * m.data.train_data.tasks.len())
            .max()
            .unwrap_or(0),
        history_len: members.iter().map(|m| m.data.sampler_cfg.k).max().unwrap_or(0),
        prompt_len: members
            .iter()
            .filter(|m| m.cfg.run.method.uses_prompt())
            .map(|m| m.data.sampler_cfg.prompt_steps())
            .max()
            .unwrap_or(0),
    };
    let libtorch_threads = pdt_base::threads(members[0].cfg.run.threads);
    let engine = {
        let _rng = torch_rng_lock();
        make_engine(engine_kind, specs, layout, device)?
    };
    Ok(ReadyPack { members, engine, engine_kind, libtorch_threads })
}

/// Trains a prepared pack: each run's loop in its own thread, the gradient steps in the hub.
pub(crate) fn run_pack(
    ready: ReadyPack,
    opts: PackOptions<'_>,
) -> Vec<Result<TrainSummary, RunError>> {
    let ReadyPack { members, engine, engine_kind, libtorch_threads } = ready;
    let libtorch_threads = i32::try_from(libtorch_threads).unwrap_or(i32::MAX);
    tch::set_num_threads(libtorch_threads);
    let hub = Hub::new(engine);
    let size = members.len();
    let (with, stop, progress) = (&opts.resume_with, opts.stop_after_iterations, opts.progress);
    std::thread::scope(|scope| {
        // Named, so that `top -H` or a profiler shows which thread steps and which run is which.
        let stepper =
            std::thread::Builder::new().name("pack-stepper".into()).spawn_scoped(scope, || {
                // The pack's steps compute on this thread: the runs' libtorch thread count.
                tch::set_num_threads(libtorch_threads);
                hub.stepper();
            });
        let stepper = match stepper {
            Ok(s) => s,
            Err(e) => {
                let message = format!("could not start the pack's stepper thread: {e}");
                return (0..size).map(|_| Err(RunError::Internal(message.clone()))).collect();
            }
        };
        let handles: Vec<_> = members
            .into_iter()
            .enumerate()
            .map(|(slot, m)| {
                let hub = &hub;
                let info = PackInfo { size, slot, engine: engine_kind.name().into() };
                let thread = std::thread::Builder::new().name(format!("pack-run-{slot}"));
                let spawned = thread.spawn_scoped(scope, move || {
                    // Per OS thread (OpenMP's): this run's evaluations get the pack's count.
                    tch::set_num_threads(libtorch_threads);
                    let with = if m.resume { with.clone() } else { ResumeWith::default() };
                    let mut report = |p: &Progress| progress(slot, p);
                    let opts = TrainOptions {
                        resume: m.resume,
                        resume_with: with,
                        stop_after_iterations: stop,
                        progress: &mut report,
                        // A pack is the CLI's (`promptdt pack`), which Ctrl-C ends outright.
                        interrupt: Default::default(),
                        envs: None,
                    };
                    train_member(m, slot, hub, opts, &info)
                });
                // A run whose thread did not start has left: the others do not wait for it.
                spawned.map_err(|e| {
                    hub.leave(slot);
                    RunError::Internal(format!(
                        "could not start the thread of the pack's run {slot}: {e}"
                    ))
                })
            })
            .collect();
        let results = handles
            .into_iter()
            .map(|h| {
                h?.join().unwrap_or_else(|_| {
                    Err(RunError::Internal("a run of the pack panicked (see above)".into()))
                })
            })
            .collect();
        hub.close();
        // (A panic in the stepper's engine step is caught there and fails that step's runs.)
        let _ = stepper.join();
        results
    })
}

/// One run of the pack, in its thread: its set-up over the shared data, its learner, its loop.
fn train_member(
    m: Member,
    slot: usize,
    hub: &Hub,
    opts: TrainOptions<'_>,
    info: &PackInfo,
) -> Result<TrainSummary, RunError> {
    // However the run ends (finished, stopped, failed before its first step, panicked), the pack
    // stops waiting for it.
    let _leave = Leave { hub, slot };
    let toml = m.cfg.to_toml()?;
    let setup = Setup::with_data(m.cfg, m.data, info.size)?;
    let mut learner = PackMember::new(&setup, slot, hub)?;
    learner.check_can_train()?;
    train_learner(&setup, &toml, &m.dir, &mut learner, opts, Some(info))
}

/// Takes a run out of the hub when dropped.
struct Leave<'h> {
    hub: &'h Hub,
    slot: usize,
}

impl Drop for Leave<'_> {
    fn drop(&mut self) {
        self.hub.leave(self.slot);
    }
}

/// The one place an engine is built.
fn make_engine(
    kind: Engine,
    specs: Vec<SlotSpec>,
    layout: PackLayout,
    device: tch::Device,
) -> Result<Box<dyn PackEngine + Send>, RunError> {
    Ok(match kind {
        Engine::Solo => Box::new(SoloEngine::new(specs, device)),
        Engine::Batched => Box::new(BatchedEngine::new(specs, layout, device)?),
    })
}

/// The runs' configurations (a resumed run's from its directory), checked to fit one pack, with
/// their data loaded once per data setting.
fn members(runs: Vec<PackRun>, opts: &PackOptions<'_>) -> Result<Vec<Member>, RunError> {
    if runs.is_empty() {
        return Err(RunError::invalid("pack", "needs at least one run"));
    }
    let mut seen = BTreeMap::new();
    let mut picked = Vec::with_capacity(runs.len());
    for (i, run) in runs.into_iter().enumerate() {
        let dir = absolute(&run.dir);
        if let Some(j) = seen.insert(dir.clone(), i) {
            return Err(RunError::invalid(
                format!("runs {j} and {i} of the pack"),
                format!(
                    "would both write {}; give them different directories (or seeds)",
                    dir.display()
                ),
            ));
        }
        let resume = opts.resume && dir.join("config.toml").is_file();
        let cfg = if resume {
            run_config_for(None, &dir, true, &opts.resume_with)?
        } else {
            if dir.join("checkpoints").join("latest.json").exists() && !opts.resume {
                return Err(RunError::invalid(
                    dir.display(),
                    "already holds a run; resume the pack or pick other directories",
                ));
            }
            let mut cfg = run.config;
            if opts.resume {
                // A run the pack never got to create starts as resuming it would have it end.
                let with = &opts.resume_with;
                if let Some(n) = with.iterations {
                    cfg.train.iterations = n;
                }
                if let Some(d) = with.device {
                    cfg.run.device = d;
                }
                if let Some(d) = &with.data {
                    cfg.data.dir.clone_from(d);
                }
            }
            run_config_for(Some(cfg), &dir, false, &opts.resume_with)?
        };
        cfg.validate().map_err(|e| in_run(&dir, e.into()))?;
        picked.push((cfg, dir, resume));
    }
    check_fits(&picked)?;
    let mut loaded: BTreeMap<String, Arc<RunData>> = BTreeMap::new();
    let mut members = Vec::with_capacity(picked.len());
    for (cfg, dir, resume) in picked {
        let key = Setup::data_key(&cfg)?;
        let data = match loaded.get(&key) {
            Some(d) => Arc::clone(d),
            None => {
                let family = pdt_envs::family(&cfg.env.name)?;
                let d = Arc::new(
                    RunData::load(&cfg, family.as_ref()).map_err(|e| in_run(&dir, e.into()))?,
                );
                loaded.insert(key, Arc::clone(&d));
                d
            }
        };
        members.push(Member { cfg, data, dir, resume });
    }
    Ok(members)
}

/// `e`, naming the run directory it is about.
fn in_run(dir: &std::path::Path, e: RunError) -> RunError {
    RunError::InPack { dir: dir.into(), source: Box::new(e) }
}

/// Refuses runs that cannot share a pack, naming the setting: one environment family, one model
/// shape (`[model]`), one device and matmul precision; methods that pack (`Method::packs`) only.
fn check_fits(runs: &[(TrainConfig, PathBuf, bool)]) -> Result<(), RunError> {
    for (cfg, dir, _) in runs {
        if !cfg.run.method.packs() {
            let e = pdt_train::methods::cannot_pack(cfg.run.method);
            return Err(RunError::InPack { dir: dir.clone(), source: Box::new(e) });
        }
    }
    let (first, first_dir, _) = &runs[0];
    let model = section(&first.model)?;
    for (cfg, dir, _) in &runs[1..] {
        let differ = |field: &str, a: String, b: String| {
            RunError::invalid(
                "the runs of a pack",
                format!(
                    "must agree on {field}: {} has {a}, {} has {b}",
                    first_dir.display(),
                    dir.display()
                ),
            )
        };
        if cfg.env.name != first.env.name {
            return Err(differ("env.name", first.env.name.clone(), cfg.env.name.clone()));
        }
        if cfg.run.device != first.run.device {
            return Err(differ(
                "run.device",
                format!("{:?}", first.run.device),
                format!("{:?}", cfg.run.device),
            ));
        }
        if cfg.run.matmul != first.run.matmul {
            return Err(differ(
                "run.matmul",
                first.run.matmul.as_str().into(),
                cfg.run.matmul.as_str().into(),
            ));
        }
        let other = section(&cfg.model)?;
        for (k, v) in &model {
            let w = other.get(k);
            if w != Some(v) {
                let shown = |x: Option<&toml::Value>| x.map_or("nothing".into(), |x| x.to_string());
                return Err(differ(&format!("model.{k}"), shown(Some(v)), shown(w)));
            }
        }
    }
    Ok(())
}

/// A configuration section's fields by name.
fn section<T: serde::Serialize>(s: &T) -> Result<toml::Table, RunError> {
    toml::Table::try_from(s)
        .map_err(|e| RunError::Internal(format!("a configuration section as TOML: {e}")))
}
