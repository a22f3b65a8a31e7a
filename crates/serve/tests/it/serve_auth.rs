//! Authentication of `promptdt serve` (docs/serve.md, "Authentication"), over
//! the wire: a server with a token answers 401 to a request without it or with a wrong one, on
//! every endpoint but the health check, and serves with the right one; an address other than
//! loopback is refused without a token or an explicit `Auth::Disabled`. Addresses other than
//! loopback are only bound as 0.0.0.0 on port 0, and reached through 127.0.0.1: no test sends
//! anything off this machine.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_policy::Policy;
use pdt_serve::{Auth, ServeError, ServeOptions, Server, Token};
use std::net::SocketAddr;

use crate::support;
use support::{http_with, start, tiny_run};

const SECRET: &str = "pdt-test-token-0123456789abcdef";

fn bearer(t: &str) -> String {
    format!("Authorization: Bearer {t}")
}

fn token() -> Token {
    Token::new(SECRET, "test").unwrap()
}

#[test]
fn a_token_server_answers_401_without_the_right_token_and_serves_with_it() {
    let server = start(ServeOptions { auth: Auth::Token(token()), ..Default::default() });
    let addr = server.addr;
    let right = bearer(SECRET);
    let open = r#"{"task": 34, "observation": [0.0, 0.0]}"#;
    // The health check is open.
    let (s, _, r) = http_with(addr, "GET", "/v1/health", None, &[]);
    assert_eq!((s, r["status"].as_str()), (200, Some("ok")), "{r}");
    // Without a token, with a wrong one, or with one that is not a bearer token: 401 with a
    // challenge and a JSON error, on every endpoint (an unknown route too: it says nothing of
    // which routes exist), and nothing is opened.
    let wrong = [
        (vec![], "needs a token"),
        (vec![bearer("pdt-test-token-0123456789abcdeF")], "not this server's"),
        (vec![bearer(&SECRET[..SECRET.len() - 1])], "not this server's"),
        (vec![bearer(&format!("{SECRET}0"))], "not this server's"),
        (vec![format!("Authorization: Basic {SECRET}")], "not `Bearer <token>`"),
        (vec![format!("Authorization: {SECRET}")], "not `Bearer <token>`"),
    ];
    let requests = [
        ("GET", "/v1/info", None),
        ("POST", "/v1/episodes", Some(open)),
        ("POST", "/v1/episodes/1/step", Some(r#"{"reward": 0.0, "observation": [0.0, 0.0]}"#)),
        ("DELETE", "/v1/episodes/1", None),
        ("GET", "/v1/nowhere", None),
        ("POST", "/v1/health", None),
    ];
    for (headers, says) in &wrong {
        let headers: Vec<&str> = headers.iter().map(String::as_str).collect();
        for (method, path, body) in requests {
            let (s, head, r) = http_with(addr, method, path, body, &headers);
            assert_eq!(s, 401, "{method} {path} {headers:?}: {r}");
            assert!(head.contains("www-authenticate: bearer"), "{head}");
            let msg = r["error"].as_str().unwrap_or_default();
            assert!(msg.contains(says), "{method} {path} {headers:?}: {msg}");
        }
    }
    // With the right token (the scheme in any case) it serves as usual.
    let (s, _, info) = http_with(addr, "GET", "/v1/info", None, &[&right]);
    assert_eq!(s, 200, "{info}");
    assert_eq!(info["open_episodes"], 0, "a refused request opened an episode: {info}");
    let (s, _, r) = http_with(addr, "POST", "/v1/episodes", Some(open), &[&right]);
    assert_eq!(s, 201, "{r}");
    let id = r["episode"].as_u64().unwrap();
    let step = format!("/v1/episodes/{id}/step");
    let lower = format!("Authorization: bearer {SECRET}");
    let body = r#"{"reward": -0.5, "observation": [0.1, 0.0]}"#;
    let (s, _, r) = http_with(addr, "POST", &step, Some(body), &[&lower]);
    assert_eq!((s, r["t"].as_u64()), (200, Some(1)), "{r}");
    let (s, _, r) = http_with(addr, "GET", "/v1/nowhere", None, &[&right]);
    assert_eq!(s, 404, "{r}");
    let (s, _, r) = http_with(addr, "DELETE", &format!("/v1/episodes/{id}"), None, &[&right]);
    assert_eq!(s, 204, "{r}");
}

#[test]
fn an_address_other_than_loopback_needs_a_token_or_disabled_auth() {
    let any: SocketAddr = "0.0.0.0:0".parse().unwrap();
    let run = || Policy::load(&tiny_run().1, None, None).unwrap();
    // Refused without a token: before anything is bound.
    let e = match Server::start(run(), ServeOptions { listen: any, ..Default::default() }) {
        Ok(_) => panic!("served 0.0.0.0 without authentication"),
        Err(e) => e,
    };
    assert!(matches!(e, ServeError::Unauthenticated(_)), "{e}");
    let msg = e.to_string();
    for says in ["0.0.0.0:0", "--token-file", "PROMPTDT_SERVE_TOKEN", "--no-auth"] {
        assert!(msg.contains(says), "{says}: {msg}");
    }
    assert!(pdt_serve::auth::check(&"[::]:0".parse().unwrap(), &Auth::LoopbackOnly).is_err());
    assert!(pdt_serve::auth::check(&"[::1]:0".parse().unwrap(), &Auth::LoopbackOnly).is_ok());
    // With a token it serves, and asks for the token (reached through loopback).
    let opts = ServeOptions { listen: any, auth: Auth::Token(token()), ..Default::default() };
    let server = Server::start(run(), opts).unwrap();
    let local = SocketAddr::from(([127, 0, 0, 1], server.addr.port()));
    assert_eq!(http_with(local, "GET", "/v1/info", None, &[]).0, 401);
    assert_eq!(http_with(local, "GET", "/v1/info", None, &[&bearer(SECRET)]).0, 200);
    drop(server);
    // Disabled explicitly, it serves without a token, and there is a warning to print.
    let opts = ServeOptions { listen: any, auth: Auth::Disabled, ..Default::default() };
    let warning = pdt_serve::auth::exposure_warning(&opts.listen, &opts.auth).unwrap();
    assert!(warning.contains("without authentication"), "{warning}");
    let server = Server::start(run(), opts).unwrap();
    let local = SocketAddr::from(([127, 0, 0, 1], server.addr.port()));
    assert_eq!(http_with(local, "GET", "/v1/info", None, &[]).0, 200);
    // On loopback the default needs no token and warns of nothing: as before.
    let loopback: SocketAddr = "127.0.0.1:0".parse().unwrap();
    assert!(pdt_serve::auth::exposure_warning(&loopback, &Auth::Disabled).is_none());
    let server = start(ServeOptions::default());
    assert_eq!(http_with(server.addr, "GET", "/v1/info", None, &[]).0, 200);
}
