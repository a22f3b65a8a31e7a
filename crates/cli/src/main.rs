//! `promptdt`: a thin shell over the library crates. Each subcommand turns its arguments into a
//! library call; errors are printed with their causes and give a nonzero exit code.

/// `println!` that hands a failed write back as an error instead of panicking:
/// `promptdt reproduce --list | head` closes the pipe early, and `main` ends quietly on that.
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*).map_err($crate::StdoutError)?
    }};
}

/// `print!` the same way as `out!` (no newline added).
macro_rules! out_inline {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        write!(std::io::stdout().lock(), $($arg)*).map_err($crate::StdoutError)?
    }};
}

mod args;
mod bench_args;
mod commands;
mod eval_flags;
mod packs;
mod prompt_args;

use anyhow::{bail, Context, Result};
use args::{AgentCommand, Cli, Command, DataCommand, EnvCommand, ModelCommand, ResultsCommand};
use clap::Parser;
use commands::{collect, train};
use std::io::ErrorKind;
use std::process::ExitCode;

/// A write to standard output failed (see `out!`).
#[derive(Debug)]
pub struct StdoutError(pub std::io::Error);

impl std::fmt::Display for StdoutError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "writing to standard output: {}", self.0)
    }
}

impl std::error::Error for StdoutError {}

fn main() -> ExitCode {
    // Before any tensor exists: a large-batch training step otherwise spends much of its CPU
    // time faulting in and zero-filling pages the allocator gave back after the previous step
    // (pdt_model::host_memory; 4.4 s -> 2.8 s per step at batch 560). Results do not change.
    let _ = pdt_model::host_memory::keep_freed_memory();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        // The reader of our standard output went away (`| head`): not an error of ours.
        Err(e)
            if e.downcast_ref::<StdoutError>()
                .is_some_and(|s| s.0.kind() == ErrorKind::BrokenPipe) =>
        {
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", error_chain(&e));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes, `: `-separated. Library errors already include their cause in their
/// message (so `to_string()` is useful to library users); a cause whose text is already there is
/// not repeated.
fn error_chain(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if !out.contains(&text) {
            if !out.is_empty() {
                out.push_str(": ");
            }
            out.push_str(&text);
        }
    }
    out
}

/// `--die-with-parent`: `reproduce` holds the write end of a pipe that is this process's standard
/// input and never writes to it. When `reproduce` dies, however it dies (even SIGKILL), the kernel
/// closes that end and the read here ends: stop, so no child outlives a killed sweep. Whatever this
/// process was writing is safe: every file goes through the atomic writer, and its temporaries
/// are removed on the next start (`docs/failure-behaviour.md`). (A pipe rather than
/// `prctl(PR_SET_PDEATHSIG)`: that needs unsafe code.)
fn die_with_parent() {
    std::thread::spawn(|| {
        use std::io::Read as _;
        let mut stdin = std::io::stdin().lock();
        let mut buf = [0_u8; 64];
        loop {
            match stdin.read(&mut buf) {
                Ok(0) => break,
                Ok(_) => {}
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(_) => break,
            }
        }
        // Not `eprintln!`: standard error is often a pipe to the parent that died, and
        // `eprintln!` panics when the write fails, which would end this thread, not the process.
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), "promptdt: the parent process is gone; stopping");
        std::process::exit(1);
    });
}

fn run(cli: Cli) -> Result<()> {
    if cli.die_with_parent {
        die_with_parent();
    }
    match cli.command {
        Command::Data(DataCommand::Inspect(a)) => {
            let reports = pdt_data::inspect::inspect_path(&a.path)?;
            if a.json {
                out!("{}", serde_json::to_string_pretty(&reports)?);
            } else {
                out_inline!("{}", pdt_data::inspect::render_table(&reports));
            }
        }
        Command::Data(DataCommand::Convert(a)) => {
            let files = pdt_data::multitask::convert_reference_dir(&a.src, &a.dst)?;
            for f in &files {
                out!(
                    "{} -> {} ({} trajectories, {} steps)",
                    f.source.display(),
                    f.dest.display(),
                    f.trajectories,
                    f.steps
                );
            }
            out!("converted {} files into {}", files.len(), a.dst.display());
        }
        Command::Data(DataCommand::Report(a)) => {
            let cfg = pdt_report::DatasetReportConfig {
                out_dir: a.out.clone().unwrap_or_else(|| a.ours.join("report")),
                ours: a.ours.clone(),
                reference: a.reference.clone(),
            };
            let summary = pdt_report::dataset_report(&cfg)?;
            for f in &summary.families {
                out_inline!("{}", f.markdown);
            }
            for w in &summary.warnings {
                eprintln!("warning: {w}");
            }
            for f in &summary.files {
                out!("wrote {}", f.display());
            }
        }
        Command::Model(ModelCommand::Forward(a)) => {
            match a.threads {
                Some(0) => bail!("--threads must be at least 1"),
                Some(t) => tch::set_num_threads(i32::try_from(t).unwrap_or(i32::MAX)),
                None => {}
            }
            let device = pdt_model::device::resolve(a.device)?;
            let run = pdt_policy::files::run_architecture_of(&a.weights)?;
            let s = pdt_model::forward_file::forward_file(
                &a.weights,
                &a.inputs,
                &a.out,
                device,
                a.n_head,
                run.as_ref(),
            )?;
            out!(
                "wrote action_preds [{}, {}, {}] to {} (prompt: {} steps)",
                s.batch,
                s.history_steps,
                s.act_dim,
                a.out.display(),
                s.prompt_steps
            );
        }
        Command::Agent(AgentCommand::Combine(a)) => {
            let device = pdt_model::device::resolve(a.device)?;
            let cfg = pdt_rl::combine::CombineConfig {
                base: a.base.clone(),
                candidates: a.snapshots.clone(),
                top_k: a.top_k,
                eval_episodes: a.eval_episodes,
                seed: a.seed,
                mirrors: !a.no_mirrors,
                dataset_noise: a
                    .deterministic_datasets
                    .then_some(pdt_rl::agent::Noise::Deterministic),
            };
            let pb =
                commands::bar(0, "evaluating {bar:30} {pos}/{len} snapshots [{elapsed} < {eta}]");
            let card = pdt_rl::combine::combine(&cfg, &a.out, device, &mut |done, total| {
                pb.set_length(total as u64);
                pb.set_position(done as u64);
            })?;
            pb.finish_and_clear();
            out!("{:<6} {:>12} {:>10} {:>10}  file", "task", "return", "step", "mirror");
            for e in &card.task_experts {
                let m = e.mirror.as_deref().unwrap_or("-");
                out!("{:<6} {:>12.1} {:>10} {m:>10}  {}", e.task, e.eval_return, e.step, e.file);
            }
            let m = card.expert_eval.iter().sum::<f64>() / card.expert_eval.len().max(1) as f64;
            out!(
                "mean expert return {m:.1} over {} tasks; wrote {}/agent.json",
                card.expert_eval.len(),
                a.out.display()
            );
        }
        Command::Collect(a) => collect(&a)?,
        Command::Train(a) if packs::is_pack(&a) => packs::train_pack(&a)?,
        Command::Train(a) => train(&a)?,
        Command::Eval(a) => {
            eval_flags::check_eval_flags(&a).map_err(anyhow::Error::msg)?;
            // --adapt-steps / --adapt-batch are the budget of the adaptation --adapt names: an
            // [eval.adapt] kind's, or the run's own (MACAW's, MT-BC-Finetune's).
            let (adapt, macaw) = match (a.adaptation.adapt, a.adapt_steps.or(a.adapt_batch)) {
                (None, None) => (None, Default::default()),
                _ => {
                    let run = pdt_rundir::RunDir::at(&a.run);
                    let cfg = pdt_policy::files::run_config(&run, None, a.data.as_deref())?;
                    let test_time = pdt_rundir::config::TestTime::of(&cfg);
                    let own = eval_flags::own_budget(&a, &test_time, cfg.run.method)
                        .map_err(anyhow::Error::msg)?;
                    (eval_flags::eval_adapt(&a, &cfg.eval.adapt), own.unwrap_or_default())
                }
            };
            let req = pdt_train::run::EvalRequest {
                episodes: a.episodes,
                split: a.split.clone(),
                device: a.device,
                data: a.data.clone(),
                macaw,
                prompt: eval_flags::eval_prompt(&a),
                adapt,
                repeats: a.repeats,
            };
            let prompted = pdt_train::run::evaluate_run_as(&a.run, &req)?;
            let r = &prompted.eval;
            // Families with a success criterion (Meta-World) also show the success rate.
            let rates: Option<Vec<f64>> = r.tasks.iter().map(|t| t.success_rate).collect();
            let rates = rates.filter(|v| !v.is_empty());
            let success_col = |x: Option<f64>| match (&rates, x) {
                (Some(_), Some(v)) => format!(" {:>8.1}%", 100.0 * v),
                _ => String::new(),
            };
            let head = if rates.is_some() { format!(" {:>9}", "success") } else { String::new() };
            out!("{:<24} {:>12} {:>10} {:>9}{head}", "task", "return mean", "std", "episodes");
            for t in &r.tasks {
                out!(
                    "{:<24} {:>12.2} {:>10.2} {:>9}{}",
                    t.task,
                    t.return_mean,
                    t.return_std,
                    t.episodes,
                    success_col(t.success_rate)
                );
            }
            let mean_rate = rates.as_ref().map(|v| v.iter().sum::<f64>() / v.len() as f64);
            out!(
                "{:<24} {:>12.2} {:>10} {:>9}{}",
                format!("average ({})", r.eval_on),
                r.mean_return,
                "",
                "",
                success_col(mean_rate)
            );
            if let Some(how) = &r.adaptation {
                out!("adapted to each task with {how}");
            }
            if let Some(rep) = &r.repeats {
                out!(
                    "{} repeats (the rows above: repeat 0): average {:.2} ± {:.2} (sample std over \
                     repeats: evaluation noise)",
                    rep.mean_returns.len(),
                    rep.mean_returns.iter().sum::<f64>() / rep.mean_returns.len() as f64,
                    rep.mean_return_sd
                );
            }
            for l in &prompted.adapt_log {
                out!(
                    "adapted {:<24} action loss {:.5} -> {:.5} ({} steps, {} values, {:.2} s)",
                    l.task,
                    l.loss_before,
                    l.loss_after,
                    l.steps,
                    l.trainable,
                    l.seconds
                );
            }
            let file = if !prompted.adapt.is_none() {
                out!("adaptation {} (eval.adapt)", prompted.adapt.kind);
                format!("eval_adapt_{}.json", prompted.adapt.kind)
            } else if prompted.prompt_strategy.is_default() {
                pdt_rundir::EVAL_FINAL_JSON.to_string()
            } else {
                let s = &prompted.prompt_strategy;
                out!("prompt strategy {} ({} choices logged)", s.strategy, prompted.picks.len());
                format!("eval_prompt_{}.json", s.strategy)
            };
            out!(
                "checkpoint {} (iteration {}); wrote {}/{file}",
                r.checkpoint,
                r.iteration,
                a.run.display()
            );
        }
        Command::Report(a) => {
            let cfg = pdt_report::ReportConfig {
                runs: a.runs.clone(),
                out_dir: a.out.clone(),
                title: a.title.clone(),
            };
            let summary = pdt_report::run(&cfg)?;
            out_inline!("{}", summary.markdown);
            for w in &summary.warnings {
                eprintln!("warning: {w}");
            }
            for f in &summary.files {
                out!("wrote {}", f.display());
            }
        }
        Command::Env(EnvCommand::Replay(a)) => {
            let read = |p: &std::path::Path| {
                pdt_base::fs::read_text_limited(p, pdt_base::fs::MAX_TEXT_BYTES)
                    .with_context(|| format!("reading {}", p.display()))
            };
            let actions: Vec<Vec<f32>> =
                serde_json::from_str(&read(&a.actions)?).with_context(|| {
                    format!(
                        "{}: expected a JSON array of actions (arrays of numbers)",
                        a.actions.display()
                    )
                })?;
            // An unknown family is named as such, before its initial state is read; the family
            // itself knows what initial state it takes (`EnvFamily::replay`).
            let family = pdt_envs::family(&a.env)?;
            let init = a.init.as_deref().map(read).transpose()?;
            let r = family.replay(a.task, init.as_deref(), &actions);
            let r = match &a.init {
                Some(p) => r.with_context(|| format!("--init {}", p.display()))?,
                None => r?,
            };
            let text = serde_json::to_string(&r)?;
            pdt_model::checkpoint::write_atomic(&a.out, text.as_bytes())
                .with_context(|| format!("writing {}", a.out.display()))?;
            let ret: f64 = r.rewards.iter().map(|&x| x as f64).sum();
            out!(
                "{} task {}: {} steps, return {ret:.3}, terminated {}, wrote {}",
                r.family,
                r.task,
                r.rewards.len(),
                r.terminated.iter().any(|&t| t),
                a.out.display()
            );
        }
        Command::Reproduce(a) => commands::reproduce(&a)?,
        Command::Results(ResultsCommand::Add(a)) => {
            for r in pdt_repro::registry::add(&a.to_options())? {
                out!("archived {} into {} ({} bytes)", r.key, r.dir.display(), r.bytes);
            }
        }
        Command::Results(ResultsCommand::Render(a)) => {
            for f in pdt_repro::render::write(&a.to_options())? {
                out!("wrote {}", f.display());
            }
        }
        Command::Render(a) => {
            let mut cfg = pdt_policy::video::VideoConfig::new(
                a.run,
                a.task,
                a.out,
                a.width,
                a.height,
                a.fps,
                a.max_steps,
                a.seed,
            )?;
            (cfg.device, cfg.data) = (a.device, a.data);
            let v = pdt_policy::video::record_episode(&cfg)?;
            out!(
                "{}: {} task {}, {} steps, return {:.2} ({} frames)",
                v.out.display(),
                v.family,
                v.task,
                v.steps,
                v.ret,
                v.frames
            );
        }
        Command::Serve(a) => {
            // Who may use it, settled (and an exposed address without a token refused) before
            // the run is loaded.
            let (auth, generated) = a.auth()?;
            pdt_serve::auth::check(&a.listen, &auth)?;
            let run = pdt_policy::Policy::load(&a.run, a.device, a.data.as_deref())?;
            let opts = pdt_serve::ServeOptions {
                listen: a.listen,
                max_episodes: a.max_episodes,
                max_batch: a.max_batch,
                batch_wait: std::time::Duration::from_millis(a.batch_wait_ms as u64),
                idle_timeout: std::time::Duration::from_secs(a.idle_timeout_s as u64),
                max_body_bytes: a.max_body_bytes,
                header_timeout: std::time::Duration::from_secs(a.header_timeout_s as u64),
                body_timeout: std::time::Duration::from_secs(a.body_timeout_s as u64),
                max_connections: a.max_connections,
                threads: a.threads,
                prompt_strategy: pdt_prompt::PromptStrategy {
                    strategy: a.prompt_strategy.unwrap_or_default(),
                    episodes: a.prompt_episodes,
                    length: a.prompt_length,
                    ..Default::default()
                },
                adapt: a.adaptation.to_config().map_err(anyhow::Error::msg)?,
                auth,
                ..Default::default()
            };
            let warning = pdt_serve::auth::exposure_warning(&opts.listen, &opts.auth);
            let server = pdt_serve::Server::start(run, opts)?;
            if let Some(w) = warning {
                eprintln!("{w}");
            }
            // The first line of output: clients (and tests) read the address from it; a
            // generated token is the second, shown this once.
            out!("listening on http://{}", server.addr);
            if let Some(token) = generated {
                out!("token: {token}");
            }
            use std::io::Write as _;
            let _ = std::io::stdout().flush();
            server.wait_for_ctrl_c()?;
        }
        Command::Bench(a) => {
            if let Some(crate::bench_args::BenchCommand::Render(r)) = &a.action {
                let md = pdt_bench::record::render_dir(&r.records)?;
                pdt_base::fs::write_atomic(&r.out, md.as_bytes())
                    .with_context(|| format!("writing {}", r.out.display()))?;
                out!("wrote {}", r.out.display());
                return Ok(());
            }
            let cfg = a.to_config()?;
            let report = pdt_bench::run(&cfg)?;
            let md = pdt_bench::render_markdown(&report);
            out_inline!("{md}");
            if let Some(dir) = &a.out {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
                std::fs::write(dir.join("bench.json"), serde_json::to_string_pretty(&report)?)?;
                std::fs::write(dir.join("bench.md"), md)?;
                out!("wrote {}/bench.json and bench.md", dir.display());
            }
            if let Some(path) = &a.json_out {
                let command = crate::bench_args::command_line();
                pdt_bench::record::from_report(&report, command, a.title.clone()).write(path)?;
                out!("wrote {}", path.display());
            }
        }
        Command::Demo(a) if a.smoke => {
            let device = pdt_model::device::resolve(a.device)?;
            for (i, s) in pdt_train::smoke::run(0, 20, device)?.iter().enumerate() {
                out!(
                    "step {i:>3}  loss {:.5}  grad-norm {:.4}  lr {:.2e}",
                    s.loss,
                    s.grad_norm,
                    s.lr
                );
            }
        }
        Command::Demo(a) => commands::demo(&a)?,
    }
    Ok(())
}
