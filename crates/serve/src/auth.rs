//! Who may use the server (docs/serve.md, "Authentication").
//!
//! On a loopback address the server needs no token (only this machine reaches it); on any other
//! address it needs one, or an explicit [`Auth::Disabled`] (`promptdt serve --no-auth`), because
//! whoever reaches the port can open episodes and use the model's compute. A token is sent as
//! `Authorization: Bearer <token>` on every request but `GET /v1/health`. Only its SHA-256 digest
//! is kept, and a presented token is compared digest to digest in constant time: the comparison
//! takes as long whatever the presented token is, so its timing tells nothing about the token.

use axum::extract::{Request, State};
use axum::http::{header, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use std::io::Read;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;

use crate::{ApiError, ServeError};

/// The environment variable a token may be read from (`promptdt serve`).
pub const TOKEN_ENV: &str = "PROMPTDT_SERVE_TOKEN";

/// The shortest token accepted: a shorter one could be guessed.
pub const MIN_TOKEN_CHARS: usize = 16;

/// The one path open without a token (for load balancers and orchestrators).
pub const HEALTH_PATH: &str = "/v1/health";

/// A bearer token. Only its digest is kept; `Debug` does not show it.
#[derive(Clone)]
pub struct Token {
    digest: [u8; 32],
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(..)")
    }
}

impl Token {
    /// `secret` as a token; `from` names where it came from, for the error (`token file
    /// /etc/pdt/token`). Surrounding whitespace (a file's final newline) is not part of it.
    pub fn new(secret: &str, from: &str) -> Result<Self, ServeError> {
        let bad = |why: String| Err(ServeError::Token { from: from.to_string(), why });
        let secret = secret.trim();
        if secret.is_empty() {
            return bad("it is empty".into());
        }
        // What a client can send in an `Authorization` header as one word.
        if let Some(c) = secret.chars().find(|c| !c.is_ascii_graphic()) {
            return bad(format!(
                "it holds {c:?}; a token is printable ASCII without spaces (e.g. the output of \
                 `openssl rand -hex 32`)"
            ));
        }
        if secret.len() < MIN_TOKEN_CHARS {
            return bad(format!(
                "it has {} characters, too few to be hard to guess; use at least \
                 {MIN_TOKEN_CHARS} (e.g. the output of `openssl rand -hex 32`)",
                secret.len()
            ));
        }
        Ok(Self { digest: Sha256::digest(secret.as_bytes()).into() })
    }

    /// The token held by the file at `path` (its first line is not special: the whole file,
    /// less surrounding whitespace, is the token).
    pub fn from_file(path: &Path) -> Result<Self, ServeError> {
        let from = format!("token file {} (--token-file)", path.display());
        let text = std::fs::read_to_string(path)
            .map_err(|e| ServeError::Token { from: from.clone(), why: e.to_string() })?;
        Self::new(&text, &from)
    }

    /// The token in the environment variable `var`, or `None` when it is not set.
    pub fn from_env(var: &str) -> Result<Option<Self>, ServeError> {
        match std::env::var(var) {
            Ok(v) => Self::new(&v, &format!("environment variable {var}")).map(Some),
            Err(std::env::VarError::NotPresent) => Ok(None),
            Err(std::env::VarError::NotUnicode(_)) => Err(ServeError::Token {
                from: format!("environment variable {var}"),
                why: "it is not UTF-8".into(),
            }),
        }
    }

    /// A new random token (32 bytes from the operating system's generator, as 64 hex
    /// characters) and its text, to be shown once.
    pub fn generate() -> Result<(Self, String), ServeError> {
        let mut bytes = [0u8; 32];
        std::fs::File::open("/dev/urandom").and_then(|mut f| f.read_exact(&mut bytes)).map_err(
            |e| ServeError::Token {
                from: "a generated token (--generate-token)".into(),
                why: format!("/dev/urandom: {e}"),
            },
        )?;
        let text: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        Ok((Self::new(&text, "a generated token")?, text))
    }

    /// Whether `presented` is this token. Digests are compared in full, every byte, so the time
    /// taken does not depend on where they first differ (nor on the presented token's length).
    pub fn matches(&self, presented: &[u8]) -> bool {
        let other: [u8; 32] = Sha256::digest(presented).into();
        let diff = self.digest.iter().zip(&other).fold(0u8, |acc, (a, b)| acc | (a ^ b));
        // black_box: keep the fold a fold, not an early exit.
        std::hint::black_box(diff) == 0
    }
}

/// Who may use the server.
#[derive(Debug, Clone, Default)]
pub enum Auth {
    /// No token: a loopback address only (the default); any other address is refused at start.
    #[default]
    LoopbackOnly,
    /// Every request but `GET /v1/health` carries `Authorization: Bearer <token>`, on any
    /// address (loopback too).
    Token(Token),
    /// No authentication on any address (`--no-auth`): for a server behind something else that
    /// authenticates. On an address other than loopback the server says so at start
    /// ([`exposure_warning`]).
    Disabled,
}

/// Whether `addr` reaches this machine only (`127.0.0.0/8`, `::1`, `::ffff:127.x.y.z`).
pub fn is_loopback(addr: &SocketAddr) -> bool {
    addr.ip().to_canonical().is_loopback()
}

/// Refuses to serve `addr` without authentication unless it is loopback or `auth` disables it
/// explicitly; says how to give a token.
pub fn check(addr: &SocketAddr, auth: &Auth) -> Result<(), ServeError> {
    match auth {
        Auth::LoopbackOnly if !is_loopback(addr) => Err(ServeError::Unauthenticated(*addr)),
        _ => Ok(()),
    }
}

/// The warning line of a server that runs without authentication where others can reach it.
pub fn exposure_warning(addr: &SocketAddr, auth: &Auth) -> Option<String> {
    (matches!(auth, Auth::Disabled) && !is_loopback(addr)).then(|| {
        format!(
            "warning: serving on {addr} without authentication (--no-auth): anyone who can reach \
             this port can open episodes and use the model's compute"
        )
    })
}

/// Answers 401 to a request without the right bearer token (before its body is read), except
/// `GET /v1/health`.
pub(crate) async fn require_token(
    State(token): State<Arc<Token>>,
    req: Request,
    next: Next,
) -> Response {
    if req.method() == Method::GET && req.uri().path() == HEALTH_PATH {
        return next.run(req).await;
    }
    let presented = req.headers().get(header::AUTHORIZATION).map(|v| bearer(v.as_bytes()));
    match presented {
        Some(Some(t)) if token.matches(t) => next.run(req).await,
        Some(Some(_)) => unauthorized(
            r#"Bearer realm="promptdt", error="invalid_token""#,
            "the bearer token is not this server's",
        ),
        Some(None) => unauthorized(
            r#"Bearer realm="promptdt", error="invalid_request""#,
            "the Authorization header is not `Bearer <token>`",
        ),
        None => unauthorized(
            r#"Bearer realm="promptdt""#,
            "this server needs a token: send `Authorization: Bearer <token>` (docs/serve.md, \
             Authentication)",
        ),
    }
}

/// The token of an `Authorization: Bearer <token>` value (the scheme in any case), or `None`.
fn bearer(value: &[u8]) -> Option<&[u8]> {
    let value = value.trim_ascii();
    let (scheme, rest) = value.split_at_checked(6)?;
    let token = rest.trim_ascii_start();
    let spaced = rest.first().is_some_and(|c| *c == b' ' || *c == b'\t');
    (scheme.eq_ignore_ascii_case(b"bearer") && spaced && !token.is_empty()).then_some(token)
}

fn unauthorized(challenge: &'static str, message: &str) -> Response {
    let mut r = ApiError::new(StatusCode::UNAUTHORIZED, message).into_response();
    r.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static(challenge));
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_are_checked_and_matched_by_digest() {
        let t = Token::new("0123456789abcdef\n", "test").unwrap_or_else(|e| panic!("{e}"));
        assert!(t.matches(b"0123456789abcdef"));
        assert!(!t.matches(b"0123456789abcdeF"));
        assert!(!t.matches(b"0123456789abcdef0"));
        assert!(!t.matches(b""));
        for (bad, says) in [("", "empty"), ("short", "too few"), ("0123456789 abcdef", "' '")] {
            let e = Token::new(bad, "token file x").map(|_| ()).unwrap_err().to_string();
            assert!(e.contains("token file x") && e.contains(says), "{bad:?}: {e}");
        }
        assert_eq!(format!("{t:?}"), "Token(..)");
    }

    #[test]
    fn bearer_values_are_parsed() {
        assert_eq!(bearer(b"Bearer abc"), Some(&b"abc"[..]));
        assert_eq!(bearer(b"bearer   abc "), Some(&b"abc"[..]));
        assert_eq!(bearer(b"Bearerabc"), None);
        assert_eq!(bearer(b"Basic abc"), None);
        assert_eq!(bearer(b"Bearer "), None);
    }
}
