//! Random request bodies through the real server on loopback: wrong types, missing and unknown
//! fields, finite extremes (±3e38, 1e30, 1e-45, f32::MAX and just beyond), huge arrays. Every reply
//! is a finite action or a 4xx whose error names the field at fault; a refused step leaves its
//! episode usable (the next good step acts, at the next t); the server keeps answering.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_serve::ServeOptions;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use serde_json::{json, Map, Value};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

use crate::support;
use support::{http, start};

/// One request with a body that may be large: the server may refuse it (413) and close before
/// all of it is sent, so a failed write or a reset is read as "closed" (status 0) for the caller
/// to judge.
fn send(addr: SocketAddr, path: &str, body: &str) -> (u16, Value) {
    if body.len() < 64 << 10 {
        return http(addr, "POST", path, Some(body));
    }
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    let _ = s.write_all(head.as_bytes()).and_then(|()| s.write_all(body.as_bytes()));
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    let out = String::from_utf8_lossy(&out);
    let status = out.split(' ').nth(1).and_then(|x| x.parse().ok()).unwrap_or(0);
    let payload = out.split("\r\n\r\n").nth(1).unwrap_or("");
    (status, serde_json::from_str(payload).unwrap_or(Value::Null))
}

/// What an error may name: a field of a request, or the body as a whole.
const FIELDS: &[&str] = &[
    "observation",
    "reward",
    "target_return",
    "task",
    "prompt",
    "prompt_seed",
    "states",
    "actions",
    "returns_to_go",
    "timesteps",
    "colour",
    "--max-body-bytes",
];

const EXTREMES: &[f64] = &[
    0.0,
    -0.0,
    1.0,
    -1.0,
    3e38,
    -3e38,
    1e30,
    -1e30,
    1e-45,
    -1e-45,
    5e-324,
    3.4028235e38,
    -3.4028235e38,
    3.5e38,
    1e39,
    1e308,
    -1e308,
    1e15,
    -1e20,
];

/// Stand-ins for arrays of 100,000 and 300,000 values (under and over the 1 MiB body limit),
/// written out only when the body is sent, so that a failing case prints short.
const HUGE: &str = "HUGE-ARRAY-100000";
const BIGGER: &str = "HUGE-ARRAY-300000";

/// The body as sent: the stand-ins replaced by their arrays.
fn body_text(body: &Value) -> String {
    let array = |n: usize| format!("[{}]", vec!["1e30"; n].join(","));
    body.to_string()
        .replace(&format!("\"{HUGE}\""), &array(100_000))
        .replace(&format!("\"{BIGGER}\""), &array(300_000))
}

fn number() -> impl Strategy<Value = Value> {
    prop_oneof![
        3 => prop::sample::select(EXTREMES).prop_map(|x| json!(x)),
        3 => (-2.0f64..2.0).prop_map(|x| json!(x)),
        1 => any::<f64>().prop_filter("JSON numbers are finite", |x| x.is_finite()).prop_map(|x| json!(x)),
        1 => any::<i64>().prop_map(|x| json!(x)),
    ]
}

fn junk() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        "[a-z0-9]{0,6}".prop_map(Value::String),
        Just(json!({})),
        Just(json!([[1.0]])),
    ]
}

fn value() -> impl Strategy<Value = Value> {
    prop_oneof![8 => number(), 1 => junk()]
}

/// Mostly two values (the point robot's sizes), sometimes another count, rarely a huge array.
fn vector() -> impl Strategy<Value = Value> {
    prop_oneof![
        8 => prop::collection::vec(value(), 2..=2).prop_map(Value::Array),
        2 => prop::collection::vec(value(), 0..5).prop_map(Value::Array),
        1 => junk(),
        1 => prop::sample::select(vec![HUGE, BIGGER]).prop_map(|m| json!(m)),
    ]
}

fn prompt() -> impl Strategy<Value = Value> {
    (1usize..4).prop_flat_map(|n| {
        (
            prop::collection::vec(vector(), n..=n),
            prop::collection::vec(vector(), n..=n),
            prop::collection::vec(value(), n..=n),
            prop::collection::vec(prop_oneof![4 => 0i64..1000, 1 => any::<i64>()], n..=n),
        )
            .prop_map(|(s, a, r, t)| {
                json!({"states": s, "actions": a, "returns_to_go": r, "timesteps": t})
            })
    })
}

fn object(fields: Vec<(&str, Option<Value>)>) -> Value {
    let mut m = Map::new();
    for (k, v) in fields {
        if let Some(v) = v {
            m.insert(k.to_string(), v);
        }
    }
    Value::Object(m)
}

fn open_body() -> impl Strategy<Value = Value> {
    let task = prop_oneof![
        4 => prop::sample::select(vec![2u64, 10, 18, 26, 34]).prop_map(|t| json!(t)),
        1 => any::<i64>().prop_map(|t| json!(t)),
        1 => junk(),
    ];
    (
        prop::option::weighted(0.9, vector()),
        prop::option::weighted(0.5, task),
        prop::option::weighted(0.4, prompt()),
        prop::option::weighted(0.2, prop_oneof![any::<u64>().prop_map(|s| json!(s)), value()]),
        prop::option::weighted(0.4, value()),
        prop::option::weighted(0.05, value()),
    )
        .prop_map(|(obs, task, prompt, seed, target, extra)| {
            object(vec![
                ("observation", obs),
                ("task", task),
                ("prompt", prompt),
                ("prompt_seed", seed),
                ("target_return", target),
                ("colour", extra),
            ])
        })
}

fn step_body() -> impl Strategy<Value = Value> {
    (
        prop::option::weighted(0.95, value()),
        prop::option::weighted(0.95, vector()),
        prop::option::weighted(0.05, value()),
    )
        .prop_map(|(reward, obs, extra)| {
            object(vec![("reward", reward), ("observation", obs), ("colour", extra)])
        })
}

/// A reply is a finite action of `act_dim` values (`2xx`) or a 4xx naming a field.
fn check(
    what: &str,
    body: &Value,
    status: u16,
    reply: &Value,
    ok: u16,
) -> Result<bool, TestCaseError> {
    let text = body.to_string();
    let shown = &text[..text.len().min(300)];
    if status == 0 {
        // Closed without a reply: only for a body over the limit, refused before it was all sent.
        prop_assert!(body_text(body).len() > 1 << 20, "{what} {shown}: no reply");
        return Ok(false);
    }
    if status == ok {
        let action = reply["action"].as_array().cloned().unwrap_or_default();
        let finite = action.iter().all(|x| x.as_f64().is_some_and(f64::is_finite));
        prop_assert!(action.len() == 2 && finite, "{what} {shown}: {status} {reply}");
        return Ok(true);
    }
    prop_assert!((400..500).contains(&status), "{what} {shown}: {status} {reply}");
    prop_assert!(status != 429, "{what}: episodes leak: {reply}");
    let msg = reply["error"].as_str().unwrap_or("");
    prop_assert!(
        FIELDS.iter().any(|f| msg.contains(f)),
        "{what} {shown}: {status}, the error names no field: {msg}"
    );
    Ok(false)
}

fn good_step(addr: SocketAddr, id: u64, t: u64) -> Result<(), TestCaseError> {
    let (s, r) = http(
        addr,
        "POST",
        &format!("/v1/episodes/{id}/step"),
        Some(r#"{"reward": -0.5, "observation": [0.1, -0.2]}"#),
    );
    let finite = r["action"]
        .as_array()
        .is_some_and(|a| a.len() == 2 && a.iter().all(|x| x.as_f64().is_some_and(f64::is_finite)));
    prop_assert!(s == 200 && finite && r["t"] == t, "a good step after a refused one: {s} {r}");
    Ok(())
}

/// One case: a random open, then a sane episode taking random steps, each followed by a good
/// step. The episodes it opens go to `opened`.
fn case(
    addr: SocketAddr,
    open: &Value,
    steps: &[Value],
    opened: &mut Vec<u64>,
) -> Result<(), TestCaseError> {
    let (s, r) = send(addr, "/v1/episodes", &body_text(open));
    opened.extend(r["episode"].as_u64().filter(|_| s == 201));
    check("open", open, s, &r, 201)?;
    let (s, r) =
        http(addr, "POST", "/v1/episodes", Some(r#"{"task": 34, "observation": [0.0, 0.0]}"#));
    prop_assert_eq!(s, 201, "{}", r);
    let id = r["episode"].as_u64().unwrap();
    opened.push(id);
    let mut t = 0;
    for step in steps {
        let (s, r) = send(addr, &format!("/v1/episodes/{id}/step"), &body_text(step));
        if check("step", step, s, &r, 200)? {
            t += 1;
            prop_assert_eq!(&r["t"], &json!(t));
        }
        t += 1;
        good_step(addr, id, t)?;
    }
    Ok(())
}

#[test]
fn random_requests_get_finite_actions_or_errors_naming_a_field() {
    let server = start(ServeOptions { max_episodes: 8, threads: 1, ..Default::default() });
    let addr = server.addr;
    // 160 cases of about ten requests each: a few seconds on two cores.
    let mut runner = TestRunner::new(Config {
        cases: 160,
        failure_persistence: None,
        max_shrink_iters: 64,
        ..Config::default()
    });
    let bodies = (open_body(), prop::collection::vec(step_body(), 1..4));
    runner
        .run(&bodies, |(open, steps)| {
            let mut opened = Vec::new();
            let result = case(addr, &open, &steps, &mut opened);
            // Closed whatever happened, so that a failing case (and its shrinking) leaves no
            // episode behind to fail the next with 429.
            for id in opened {
                let _ = http(addr, "DELETE", &format!("/v1/episodes/{id}"), None);
            }
            result?;
            let (s, r) = http(addr, "GET", "/v1/info", None);
            prop_assert!(s == 200 && r["open_episodes"] == 0, "{s} {r}");
            Ok(())
        })
        .unwrap();
}
