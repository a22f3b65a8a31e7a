//! Fine-tuning a run on a subset of tasks (`Start::Resume { tasks }`) and per-task experts
//! (`combine`), on tiny Cheetah-Dir runs.
#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use pdt_data::mode::Mode;
use pdt_rl::agent::{Algorithm, Noise};
use pdt_rl::combine::{combine, evaluate_policy, CombineConfig};
use pdt_rl::datasets::{generate, DatasetConfig};
use pdt_rl::policy;
use pdt_rl::train::{agent_dir, read_agent_card, train, RlConfig, Start};
use pdt_testkit::fs::copy_dir;
use std::path::{Path, PathBuf};
use tch::Device;

fn tiny(steps: u64) -> RlConfig {
    let mut cfg = RlConfig::preset("cheetah_dir").unwrap();
    cfg.algorithm = Algorithm::Sac;
    cfg.total_steps = steps;
    cfg.learning_starts = steps / 4;
    cfg.batch_size = 32;
    cfg.checkpoint_every = steps / 3;
    cfg.snapshot_fractions = vec![0.5, 1.0];
    cfg.agent.sac.hidden = vec![16, 16];
    cfg
}

fn policy_files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    v.sort();
    v
}

#[test]
fn fine_tuning_on_some_tasks_then_per_task_experts() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, c) = (tmp.path().join("a"), tmp.path().join("c"));
    train(Start::New(&tiny(600)), &a, None, Device::Cpu, &mut |_| {}).unwrap().unwrap();

    // Fine-tune a copy on task 1 only, with a larger budget.
    copy_dir(&a, &c).unwrap();
    std::fs::remove_dir_all(c.join("agent")).unwrap();
    let card = train(
        Start::Resume { total_steps: Some(900), tasks: Some(&[1]), sample_recent: Some(200) },
        &c,
        None,
        Device::Cpu,
        &mut |_| {},
    )
    .unwrap()
    .unwrap();
    assert_eq!(card.config.tasks, vec![1]);
    assert_eq!(card.config.sample_recent, 200);
    let csv = std::fs::read_to_string(c.join("episodes.csv")).unwrap();
    let mut after = 0;
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let (start_step, task): (u64, usize) = (f[1].parse().unwrap(), f[2].parse().unwrap());
        let len: u64 = f[4].parse().unwrap();
        if start_step - len >= 600 {
            assert_eq!(task, 1, "an episode after the fine-tuning started is on task {task}");
            after += 1;
        }
    }
    assert!(after >= 1, "no fine-tuning episode");
    assert!(c.join("snapshots").join("actor-000000900.safetensors").exists());
    // An unknown task is refused, naming it.
    let e = train(
        Start::Resume { total_steps: Some(1000), tasks: Some(&[7]), sample_recent: None },
        &c,
        None,
        Device::Cpu,
        &mut |_| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains('7'), "{e}");

    // Per-task experts from both runs' snapshots; top_k large, so every candidate is evaluated.
    let out = tmp.path().join("combined");
    let cfg = CombineConfig {
        base: agent_dir(&a),
        candidates: vec![a.join("snapshots"), c.join("snapshots")],
        top_k: 100,
        eval_episodes: 2,
        seed: 3,
        mirrors: true,
        dataset_noise: Some(Noise::Deterministic),
    };
    let comb = combine(&cfg, &out, Device::Cpu, &mut |_, _| {}).unwrap();
    assert_eq!(read_agent_card(&out).unwrap(), comb);
    assert_eq!(comb.task_experts.len(), 2);
    let family = pdt_envs::family("cheetah_dir").unwrap();
    let mut candidates = vec![agent_dir(&a).join("expert.safetensors")];
    candidates.extend(policy_files(&a.join("snapshots")));
    candidates.extend(policy_files(&c.join("snapshots")));
    for e in &comb.task_experts {
        // The chosen one is the best of all candidates under the same evaluation.
        let best = candidates
            .iter()
            .map(|p| {
                let pol = policy::load(p, Device::Cpu).unwrap();
                evaluate_policy(&pol, family.as_ref(), &[e.task], 2, 3, Device::Cpu).unwrap()[0]
            })
            .fold(f64::NEG_INFINITY, f64::max);
        // Not bitwise: `combine` steps both tasks' episodes in one batch, this check one task's,
        // and a batched matmul may round the last bit differently for another batch size.
        assert!(
            (e.eval_return - best).abs() <= 1e-4 * best.abs().max(1.0),
            "task {}: {} vs {best}",
            e.task,
            e.eval_return
        );
        assert_eq!(comb.expert_eval[e.task], e.eval_return);
        assert!(
            std::fs::read(out.join(&e.file)).unwrap() == std::fs::read(&e.source).unwrap(),
            "{} is not a copy of {}",
            e.file,
            e.source
        );
    }
    // The medium policy: of the base medium and the candidates, the one whose recorded returns are
    // on average closest to each task's halfway point between random actions and its expert.
    let half: Vec<f64> =
        comb.random_eval.iter().zip(&comb.expert_eval).map(|(r, e)| 0.5 * (r + e)).collect();
    let gap = |r: &[f64]| r.iter().zip(&half).map(|(a, h)| (a - h).abs()).sum::<f64>();
    let medium = policy::load(&out.join("medium.safetensors"), Device::Cpu).unwrap();
    assert_eq!(medium.meta.eval_returns, comb.medium_eval);
    let mut pool = candidates.clone();
    pool.push(agent_dir(&a).join("medium.safetensors"));
    for p in &pool {
        let r = policy::load(p, Device::Cpu).unwrap().meta.eval_returns;
        assert!(gap(&comb.medium_eval) <= gap(&r), "{} is closer to halfway", p.display());
    }

    // Datasets: each task's expert data comes from that task's expert file: the same bytes as from
    // an agent directory whose only expert is that file.
    for e in &comb.task_experts {
        let single = tmp.path().join(format!("single-{}", e.task));
        std::fs::create_dir_all(&single).unwrap();
        std::fs::copy(out.join(&e.file), single.join("expert.safetensors")).unwrap();
        std::fs::copy(out.join("medium.safetensors"), single.join("medium.safetensors")).unwrap();
        let mut plain = comb.clone();
        plain.task_experts.clear();
        std::fs::write(single.join("agent.json"), serde_json::to_string(&plain).unwrap()).unwrap();
        let dcfg = DatasetConfig {
            episodes: 3,
            prompt_episodes: 2,
            modes: vec![Mode::Expert],
            tasks: vec![e.task],
            threads: 2,
            ..Default::default()
        };
        let (d1, d2) =
            (tmp.path().join(format!("d1-{}", e.task)), tmp.path().join(format!("d2-{}", e.task)));
        generate(&out, &d1, &dcfg, Device::Cpu, &mut |_, _| {}).unwrap();
        generate(&single, &d2, &dcfg, Device::Cpu, &mut |_, _| {}).unwrap();
        let name = format!("cheetah_dir-{}-expert.safetensors", e.task);
        assert!(std::fs::read(d1.join(&name)).unwrap() == std::fs::read(d2.join(&name)).unwrap());
        let card: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(d1.join("dataset.json")).unwrap())
                .unwrap();
        let per_task = &card["generator"]["expert_per_task"];
        assert_eq!(per_task[0]["task"], e.task);
        assert_eq!(per_task[0]["file"], e.file.as_str());
        // The agent asked for noiseless data, and the config left it to the agent.
        assert_eq!(card["generator"]["noise"], "deterministic");
    }

    // An agent card naming an expert file outside its directory is refused.
    let mut evil = comb.clone();
    evil.task_experts[0].file = "../a/agent/expert.safetensors".into();
    std::fs::write(out.join("agent.json"), serde_json::to_string(&evil).unwrap()).unwrap();
    let e = generate(
        &out,
        &tmp.path().join("d-evil"),
        &DatasetConfig::default(),
        Device::Cpu,
        &mut |_, _| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains("not a file name"), "{e}");

    // Bad input: writing over the base, an empty candidate directory, a policy of another family.
    let e = combine(
        &CombineConfig { base: agent_dir(&a), ..cfg.clone() },
        &agent_dir(&a),
        Device::Cpu,
        &mut |_, _| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains("new directory"), "{e}");
    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = combine(
        &CombineConfig { candidates: vec![empty.clone()], ..cfg.clone() },
        &tmp.path().join("x"),
        Device::Cpu,
        &mut |_, _| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains("empty") && e.to_string().contains("no policy files"), "{e}");
    let mut other = tiny(200);
    other.family = "cheetah_vel".into();
    other.algorithm = Algorithm::Td3;
    other.agent.td3.hidden = vec![8];
    let v = tmp.path().join("vel");
    train(Start::New(&other), &v, None, Device::Cpu, &mut |_| {}).unwrap().unwrap();
    let e = combine(
        &CombineConfig { candidates: vec![v.join("snapshots")], ..cfg },
        &tmp.path().join("y"),
        Device::Cpu,
        &mut |_, _| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains("cheetah_vel policy"), "{e}");
}

/// Ant-Dir: mirrored candidates (the body's symmetries) are evaluated and written as policy files
/// whose encoder carries the mirror; a policy file with a mirror that does not fit is refused.
#[test]
fn ant_candidates_are_also_tried_mirrored() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("ant");
    let mut cfg = tiny(400);
    cfg.family = "ant_dir".into();
    cfg.snapshot_fractions = vec![1.0];
    train(Start::New(&cfg), &run, None, Device::Cpu, &mut |_| {}).unwrap().unwrap();
    let out = tmp.path().join("combined");
    let ccfg = CombineConfig {
        base: agent_dir(&run),
        candidates: vec![run.join("snapshots")],
        top_k: 4, // the expert as it is and through each of the 3 symmetries
        eval_episodes: 1,
        seed: 0,
        mirrors: true,
        dataset_noise: None,
    };
    let card = combine(&ccfg, &out, Device::Cpu, &mut |_, _| {}).unwrap();
    let family = pdt_envs::family("ant_dir").unwrap();
    let base = policy::load(&agent_dir(&run).join("expert.safetensors"), Device::Cpu).unwrap();
    let mut mirrored = 0;
    for e in &card.task_experts {
        let p = policy::load(&out.join(&e.file), Device::Cpu).unwrap();
        assert_eq!(p.meta.encoder.mirror.as_ref().map(|m| m.name.clone()), e.mirror);
        assert!(p.actor.to_vec() == base.actor.to_vec(), "the same actor, mirrored or not");
        let r = evaluate_policy(&p, family.as_ref(), &[e.task], 1, 0, Device::Cpu).unwrap()[0];
        assert!((r - e.eval_return).abs() <= 1e-4 * r.abs().max(1.0), "task {}", e.task);
        mirrored += usize::from(e.mirror.is_some());
    }
    // With four variants of one actor per task, some task is best served mirrored.
    assert!(mirrored > 0, "no task chose a mirrored expert");
    // Without mirrors every expert is the actor as it is.
    let plain = combine(
        &CombineConfig { mirrors: false, ..ccfg },
        &tmp.path().join("plain"),
        Device::Cpu,
        &mut |_, _| {},
    )
    .unwrap();
    assert!(plain.task_experts.iter().all(|e| e.mirror.is_none()));

    // A mirror whose maps do not fit the observation is refused when the file is read.
    let f = card.task_experts.iter().find(|e| e.mirror.is_some()).unwrap();
    let mut p = policy::load(&out.join(&f.file), Device::Cpu).unwrap();
    if let Some(m) = p.meta.encoder.mirror.as_mut() {
        m.obs_index.pop();
    }
    let bad = tmp.path().join("bad.safetensors");
    policy::save(&bad, &p.actor, &p.meta).unwrap();
    let e = policy::load(&bad, Device::Cpu).unwrap_err();
    assert!(e.to_string().contains("mirror") && e.to_string().contains("bad.safetensors"), "{e}");
}
