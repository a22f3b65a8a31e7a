//! `promptdt serve` over the wire (loopback only): a served episode takes the evaluator's actions,
//! concurrent episodes batched into one forward take the actions they take alone, and bad requests
//! get a clear error while the server keeps serving.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_eval::evaluate;
use pdt_policy::Policy;
use pdt_serve::ServeOptions;
use std::io::Write;
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

use crate::support;
use support::{http, point_task, start, tiny_run};

fn action(v: &serde_json::Value) -> Vec<f32> {
    v["action"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

/// Runs one served episode of point-robot task `task` from reset seed `seed`; returns its actions.
fn served_episode(addr: SocketAddr, open: serde_json::Value, task: usize, seed: u64) -> Vec<f32> {
    let family = pdt_envs::family("point_robot").unwrap();
    let mut env = family.make(task).unwrap();
    let mut obs = env.reset(seed);
    let mut open = open;
    open["observation"] = serde_json::json!(obs);
    let (status, reply) = http(addr, "POST", "/v1/episodes", Some(&open.to_string()));
    assert_eq!(status, 201, "{reply}");
    let id = reply["episode"].as_u64().unwrap();
    let mut actions = Vec::new();
    let mut a = action(&reply);
    loop {
        actions.extend_from_slice(&a);
        let step = env.step(&a).unwrap();
        obs = step.obs;
        if step.terminated || step.truncated {
            break;
        }
        let body = serde_json::json!({ "reward": step.reward, "observation": obs }).to_string();
        let (status, reply) = http(addr, "POST", &format!("/v1/episodes/{id}/step"), Some(&body));
        assert_eq!(status, 200, "{reply}");
        a = action(&reply);
    }
    assert_eq!(http(addr, "DELETE", &format!("/v1/episodes/{id}"), None).0, 204);
    actions
}

/// What `promptdt eval` takes for one episode of `task` with the prompt of `open`.
fn evaluated_episode(task: usize, seed: u64, prompt_seed: u64) -> Vec<f32> {
    let run = Policy::load(&tiny_run().1, None, None).unwrap();
    let _family = pdt_envs::family("point_robot").unwrap();
    let settings = run.eval_settings();
    let prompt = run.task_prompt(task, prompt_seed).unwrap();
    let t = point_task(task, seed, Some(prompt));
    tch::set_num_threads(1);
    evaluate(&run.model, vec![t], &settings).unwrap().remove(0).actions
}

#[test]
fn a_served_episode_takes_the_evaluators_actions() {
    tch::set_num_threads(1);
    let server = start(ServeOptions { threads: 1, ..Default::default() });
    let (status, info) = http(server.addr, "GET", "/v1/info", None);
    assert_eq!(status, 200);
    assert_eq!((info["obs_dim"].as_u64(), info["method"].as_str()), (Some(2), Some("prompt-dt")));
    let tasks: Vec<u64> =
        info["prompt_tasks"].as_array().unwrap().iter().map(|t| t.as_u64().unwrap()).collect();
    assert!(tasks.contains(&34), "{info}");
    for (task, seed, prompt_seed) in [(34usize, 5u64, 0u64), (2, 9, 3)] {
        let open = serde_json::json!({ "task": task, "prompt_seed": prompt_seed });
        let served = served_episode(server.addr, open, task, seed);
        let evaluated = evaluated_episode(task, seed, prompt_seed);
        assert_eq!(served.len(), 40);
        let same = served.iter().zip(&evaluated).all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same, "task {task}: served {served:?}\nevaluated {evaluated:?}");
    }
}

#[test]
fn concurrent_episodes_batched_take_their_sequential_actions() {
    tch::set_num_threads(1);
    let server = start(ServeOptions {
        batch_wait: Duration::from_millis(5),
        threads: 1,
        ..Default::default()
    });
    let addr = server.addr;
    let tasks = [2usize, 10, 18, 26, 34];
    let episodes: Vec<(usize, u64)> = (0..64).map(|i| (tasks[i % 5], i as u64)).collect();
    let open = |task: usize| serde_json::json!({ "task": task });
    // alone, one after the other
    let sequential: Vec<Vec<f32>> =
        episodes.iter().map(|&(t, s)| served_episode(addr, open(t), t, s)).collect();
    // 8 client threads, 8 episodes each, all at once
    let concurrent: Vec<Vec<f32>> = std::thread::scope(|sc| {
        let handles: Vec<_> = episodes
            .chunks(8)
            .map(|chunk| {
                sc.spawn(move || {
                    chunk
                        .iter()
                        .map(|&(t, s)| served_episode(addr, open(t), t, s))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap()).collect()
    });
    let mut worst = 0f32;
    let mut bitwise = 0;
    for (a, b) in sequential.iter().zip(&concurrent) {
        assert_eq!(a.len(), b.len());
        worst = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(worst, f32::max);
        bitwise += usize::from(a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()));
    }
    eprintln!("64 episodes: {bitwise} bit-identical to their sequential runs, largest difference {worst:e}");
    // One libtorch thread on an AVX2 CPU: batching changes no bit (the acting forward's last layer,
    // LAST_ROWS). AVX-512 libtorch kernels depend on the batch size: measured 0 of 64 bit-identical,
    // largest difference 2.98e-7 (Intel Xeon, 2026-11-24), so there the bound is 1e-6.
    if pdt_testkit::cpu::batch_invariant() {
        assert_eq!(bitwise, 64, "largest difference {worst:e}");
    } else {
        assert!(worst <= pdt_testkit::cpu::BATCH_TOLERANCE, "largest difference {worst:e}");
    }
}

#[test]
fn bad_requests_get_clear_errors_and_the_server_keeps_serving() {
    let server =
        start(ServeOptions { max_episodes: 3, max_body_bytes: 4096, ..Default::default() });
    let addr = server.addr;
    // a slow client holding a half-sent request does not block anyone
    let mut slow = TcpStream::connect(addr).unwrap();
    write!(slow, "POST /v1/episodes HTTP/1.1\r\nContent-Length: 100\r\n\r\n{{\"ta").unwrap();
    let cases: Vec<(&str, String, u16, &str)> = vec![
        ("/v1/episodes", "{not json".into(), 400, ""),
        ("/v1/episodes", r#"{"task": 34, "observation": [0.0]}"#.into(), 400, "observation has 1 values, the policy takes 2"),
        ("/v1/episodes", r#"{"task": 34, "observation": [0.0, 1e39]}"#.into(), 400, "observation[1] = 1e39 is not a finite f32"),
        ("/v1/episodes", r#"{"task": 999, "observation": [0.0, 0.0]}"#.into(), 400, "task 999 is not one of the run's tasks"),
        ("/v1/episodes", r#"{"observation": [0.0, 0.0]}"#.into(), 400, "takes a prompt"),
        ("/v1/episodes", r#"{"task": 34, "observation": [0.0, 0.0], "colour": 1}"#.into(), 422, "colour"),
        ("/v1/episodes", r#"{"prompt": {"states": [[0.0, 0.0]], "actions": [[0.1]], "returns_to_go": [1.0], "timesteps": [3]}, "observation": [0.0, 0.0]}"#.into(), 400, "action 1"),
        ("/v1/episodes", r#"{"prompt": {"states": [[0.0, 0.0]], "actions": [[0.1, 0.1]], "returns_to_go": [1.0], "timesteps": [5000]}, "observation": [0.0, 0.0]}"#.into(), 400, "outside [0, 1000)"),
        ("/v1/episodes/77/step", r#"{"reward": 0.0, "observation": [0.0, 0.0]}"#.into(), 404, "no open episode 77"),
        ("/v1/episodes", format!(r#"{{"task": 34, "observation": [{}]}}"#, vec!["0.0"; 2000].join(",")), 413, ""),
        ("/v1/nowhere", "{}".into(), 404, "unknown route"),
        ("/v1/episodes/abc/step", r#"{"reward": 0.0, "observation": [0.0, 0.0]}"#.into(), 400, "episode id"),
    ];
    for (path, body, status, says) in &cases {
        let (got, reply) = http(addr, "POST", path, Some(body));
        assert_eq!(got, *status, "{path} {body:.80}: {reply}");
        let msg = reply["error"].as_str().unwrap_or("");
        assert!(msg.contains(says), "{path}: {msg}");
    }
    // too many episodes
    let open = r#"{"task": 34, "observation": [0.0, 0.0]}"#;
    let ids: Vec<u64> = (0..3)
        .map(|_| {
            let (s, r) = http(addr, "POST", "/v1/episodes", Some(open));
            assert_eq!(s, 201, "{r}");
            r["episode"].as_u64().unwrap()
        })
        .collect();
    let (s, r) = http(addr, "POST", "/v1/episodes", Some(open));
    assert_eq!(s, 429, "{r}");
    assert!(r["error"].as_str().unwrap().contains("--max-episodes"), "{r}");
    // a NaN-like reward and a wrong step body leave the episode usable
    let step = format!("/v1/episodes/{}/step", ids[0]);
    let (s, r) = http(addr, "POST", &step, Some(r#"{"reward": 1e300, "observation": [0.0, 0.0]}"#));
    assert_eq!(s, 400, "{r}");
    let (s, r) = http(addr, "POST", &step, Some(r#"{"reward": -0.5, "observation": [0.1, 0.0]}"#));
    assert_eq!(s, 200, "{r}");
    assert_eq!(r["t"], 1);
    for id in ids {
        assert_eq!(http(addr, "DELETE", &format!("/v1/episodes/{id}"), None).0, 204);
    }
    assert_eq!(http(addr, "DELETE", "/v1/episodes/1", None).0, 404);
    drop(slow);
}

#[test]
fn idle_episodes_are_closed() {
    let server =
        start(ServeOptions { idle_timeout: Duration::from_millis(300), ..Default::default() });
    let (s, r) = http(
        server.addr,
        "POST",
        "/v1/episodes",
        Some(r#"{"task": 34, "observation": [0.0, 0.0]}"#),
    );
    assert_eq!(s, 201, "{r}");
    std::thread::sleep(Duration::from_millis(1200));
    let id = r["episode"].as_u64().unwrap();
    let (s, r) = http(
        server.addr,
        "POST",
        &format!("/v1/episodes/{id}/step"),
        Some(r#"{"reward": 0.0, "observation": [0.0, 0.0]}"#),
    );
    assert_eq!(s, 404, "{r}");
}

#[test]
fn a_step_racing_the_delete_of_its_episode_gets_404_never_500() {
    // A 20 ms batch window: the step and the DELETE sent together land in one batch, in either
    // order. A step recorded before its episode closed in the same batch used to be answered
    // `500 "episode vanished"`, and so was every other episode of that forward;
    // now the close wins (404, as for any closed episode) and the others act.
    let server =
        start(ServeOptions { batch_wait: Duration::from_millis(20), ..Default::default() });
    let addr = server.addr;
    let open = r#"{"task": 34, "observation": [0.0, 0.0]}"#;
    let body = r#"{"reward": -0.5, "observation": [0.1, 0.0]}"#;
    let (s, r) = http(addr, "POST", "/v1/episodes", Some(open));
    assert_eq!(s, 201, "{r}");
    let bystander = format!("/v1/episodes/{}/step", r["episode"]);
    let mut answers = std::collections::BTreeMap::<u16, usize>::new();
    for round in 1..=40u64 {
        let (s, r) = http(addr, "POST", "/v1/episodes", Some(open));
        assert_eq!(s, 201, "{r}");
        let id = r["episode"].as_u64().unwrap();
        let ((step, step_reply), delete, (other, other_reply)) = std::thread::scope(|sc| {
            let step =
                sc.spawn(|| http(addr, "POST", &format!("/v1/episodes/{id}/step"), Some(body)));
            let delete = sc.spawn(|| http(addr, "DELETE", &format!("/v1/episodes/{id}"), None).0);
            let other = sc.spawn(|| http(addr, "POST", &bystander, Some(body)));
            (step.join().unwrap(), delete.join().unwrap(), other.join().unwrap())
        });
        *answers.entry(step).or_default() += 1;
        assert!(step == 200 || step == 404, "round {round}: step {step} {step_reply}");
        if step == 404 {
            let msg = step_reply["error"].as_str().unwrap();
            assert!(msg.contains(&format!("no open episode {id}")), "{msg}");
        }
        assert_eq!(delete, 204, "round {round}");
        // The other episode of the batch acted, and counted its step once.
        assert_eq!((other, other_reply["t"].as_u64()), (200, Some(round)), "{other_reply}");
    }
    eprintln!("steps racing their DELETE: {answers:?} (status: count)");
    // The race was run: some steps met their closed episode.
    assert!(answers.get(&404).is_some_and(|&n| n > 0), "{answers:?}");
}
