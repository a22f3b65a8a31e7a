//! `promptdt demo`: collect -> train Prompt-DT and MT-ORL -> evaluate on the held-out goals ->
//! report; `--smoke`: a few training steps of a tiny model.

use crate::args::DemoArgs;
use crate::cmd::bar;
use anyhow::{Context, Result};

/// The steps' loss, gradient norm and learning rate (`--smoke`).
pub fn smoke(a: &DemoArgs) -> Result<()> {
    let device = pdt_torch::device::resolve(a.device)?;
    for (i, s) in pdt_train::smoke::run(0, 20, device)?.iter().enumerate() {
        let (loss, norm, lr) = (s.loss, s.grad_norm, s.lr);
        out!("step {i:>3}  loss {loss:.5}  grad-norm {norm:.4}  lr {lr:.2e}");
    }
    Ok(())
}

/// The demo's experiment file, compiled in so the demo runs from any directory.
const DEMO_CONFIG: &str = include_str!("../../../../configs/point_robot/demo.toml");

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
                envs: None,
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
