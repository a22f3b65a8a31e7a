//! `promptdt serve` with evaluation-time adaptations: an episode opened with
//! `adapt` acts as the evaluator does with that task's adaptation (`pdt_policy::Policy::adapt`,
//! through `pdt_eval::evaluate_given`, LoRA's adapters included), the adaptation's log comes back
//! with the first action, the next episode of the same task and settings reuses it, and bad
//! adaptation requests get clear errors.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_eval::{evaluate_given, GivenPrompts};
use pdt_policy::Policy;
use pdt_prompt::PromptStrategy;
use pdt_rundir::config::{AdaptConfig, AdaptKind, Adaptation, TestTime};
use pdt_serve::ServeOptions;
use std::net::SocketAddr;

use crate::support;
use support::{http, point_task, start, tiny_run};

fn floats(v: &serde_json::Value) -> Vec<f32> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

/// One served episode: its actions and the opening reply's `adaptation`.
fn serve_episode(
    addr: SocketAddr,
    open: serde_json::Value,
    task: usize,
    seed: u64,
) -> (Vec<f32>, serde_json::Value) {
    let mut env = pdt_envs::family("point_robot").unwrap().make(task).unwrap();
    let mut open = open;
    open["observation"] = serde_json::json!(env.reset(seed));
    let (status, reply) = http(addr, "POST", "/v1/episodes", Some(&open.to_string()));
    assert_eq!(status, 201, "{reply}");
    let log = reply["adaptation"].clone();
    let id = reply["episode"].as_u64().unwrap();
    let (mut actions, mut a) = (Vec::new(), floats(&reply["action"]));
    loop {
        actions.extend_from_slice(&a);
        let step = env.step(&a).unwrap();
        if step.terminated || step.truncated {
            break;
        }
        let body = serde_json::json!({ "reward": step.reward, "observation": step.obs });
        let path = format!("/v1/episodes/{id}/step");
        let (status, reply) = http(addr, "POST", &path, Some(&body.to_string()));
        assert_eq!(status, 200, "{reply}");
        assert!(reply.get("adaptation").is_none(), "the log comes with the first action: {reply}");
        a = floats(&reply["action"]);
    }
    assert_eq!(http(addr, "DELETE", &format!("/v1/episodes/{id}"), None).0, 204);
    (actions, log)
}

/// The test time of `cfg`'s adaptation from the reference prompt.
fn adapted(cfg: AdaptConfig) -> TestTime {
    TestTime::Adapt { from: PromptStrategy::default(), adaptation: Adaptation::Prompt(cfg) }
}

/// The evaluator's actions for one episode of `task` from `seed` with an adaptation.
fn evaluated(
    run: &Policy,
    task: usize,
    seed: u64,
    a: &pdt_eval::testtime::TaskAdaptation,
) -> Vec<f32> {
    let settings = run.eval_settings();
    let t = point_task(task, seed, None);
    tch::set_num_threads(1);
    let given = GivenPrompts { prefix: a.prefix(&run.model), lora: a.lora() };
    evaluate_given(&run.model, vec![t], &settings, given).unwrap().remove(0).actions
}

#[test]
fn adapted_episodes_act_as_the_evaluator_with_the_tasks_adaptation() {
    tch::set_num_threads(1);
    let budget = AdaptConfig { steps: 3, batch: 4, ..Default::default() };
    let server = start(ServeOptions { threads: 1, adapt: budget.clone(), ..Default::default() });
    let run = Policy::load(&tiny_run().1, None, None).unwrap();
    let (task, seed) = (34usize, 5u64);
    for kind in [AdaptKind::SoftPrompt, AdaptKind::Ptdt, AdaptKind::Lora] {
        let open = serde_json::json!({ "task": task, "prompt_seed": 7, "adapt": kind.name() });
        let (served, log) = serve_episode(server.addr, open.clone(), task, seed);
        let cfg = AdaptConfig { kind, ..budget.clone() };
        let a = run.adapt(task, 7, &adapted(cfg)).unwrap();
        assert_eq!(log["task"], a.log.task, "{kind}: {log}");
        assert_eq!(log["steps"], 3, "{kind}: {log}");
        assert_eq!(log["trainable"].as_u64().unwrap() as usize, a.log.trainable, "{kind}");
        assert_eq!(log["loss_before"].as_f64().unwrap(), a.log.loss_before, "{kind}");
        assert_eq!(log["loss_after"].as_f64().unwrap(), a.log.loss_after, "{kind}");
        let want = evaluated(&run, task, seed, &a);
        let same = served.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same && served.len() == want.len(), "{kind}: {served:?}\n{want:?}");
        // The next episode of the task and settings reuses the adaptation (the same log, wall
        // time included), and another seed acts on the same adapted policy.
        let (_, again) = serve_episode(server.addr, open, task, seed + 1);
        assert_eq!(again, log, "{kind}");
    }
    // The server's `--adapt` applies to `task` episodes that name none.
    let server = start(ServeOptions {
        threads: 1,
        adapt: AdaptConfig { kind: AdaptKind::Lora, ..budget.clone() },
        ..Default::default()
    });
    let (_, log) =
        serve_episode(server.addr, serde_json::json!({ "task": task, "prompt_seed": 7 }), task, 1);
    assert!(log["trainable"].as_u64().unwrap() > 0, "{log}");
    // ... and `"adapt": "none"` opts out.
    let open = serde_json::json!({ "task": task, "prompt_seed": 7, "adapt": "none" });
    let (_, log) = serve_episode(server.addr, open, task, 1);
    assert!(log.is_null(), "{log}");
}

#[test]
fn bad_adaptation_requests_get_clear_errors() {
    let server = start(ServeOptions {
        adapt: AdaptConfig { steps: 2, batch: 2, ..Default::default() },
        ..Default::default()
    });
    let post = |body: serde_json::Value| {
        let (status, reply) = http(server.addr, "POST", "/v1/episodes", Some(&body.to_string()));
        (status, reply["error"].as_str().unwrap_or_default().to_string())
    };
    let obs = serde_json::json!([0.0, 0.0]);
    let (s, e) = post(serde_json::json!({ "task": 2, "adapt": "finetune", "observation": obs }));
    assert_eq!(s, 400);
    assert!(e.contains("unknown adaptation `finetune`") && e.contains("lora"), "{e}");
    let prompt = serde_json::json!({ "states": [[0.0, 0.0]], "actions": [[0.0, 0.0]],
                                     "returns_to_go": [0.0], "timesteps": [0] });
    let (s, e) = post(serde_json::json!({ "prompt": prompt, "adapt": "lora", "observation": obs }));
    assert_eq!(s, 400);
    assert!(e.contains("send a `task`"), "{e}");
    let (s, e) = post(serde_json::json!({ "task": 2, "adapt": "lora", "prompt_strategy": "bandit",
                                          "observation": obs }));
    assert_eq!(s, 400);
    assert!(e.contains("one prompt per task") && e.contains("bandit"), "{e}");
    let (s, e) = post(serde_json::json!({ "task": 999, "adapt": "lora", "observation": obs }));
    assert_eq!(s, 400);
    assert!(e.contains("task 999"), "{e}");
    // the server keeps serving
    let (s, e) = post(serde_json::json!({ "task": 2, "adapt": "soft-prompt", "observation": obs }));
    assert_eq!(s, 201, "{e}");
}

#[test]
fn a_return_scored_ptdt_is_refused_where_no_environment_is_stepped() {
    let mut cfg = AdaptConfig { kind: AdaptKind::Ptdt, steps: 2, batch: 2, ..Default::default() };
    cfg.ptdt.score = pdt_rundir::config::PtdtScore::Return;
    let run = Policy::load(&tiny_run().1, None, None).unwrap();
    let e = run.adapt(2, 0, &adapted(cfg)).unwrap_err().to_string();
    assert!(e.contains("ptdt.score = \"return\"") && e.contains("action-loss"), "{e}");
}
