//! `promptdt serve` with test-time prompt strategies: an episode opened with
//! `prompt_strategy` acts as the evaluator does with the prompt that strategy chooses, its
//! segments come back with the first action, a `bandit` learns across a task's closed episodes,
//! and bad strategy requests get clear errors.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_eval::evaluate;
use pdt_policy::Policy;
use pdt_prompt::{PromptStrategy, SegmentBatch, SegmentChoice};
use pdt_serve::ServeOptions;
use std::net::SocketAddr;

use crate::support;
use support::{http, point_task, start, tiny_run};

fn floats(v: &serde_json::Value) -> Vec<f32> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

/// One served episode: its actions, the segments of its prompt, and the return the server saw
/// (the rewards sent; the last one ends the episode and is not sent).
struct Served {
    actions: Vec<f32>,
    segments: Vec<SegmentChoice>,
    ret: f64,
}

fn serve_episode(addr: SocketAddr, open: serde_json::Value, task: usize, seed: u64) -> Served {
    let mut env = pdt_envs::family("point_robot").unwrap().make(task).unwrap();
    let mut open = open;
    open["observation"] = serde_json::json!(env.reset(seed));
    let (status, reply) = http(addr, "POST", "/v1/episodes", Some(&open.to_string()));
    assert_eq!(status, 201, "{reply}");
    let segments: Vec<SegmentChoice> =
        serde_json::from_value(reply["prompt_segments"].clone()).unwrap();
    let id = reply["episode"].as_u64().unwrap();
    let (mut actions, mut ret, mut a) = (Vec::new(), 0.0, floats(&reply["action"]));
    loop {
        actions.extend_from_slice(&a);
        let step = env.step(&a).unwrap();
        if step.terminated || step.truncated {
            break;
        }
        ret += step.reward as f64;
        let body = serde_json::json!({ "reward": step.reward, "observation": step.obs });
        let path = format!("/v1/episodes/{id}/step");
        let (status, reply) = http(addr, "POST", &path, Some(&body.to_string()));
        assert_eq!(status, 200, "{reply}");
        a = floats(&reply["action"]);
        // the segments come with the first action only
        assert!(reply.get("prompt_segments").is_none(), "{reply}");
    }
    assert_eq!(http(addr, "DELETE", &format!("/v1/episodes/{id}"), None).0, 204);
    Served { actions, segments, ret }
}

/// The evaluator's actions for one episode of `task` from `seed` with `prompt`.
fn evaluated(run: &Policy, task: usize, seed: u64, prompt: SegmentBatch) -> Vec<f32> {
    let settings = run.eval_settings();
    let t = point_task(task, seed, Some(prompt));
    tch::set_num_threads(1);
    evaluate(&run.model, vec![t], &settings).unwrap().remove(0).actions
}

#[test]
fn strategy_episodes_take_the_evaluators_actions_with_the_strategys_prompt() {
    tch::set_num_threads(1);
    let server = start(ServeOptions { threads: 1, ..Default::default() });
    let run = Policy::load(&tiny_run().1, None, None).unwrap();
    let (task, seed) = (34usize, 5u64);
    let first: Vec<f32> = {
        let mut env = pdt_envs::family("point_robot").unwrap().make(task).unwrap();
        env.reset(seed)
    };
    for (name, length) in
        [("random-segment", None), ("best-return", None), ("nearest-start", Some(3))]
    {
        let mut open =
            serde_json::json!({ "task": task, "prompt_seed": 7, "prompt_strategy": name });
        if let Some(h) = length {
            open["prompt_length"] = serde_json::json!(h);
        }
        let served = serve_episode(server.addr, open, task, seed);
        let strategy = PromptStrategy { length, ..PromptStrategy::named(name).unwrap() };
        let chosen = run.strategy_prompt(task, 7, &strategy, Some(&first)).unwrap();
        assert_eq!(served.segments, chosen.segments, "{name}");
        assert_eq!(chosen.prompt.steps, length.unwrap_or(run.prompt_steps), "{name}");
        let want = evaluated(&run, task, seed, chosen.prompt);
        let same = served.actions.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(
            same && served.actions.len() == want.len(),
            "{name}: {:?}\n{want:?}",
            served.actions
        );
    }
}

#[test]
fn a_bandit_learns_from_the_returns_of_its_tasks_closed_episodes() {
    tch::set_num_threads(1);
    let server = start(ServeOptions { threads: 1, ..Default::default() });
    let run = Policy::load(&tiny_run().1, None, None).unwrap();
    let task = 2usize;
    let open = serde_json::json!({ "task": task, "prompt_seed": 3, "prompt_strategy": "bandit" });
    let served: Vec<Served> =
        (0..6).map(|s| serve_episode(server.addr, open.clone(), task, s)).collect();
    // The same bandit, told the same returns, makes the same choices.
    let strategy = PromptStrategy::named("bandit").unwrap();
    let mut b = run.task_bandit(task, 3, &strategy).unwrap();
    for s in &served {
        let (chosen, choice) = run.bandit_prompt(&mut b).unwrap();
        assert_eq!(s.segments, chosen.segments);
        b.update(&choice, s.ret);
    }
    // Another task has its own bandit; a different setting for this one is refused.
    let other = serde_json::json!({ "task": task, "prompt_seed": 3, "prompt_strategy": "bandit",
                                    "prompt_length": 2, "observation": [0.0, 0.0] });
    let (status, reply) = http(server.addr, "POST", "/v1/episodes", Some(&other.to_string()));
    assert_eq!(status, 400, "{reply}");
    assert!(reply["error"].as_str().unwrap().contains("other settings"), "{reply}");
}

#[test]
fn bad_strategy_requests_get_clear_errors() {
    let server = start(ServeOptions::default());
    let post = |body: serde_json::Value| {
        let (status, reply) = http(server.addr, "POST", "/v1/episodes", Some(&body.to_string()));
        (status, reply["error"].as_str().unwrap_or_default().to_string())
    };
    let obs = serde_json::json!([0.0, 0.0]);
    let (s, e) =
        post(serde_json::json!({ "task": 2, "prompt_strategy": "tail", "observation": obs }));
    assert_eq!(s, 400);
    assert!(e.contains("unknown prompt strategy `tail`") && e.contains("best-return"), "{e}");
    let (s, e) = post(serde_json::json!({ "task": 2, "prompt_length": 400, "observation": obs }));
    assert_eq!(s, 400);
    assert!(e.contains("1 x 400"), "{e}");
    let (s, e) = post(serde_json::json!({ "prompt_strategy": "best-return", "observation": obs }));
    assert_eq!(s, 400);
    assert!(e.contains("send a `task`"), "{e}");
    // the server keeps serving
    let (s, _) = post(
        serde_json::json!({ "task": 2, "prompt_strategy": "best-return", "observation": obs }),
    );
    assert_eq!(s, 201);
}
