//! Subcommands with progress bars: argument handling and display only; the work is one library call.

use crate::args::{CollectArgs, DemoArgs, ReproduceArgs, TrainArgs};
use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

pub fn bar(len: u64, template: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    if let Ok(style) = ProgressStyle::with_template(template) {
        pb.set_style(style.progress_chars("=> "));
    }
    pb
}

pub fn collect(a: &CollectArgs) -> Result<()> {
    use pdt_data::mode::Mode;
    use pdt_envs::collect_scripted::{CollectConfig, ScriptedFamily};
    // The families named in messages come from pdt-envs, so a new family needs no edit here.
    let families_where = |keep: fn(ScriptedFamily) -> bool| {
        ScriptedFamily::all().into_iter().filter(|f| keep(*f)).map(|f| f.name()).collect::<Vec<_>>()
    };
    let noise_families = || families_where(ScriptedFamily::takes_action_noise).join(", ");
    let family = pdt_envs::family(&a.env)?;
    let Some(scripted) = family.scripted() else {
        if a.modes.is_some() {
            bail!("--modes is for the scripted families ({})", families_where(|_| true).join(", "));
        }
        if a.action_noise.is_some() {
            bail!("--action-noise is for {}", noise_families());
        }
        return collect_rl(a, family.name());
    };
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("data").join(family.name()));
    let mut cfg = CollectConfig::for_family(scripted);
    cfg.seed = a.seed;
    cfg.prompt_episodes = a.prompt_episodes;
    if let Some(n) = a.episodes {
        cfg.episodes_per_task = n;
    }
    if let Some(t) = &a.tasks {
        cfg.tasks = t.clone();
    }
    if let Some(m) = &a.modes {
        cfg.modes = m.iter().map(|m| m.parse::<Mode>()).collect::<Result<_, _>>()?;
    }
    if let Some(s) = a.action_noise {
        if !scripted.takes_action_noise() {
            bail!("--action-noise is for {}", noise_families());
        }
        cfg.reach_action_noise = s;
    }
    let pb = bar(0, "collect {bar:30} {pos}/{len} datasets [{elapsed} < {eta}]");
    let summary = pdt_envs::collect_scripted::collect(&cfg, &out, &mut |done, total| {
        pb.set_length(total as u64);
        pb.set_position(done as u64);
    })?;
    pb.finish_and_clear();
    let success = summary.entries.iter().any(|e| e.success_rate.is_some());
    out_inline!("{:<6} {:<8} {:>14} {:>14}", "task", "mode", "D_i return", "P_i return");
    out!("{}", if success { format!(" {:>10}", "success") } else { String::new() });
    // Many tasks (the point robot's 40): a sample of them; otherwise every task.
    let many = cfg.tasks.len() > 20;
    let shown = |t: usize| !many || t % 8 == 2;
    for e in summary.entries.iter().filter(|e| shown(e.task)) {
        out_inline!(
            "{:<6} {:<8} {:>14.2} {:>14.2}",
            e.task,
            e.mode.name(),
            e.dataset.mean,
            e.prompts.mean
        );
        out!("{}", e.success_rate.map_or(String::new(), |r| format!(" {:>9.1}%", 100.0 * r)));
    }
    out!(
        "wrote {} datasets and {} to {}",
        summary.entries.len() * 2,
        summary.card.display(),
        out.display()
    );
    Ok(())
}

pub fn train(a: &TrainArgs) -> Result<()> {
    use pdt_rundir::config::{Overrides, TrainConfig};
    // (A pack, `--pack` or `--resume` of a pack directory, goes to `crate::packs` from `main`.)
    if a.engine.is_some() || a.pack_eval.is_some() {
        bail!("--engine and --pack-eval are for packs (--pack, or --resume of a pack directory)");
    }
    let (cfg, dir) = match (&a.resume, &a.config) {
        (Some(dir), _) => (None, dir.clone()),
        (None, Some(path)) => {
            let mut cfg = TrainConfig::from_file(path)?;
            let method = a
                .method
                .as_deref()
                .map(str::parse)
                .transpose()
                .map_err(|e| anyhow::anyhow!("--method {e}"))?;
            let macaw_preset = a.macaw_preset.map(|p| match p {
                crate::args::MacawPresetArg::Official => {
                    pdt_rundir::config::macaw::Preset::Official
                }
                crate::args::MacawPresetArg::Promptdt => {
                    pdt_rundir::config::macaw::Preset::Promptdt
                }
            });
            let overrides = Overrides {
                seed: a.seed,
                iterations: a.iterations,
                method,
                macaw_preset,
                device: a.device,
                matmul: a.matmul,
                data: a.data.clone(),
            };
            cfg.apply(&overrides, |env| pdt_envs::family(env).map(|f| f.preset().prompt_length))?;
            let dir = a.out.clone().unwrap_or_else(|| cfg.default_run_dir());
            (Some(cfg), dir)
        }
        (None, None) => bail!("give --config or --resume"),
    };
    let pb = if a.quiet {
        ProgressBar::hidden()
    } else {
        bar(0, "train {bar:30} {pos}/{len} it [{elapsed} < {eta}] {msg}")
    };
    let mut last_test: Option<f64> = None;
    let mut progress = |p: &pdt_train::run::Progress| {
        pb.set_length(p.iterations);
        pb.set_position(p.iteration);
        last_test = p.test_return.or(last_test);
        let test = last_test.map_or(String::new(), |r| format!("  test return {r:.2}"));
        pb.set_message(format!("loss {:.5}{test}", p.loss));
    };
    let resume_with = pdt_train::run::ResumeWith {
        iterations: a.iterations,
        device: a.device,
        data: a.data.clone(),
    };
    let opts = pdt_train::run::TrainOptions {
        resume: a.resume.is_some(),
        resume_with,
        stop_after_iterations: a.stop_after_iterations,
        progress: &mut progress,
        interrupt: Default::default(),
    };
    let summary = pdt_train::run::train(cfg, &dir, opts)?;
    pb.finish_and_clear();
    if let Some(tasks) = &summary.last_test {
        let mean = tasks.iter().map(|t| t.return_mean).sum::<f64>() / tasks.len().max(1) as f64;
        out!(
            "held-out tasks after iteration {}: average return {mean:.2}",
            summary.iterations_done
        );
    }
    out!("run directory: {}", summary.dir.display());
    Ok(())
}

/// The demo's experiment file, compiled in so the demo runs from any directory.
const DEMO_CONFIG: &str = include_str!("../../../configs/point_robot/demo.toml");

/// collect -> train Prompt-DT and MT-ORL -> evaluate on the held-out goals -> report.
pub fn demo(a: &DemoArgs) -> Result<()> {
    use pdt_rundir::config::{Method, TrainConfig};
    let started = std::time::Instant::now();
    let out = &a.out;
    if out.exists() {
        std::fs::remove_dir_all(out).with_context(|| format!("clearing {}", out.display()))?;
    }
    let data = out.join("data");
    out!(
        "[1/4] collecting point-robot datasets (40 goals x expert/medium/random) into {}",
        data.display()
    );
    let base: TrainConfig = toml::from_str(DEMO_CONFIG).context("configs/point_robot/demo.toml")?;
    // The demo config's family, collected with its scripted policies' defaults.
    let family = pdt_envs::collect_scripted::ScriptedFamily::named(&base.env.name)?;
    let cfg = pdt_envs::collect_scripted::CollectConfig::for_family(family);
    pdt_envs::collect_scripted::collect(&cfg, &data, &mut |_, _| {})?;
    let mut runs = Vec::new();
    for (n, method) in [Method::PromptDt, Method::MtOrl].into_iter().enumerate() {
        for seed in 0..a.seeds {
            let mut cfg = base.clone();
            cfg.run.method = method;
            cfg.run.seed = seed;
            cfg.run.device = a.device;
            cfg.data.dir = data.clone();
            if let Some(i) = a.iterations {
                cfg.train.iterations = i;
            }
            let dir = out.join(format!("{}-seed{seed}", method.name()));
            out!("[{}/4] training {} (seed {seed}) -> {}", n + 2, method.name(), dir.display());
            let pb = bar(
                cfg.train.iterations,
                "      {bar:30} {pos}/{len} it [{elapsed} < {eta}] {msg}",
            );
            let mut progress = |p: &pdt_train::run::Progress| {
                pb.set_position(p.iteration);
                let test = p.test_return.map_or(String::new(), |r| format!("  test return {r:.2}"));
                if !test.is_empty() || p.iteration == 1 {
                    pb.set_message(format!("loss {:.5}{test}", p.loss));
                }
            };
            let opts = pdt_train::run::TrainOptions {
                resume: false,
                resume_with: Default::default(),
                stop_after_iterations: None,
                progress: &mut progress,
                interrupt: Default::default(),
            };
            pdt_train::run::train(Some(cfg), &dir, opts)?;
            pb.finish_and_clear();
            let r = pdt_train::run::evaluate_run(&dir, None, "test", Some(a.device), None)?;
            out!("      held-out goals: average return {:.2}", r.mean_return);
            runs.push(dir);
        }
    }
    out!("[4/4] report");
    let report_dir = out.join("report");
    let cfg = pdt_report::ReportConfig {
        runs,
        out_dir: report_dir.clone(),
        title: Some("promptdt demo".into()),
    };
    let summary = pdt_report::run(&cfg)?;
    out_inline!("\n{}", summary.markdown);
    out!(
        "\nplots and tables: {}/ (curves_point_robot.png, table.md, table.csv, curves.csv)",
        report_dir.display()
    );
    out!("demo finished in {:.0} s", started.elapsed().as_secs_f64());
    Ok(())
}

/// `collect` for the MuJoCo families: train (or resume, or take the pretrained agent), then write
/// the datasets.
fn collect_rl(a: &CollectArgs, family: &str) -> Result<()> {
    use pdt_rl::agent::Noise;
    use pdt_rl::overrides::RlOverrides;
    use pdt_rl::train::{RlConfig, TrainProgress};
    if let Some(t) = a.threads {
        tch::set_num_threads(t as i32);
    }
    let device = pdt_torch::device::resolve(a.device)?;
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("data").join(family));
    let agent_dir = match a.from_pretrained {
        true => {
            let dir = a
                .pretrained_dir
                .clone()
                .unwrap_or_else(|| PathBuf::from("pretrained").join(family));
            out!("using the pretrained agent in {}", dir.display());
            dir
        }
        false => {
            let run_dir = a
                .run_dir
                .clone()
                .unwrap_or_else(|| PathBuf::from("runs").join(format!("collect-{family}")));
            let mut cfg = RlConfig::preset(family)?;
            cfg.apply(&RlOverrides {
                seed: Some(a.seed),
                algorithm: a.algorithm.as_deref().map(str::parse).transpose()?,
                total_steps: a.steps,
                learning_starts: a.learning_starts,
                hidden: a.hidden.clone(),
                batch_size: a.batch_size,
                checkpoint_every: a.checkpoint_every,
                tasks: a.tasks.clone(),
                sample_recent: a.sample_recent,
            });
            let pb = bar(
                cfg.total_steps,
                "{prefix} {bar:30} {pos}/{len} steps [{elapsed} < {eta}] {msg}",
            );
            pb.set_prefix(format!("{} {family}", cfg.algorithm.name()));
            let mut on_progress = |p: &TrainProgress<'_>| {
                pb.set_length(p.total);
                pb.set_position(p.step);
                let seen: Vec<f64> = p.recent.iter().flatten().copied().collect();
                let mean = seen.iter().sum::<f64>() / seen.len().max(1) as f64;
                let per_task = if p.recent.len() <= 4 {
                    p.recent
                        .iter()
                        .enumerate()
                        .map(|(i, r)| match r {
                            Some(r) => format!("t{i} {r:.0}"),
                            None => format!("t{i} -"),
                        })
                        .collect::<Vec<_>>()
                        .join(" ")
                } else {
                    // Too many tasks for one line: the worst and the best, with their indices.
                    let known = p.recent.iter().enumerate().filter_map(|(i, r)| r.map(|r| (i, r)));
                    let worst = known.clone().min_by(|a, b| a.1.total_cmp(&b.1));
                    let best = known.max_by(|a, b| a.1.total_cmp(&b.1));
                    match (worst, best) {
                        (Some((wi, w)), Some((bi, b))) => format!(
                            "worst t{wi} {w:.0}, best t{bi} {b:.0}, {}/{} tasks seen",
                            seen.len(),
                            p.recent.len()
                        ),
                        _ => "no episode yet".to_string(),
                    }
                };
                pb.set_message(format!(
                    "return {mean:.1} ({per_task}) q-loss {:.3}",
                    p.last_update.critic_loss
                ));
                if let Some(s) = p.snapshot {
                    pb.println(format!(
                        "snapshot at step {}: mean deterministic return {:.1}",
                        s.step, s.mean_return
                    ));
                }
            };
            let start = if a.resume {
                pdt_rl::train::Start::Resume {
                    total_steps: a.steps,
                    tasks: a.tasks.as_deref(),
                    sample_recent: a.sample_recent,
                }
            } else {
                pdt_rl::train::Start::New(&cfg)
            };
            let card =
                pdt_rl::train::train(start, &run_dir, a.stop_after, device, &mut on_progress)?;
            pb.finish_and_clear();
            let Some(card) = card else {
                out!(
                    "stopped as asked (--stop-after); continue with --resume --run-dir {}",
                    run_dir.display()
                );
                return Ok(());
            };
            out!(
                "trained {} on {family} for {} steps in {:.0} s; expert: step {} (mean {:.1}), medium: step {} (mean {:.1}), random: mean {:.1}",
                card.algorithm.name(),
                card.config.total_steps,
                card.wall_seconds,
                card.expert_step,
                mean(&card.expert_eval),
                card.medium_step,
                mean(&card.medium_eval),
                mean(&card.random_eval),
            );
            pdt_rl::train::agent_dir(&run_dir)
        }
    };
    let dcfg = pdt_rl::datasets::DatasetConfig {
        seed: a.seed,
        episodes: a.episodes.unwrap_or(100),
        prompt_episodes: a.prompt_episodes,
        noise: match (a.deterministic, a.explore) {
            (true, _) => Some(Noise::Deterministic),
            (_, true) => Some(Noise::Explore),
            _ => None,
        },
        ..Default::default()
    };
    let pb = bar(0, "datasets {bar:30} {pos}/{len} episodes [{elapsed} < {eta}]");
    let t0 = std::time::Instant::now();
    let summary =
        pdt_rl::datasets::generate(&agent_dir, &out, &dcfg, device, &mut |done, total| {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        })?;
    pb.finish_and_clear();
    out!(
        "{:<6} {:>12} {:>12} {:>12} {:>14}",
        "task",
        "expert",
        "medium",
        "random",
        "prompt-expert"
    );
    let tasks: Vec<usize> = {
        let mut t: Vec<usize> = summary.entries.iter().map(|e| e.task).collect();
        t.sort_unstable();
        t.dedup();
        t
    };
    let get = |t: usize, m| {
        summary.get(t, m).map_or("-".to_string(), |e: &pdt_rl::datasets::TaskModeStats| {
            format!("{:.1}", e.dataset.mean)
        })
    };
    use pdt_data::mode::Mode;
    for &t in &tasks {
        let p =
            summary.get(t, Mode::Expert).map_or("-".into(), |e| format!("{:.1}", e.prompts.mean));
        out!(
            "{:<6} {:>12} {:>12} {:>12} {:>14}",
            t,
            get(t, Mode::Expert),
            get(t, Mode::Medium),
            get(t, Mode::Random),
            p
        );
    }
    out!(
        "wrote {} files ({} steps) and {} in {:.1} s",
        summary.files,
        summary.steps,
        summary.card.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// `reproduce`: list, emit jobs, run what is unfinished, report.
pub fn reproduce(a: &ReproduceArgs) -> Result<()> {
    use pdt_repro::{exec, plan, report, Manifest, Stage};
    if a.list {
        for e in pdt_repro::list()? {
            let pending =
                if e.pending > 0 { format!(", {} pending", e.pending) } else { String::new() };
            out!("{:<30} {} ({} cells{pending})", e.name, e.title, e.cells);
            for b in &e.budgets {
                let h = b.hours.map_or(String::new(), |h| format!(", ~{h} h here"));
                out!(
                    "    {:<6} {:>3} runs x {} iterations{h}: {}",
                    b.budget,
                    b.runs,
                    b.iterations,
                    b.note
                );
            }
        }
        return Ok(());
    }
    let Some(name) = a.experiment.as_deref() else { bail!("name an experiment, or --list") };
    let m = Manifest::load(name)?;
    let cores = pdt_base::threads::available_cores();
    // Measured on 2 cores (`benchmarks/14-omp-wait-policy.json`): 2 runs of 1 thread each finish
    // a set of runs 1.36x sooner than 1 run of 2 threads. On an H200, two Cheetah-Dir runs at once
    // made 1.7x the iterations per hour of one alone, and four no more.
    let on_gpu = matches!(pdt_torch::device::resolve(a.device), Ok(d) if d.is_cuda());
    // Refused here rather than by each run after its data are collected. Emitted jobs and reports
    // may be made on a machine without the GPU that will run them.
    let trains_here = !(a.report_only || a.status || a.emit.is_some());
    if a.matmul == pdt_base::device::Matmul::Tf32 && trains_here && !on_gpu {
        bail!(
            "--matmul tf32 needs a CUDA device, and --device {} is the CPU here (the CPU computes \
             float32 products in fp32 only)",
            a.device.as_str()
        );
    }
    let jobs = match a.jobs {
        Some(j) => j,
        None if on_gpu => 2,
        None => cores,
    };
    let threads = match a.threads {
        Some(t) => t,
        None => (cores / jobs).max(1),
    };
    // On a GPU packing pays: one batched engine call steps the pack's runs at once. On the CPU a
    // pack (the solo engine, its runs one after another) gains nothing over `--jobs` processes:
    // one run per process stays the default there.
    let pack = match a.pack {
        Some(n) => n,
        None if on_gpu => 12,
        None => 1,
    };
    let pack_engine = match a.pack_engine.as_deref() {
        Some(e) => e.parse::<pdt_rundir::pack::Engine>().map_err(anyhow::Error::msg)?,
        None => pdt_rundir::pack::Engine::default_for(on_gpu),
    };
    let out = std::path::absolute(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    let data_root = match &a.data_root {
        Some(d) => {
            std::path::absolute(d).with_context(|| format!("--data-root {}", d.display()))?
        }
        None => out.join("data"),
    };
    let opts = plan::PlanOptions {
        budget: a.budget.clone(),
        out: out.clone(),
        data_root,
        threads,
        device: a.device,
        matmul: a.matmul,
        seeds: a.seeds,
    };
    let p = if a.report_only {
        // A fresh clone has no run directories: the registry's archived runs stand in for them.
        let (p, used) = pdt_repro::registry::plan_with_archive(&m, &opts, &a.registry)?;
        if !used.is_empty() {
            out!("{} runs read from the registry {}", used.len(), a.registry.display());
        }
        p
    } else {
        plan::plan(&m, &opts)?
    };
    if a.status {
        return print_status(&p, a, name);
    }
    let eopts = exec::ExecOptions {
        exe: std::env::current_exe().context("the promptdt binary's path")?,
        jobs,
        omp_wait_policy: Some(a.omp_wait_policy.clone()),
        pretrained_root: pretrained_root(a.pretrained_root.as_deref())?,
        pack,
        pack_engine,
    };
    match a.emit.as_deref() {
        Some("jobs") => {
            let dir = out.join("jobs").join(format!("{}-{}", p.experiment, p.budget));
            // Each job resolves its own device and OpenMP policy: pass the ones asked for here, so a
            // sweep emitted with `--device cuda` does not quietly fall back to the CPU on a node
            // without a CUDA libtorch.
            let mut extra = vec![
                "--threads".to_string(),
                threads.to_string(),
                "--device".into(),
                a.device.as_str().into(),
                "--omp-wait-policy".into(),
                a.omp_wait_policy.clone(),
            ];
            if a.matmul != pdt_base::device::Matmul::default() {
                extra.extend(["--matmul".into(), a.matmul.as_str().into()]);
            }
            if a.data_root.is_some() {
                extra.push("--data-root".into());
                extra.push(opts.data_root.to_string_lossy().into_owned());
            }
            extra.push("--pretrained-root".into());
            extra.push(eopts.pretrained_root.to_string_lossy().into_owned());
            // A manifest given as a file is named by its absolute path, so the jobs run from anywhere.
            let manifest = match std::path::Path::new(name).is_file() {
                true => std::path::absolute(name)?.to_string_lossy().into_owned(),
                false => name.to_string(),
            };
            if pack > 1 {
                extra.push("--pack".into());
                extra.push(pack.to_string());
                extra.push("--pack-engine".into());
                extra.push(pack_engine.name().into());
            }
            let files = exec::emit_jobs(&p, &dir, &eopts, &manifest, &extra)?;
            out!(
                "{} runs; wrote {}",
                p.runs.len(),
                files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join(", ")
            );
            out!("run them, e.g.: xargs -P 2 -I{{}} sh -c {{}} < {}", files[0].display());
            let variants = p.runs.iter().filter(|r| r.base.is_some()).count();
            if variants > 0 {
                // Variants evaluate the trained weights: after the jobs, not beside them.
                out!(
                    "then: promptdt reproduce {name} --budget {} --out {} (evaluates the {variants} \
                     variant runs, then reports)",
                    p.budget,
                    out.display()
                );
                return Ok(());
            }
            out!(
                "then: promptdt reproduce {name} --budget {} --out {} --report-only",
                p.budget,
                out.display()
            );
            return Ok(());
        }
        Some(other) => bail!("--emit {other}: expected `jobs`"),
        None => {}
    }
    if !a.report_only {
        let pb = bar(0, "{prefix} {bar:30} {pos}/{len} iterations [{elapsed} < {eta}] {msg}");
        pb.set_prefix(format!("{} {}", p.experiment, p.budget));
        let summary = exec::execute(&p, a.only.as_deref(), &eopts, &mut |pr| match &pr.stage {
            Stage::Data(env) => pb.set_message(format!("collecting the {env} datasets")),
            Stage::Training | Stage::Done => {
                pb.set_length(pr.iterations_total);
                pb.set_position(pr.iterations_done);
                pb.set_message(format!(
                    "runs {}/{} done{}{}",
                    pr.runs_finished,
                    pr.runs_total,
                    if pr.running.is_empty() {
                        String::new()
                    } else {
                        format!(", running {}", pr.running.join(" "))
                    },
                    if pr.waiting.is_empty() {
                        String::new()
                    } else {
                        format!(", waiting for {} (another process has it)", pr.waiting.join(" "))
                    }
                ));
            }
        })?;
        pb.finish_and_clear();
        for t in &summary.removed_temps {
            out!("removed {}, left by a killed collection", t.display());
        }
        out!(
            "{}: {} runs already finished, {} started, {} resumed, {} failed",
            p.experiment,
            summary.already_finished,
            summary.started,
            summary.resumed,
            summary.failed.len()
        );
        if summary.evaluated > 0 {
            out!("{} variant runs evaluated (docs/reproduce.md, \"Variants\")", summary.evaluated);
        }
        if !summary.waited.is_empty() {
            // Another process (a second `reproduce` on this --out, or a `train` on the run) had
            // them: not failed, and not run twice.
            out!(
                "waited for {} runs another process had ({} finished there): {}",
                summary.waited.len(),
                summary.finished_elsewhere,
                summary.waited.join(" ")
            );
        }
        for (k, msg) in &summary.failed {
            eprintln!("run {k} failed: {msg}");
        }
        if !summary.failed.is_empty() {
            bail!(
                "{} runs failed (logs under {})",
                summary.failed.len(),
                out.join("logs").display()
            );
        }
        if a.only.is_some() {
            return Ok(());
        }
    }
    // The reference's expert returns are committed in the manifests; `--reference DIR` recomputes
    // them from the release's prompt files instead, so a DIR that is not there is an error, not a
    // silent fallback to the committed numbers.
    if let Some(d) = a.reference.as_deref().filter(|d| !d.is_dir()) {
        bail!(
            "--reference {}: not a directory (the reference release's official-prompts/)",
            d.display()
        );
    }
    let r = report::report(&m, &p, a.reference.as_deref())?;
    out!("{}", r.markdown);
    out!("report: {}", p.report_dir().display());
    Ok(())
}

/// `--pretrained-root`, absolute: as given, else `pretrained` in this directory, else the
/// `pretrained/` of the checkout this binary was built in, so `reproduce`, and the jobs it emits for
/// other machines, find the committed agents from any directory (`exec::check_agents` refuses to
/// emit jobs whose agents are missing).
fn pretrained_root(given: Option<&std::path::Path>) -> Result<PathBuf> {
    let here = PathBuf::from("pretrained");
    let built = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pretrained");
    let dir = match given {
        Some(d) => d.to_path_buf(),
        None if !here.is_dir() && built.is_dir() => built.canonicalize().unwrap_or(built),
        None => here,
    };
    std::path::absolute(&dir).with_context(|| format!("--pretrained-root {}", dir.display()))
}

/// `reproduce --status`: the plan's runs and where each stands, then the command that goes on.
fn print_status(p: &pdt_repro::plan::Plan, a: &ReproduceArgs, name: &str) -> Result<()> {
    use pdt_repro::status;
    let runs = status::runs(p, &a.registry);
    out!("{}", status::table(&runs).trim_end());
    let t = status::Tally::of(&runs);
    let problems = match t.problems {
        0 => String::new(),
        n => format!(", {n} cannot be resumed as they are"),
    };
    out!(
        "{} runs of {} at the {} budget: {} done ({} archived in {}), {} part-way, {} not started{problems}",
        t.runs,
        p.experiment,
        p.budget,
        t.done,
        t.archived,
        a.registry.display(),
        t.partial,
        t.not_started,
    );
    if t.partial + t.not_started + t.problems > 0 {
        // The same command without --status: it resumes the part-way runs and starts the rest.
        let mut cmd = format!("promptdt reproduce {name} --budget {}", p.budget);
        cmd.push_str(&format!(" --out {}", a.out.display()));
        if let Some(d) = &a.data_root {
            cmd.push_str(&format!(" --data-root {}", d.display()));
        }
        if let Some(n) = a.seeds {
            cmd.push_str(&format!(" --seeds {n}"));
        }
        out!("to go on (resumes the part-way runs, starts the rest): {cmd}");
    }
    Ok(())
}
