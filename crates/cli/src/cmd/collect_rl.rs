//! `promptdt collect` for the MuJoCo families: train an agent (or resume one, or take the
//! pretrained one), then write the datasets from its snapshots.

use crate::args::CollectArgs;
use crate::cmd::{bar, follow};
use anyhow::Result;
use pdt_rl::agent::Noise;
use pdt_rl::overrides::RlOverrides;
use pdt_rl::train::{RlConfig, Start, TrainProgress};
use std::path::PathBuf;

pub fn collect(a: &CollectArgs, family: &str) -> Result<()> {
    if let Some(t) = a.threads {
        tch::set_num_threads(t as i32);
    }
    let device = pdt_torch::device::resolve(a.device)?;
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("data").join(family));
    let agent_dir = if a.from_pretrained {
        let default = || PathBuf::from("pretrained").join(family);
        let dir = a.pretrained_dir.clone().unwrap_or_else(default);
        out!("using the pretrained agent in {}", dir.display());
        dir
    } else {
        match train_agent(a, family, device)? {
            Some(dir) => dir,
            None => return Ok(()),
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
    let summary = pdt_rl::datasets::generate(&agent_dir, &out, &dcfg, device, &mut follow(&pb))?;
    pb.finish_and_clear();
    out!("{summary} in {:.1} s", t0.elapsed().as_secs_f64());
    Ok(())
}

/// Trains (or resumes) the family's agent; its agent directory, or `None` where it stopped as
/// asked (`--stop-after`) before the end.
fn train_agent(a: &CollectArgs, family: &str, device: tch::Device) -> Result<Option<PathBuf>> {
    let default = || PathBuf::from("runs").join(format!("collect-{family}"));
    let run_dir = a.run_dir.clone().unwrap_or_else(default);
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
    let pb = bar(cfg.total_steps, "{prefix} {bar:30} {pos}/{len} steps [{elapsed} < {eta}] {msg}");
    pb.set_prefix(format!("{} {family}", cfg.algorithm.name()));
    let mut on_progress = |p: &TrainProgress<'_>| {
        pb.set_length(p.total);
        pb.set_position(p.step);
        pb.set_message(p.message());
        if let Some(s) = p.snapshot {
            pb.println(format!(
                "snapshot at step {}: mean deterministic return {:.1}",
                s.step, s.mean_return
            ));
        }
    };
    let start = if a.resume {
        let tasks = a.tasks.as_deref();
        Start::Resume { total_steps: a.steps, tasks, sample_recent: a.sample_recent }
    } else {
        Start::New(&cfg)
    };
    let card = pdt_rl::train::train(start, &run_dir, a.stop_after, device, &mut on_progress)?;
    pb.finish_and_clear();
    let Some(card) = card else {
        out!(
            "stopped as asked (--stop-after); continue with --resume --run-dir {}",
            run_dir.display()
        );
        return Ok(None);
    };
    out!("{}", card.training_summary());
    Ok(Some(pdt_rl::train::agent_dir(&run_dir)))
}
