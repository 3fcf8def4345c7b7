//! Who may do what: the trust boundary of the HTTP API.
//!
//! | access  | endpoints | needs |
//! |---|---|---|
//! | public  | `/healthz`, `/v1/openapi.json`, the dashboard's files | nothing |
//! | read    | runs, state, live, timeline, series, trajectories, truth, evaluation, export, models, `/metrics` | the read or admin token when reads are protected (`read_access`: by default when the server is not on a loopback address) |
//! | admin   | create, end, delete and re-run runs, upload truth | the admin token, when one is configured |
//! | enroll  | register a robot | the admin token or the run's enrollment token (created with the run), when an admin token is configured |
//! | robot   | post records | the robot's own token (from its registration); records of other robots are refused |
//!
//! Tokens travel as `Authorization: Bearer <token>` (the scheme in any case); a browser's
//! websocket, which cannot set headers, may send the read token as `?access_token=`, which is
//! removed from the request before it goes further. Tokens are compared through their
//! SHA-256 digests in constant time. State-changing requests with a body must be JSON (415
//! otherwise), and requests that carry an `Origin` header (web pages) may change state or
//! open the live websocket only from an allowed origin (403 otherwise), so that a page in
//! the operator's browser cannot drive a local server. The policy table is [`policy`]; a
//! route missing from it is refused (a unit test checks every route is listed).

use crate::app::AppState;
use crate::error::ApiError;
use axum::extract::{MatchedPath, Request, State};
use axum::http::{HeaderMap, Method, Uri, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

/// The shortest token accepted as an admin or read token.
pub const MIN_TOKEN_LEN: usize = 16;

/// The query parameter a browser may carry the read token in (websockets cannot set headers).
pub const TOKEN_QUERY_PARAM: &str = "access_token";

/// Who may read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ReadAccess {
    /// Anyone when the server listens on a loopback address; a token otherwise.
    #[default]
    Auto,
    /// Always the read or admin token.
    Token,
    /// Anyone (only behind a proxy that authenticates).
    Open,
}

/// The server's credentials and origin allow-list.
#[derive(Debug, Clone, Default)]
pub struct AuthConfig {
    pub admin_token: Option<String>,
    pub read_token: Option<String>,
    pub read_access: ReadAccess,
    /// Normalised origins (`scheme://host:port`) allowed besides the server's own.
    pub allowed_origins: Vec<String>,
    /// The server listens on a loopback address only.
    pub loopback: bool,
}

impl AuthConfig {
    /// Whether reads need a token.
    pub fn reads_need_token(&self) -> bool {
        match self.read_access {
            ReadAccess::Auto => !self.loopback,
            ReadAccess::Token => true,
            ReadAccess::Open => false,
        }
    }
}

/// What a route needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    Public,
    Read,
    Admin,
    /// Admin or the run's enrollment token (checked by the handler, which knows the run).
    Enroll,
    /// A robot's token (checked by the handler, which knows the robots).
    Robot,
}

/// The access a (method, route pattern) needs; `None` for a route this table does not list
/// (refused), `Some(None)` for a listed route without that method (axum answers 405).
pub fn policy(method: &Method, route: &str) -> Option<Option<Access>> {
    use Access::*;
    let m =
        |get: Option<Access>, post: Option<Access>, put: Option<Access>, del: Option<Access>| {
            Some(match *method {
                Method::GET | Method::HEAD => get,
                Method::POST => post,
                Method::PUT => put,
                Method::DELETE => del,
                _ => None,
            })
        };
    match route {
        "/healthz" | "/v1/openapi.json" => m(Some(Public), None, None, None),
        "/metrics" | "/v1/models" => m(Some(Read), None, None, None),
        "/v1/runs" => m(Some(Read), Some(Admin), None, None),
        "/v1/runs/{run}" => m(Some(Read), None, None, Some(Admin)),
        "/v1/runs/{run}/end" | "/v1/runs/{run}/rerun" => m(None, Some(Admin), None, None),
        "/v1/runs/{run}/robots" => m(None, Some(Enroll), None, None),
        "/v1/runs/{run}/observations" => m(None, Some(Robot), None, None),
        "/v1/runs/{run}/truth" => m(Some(Read), None, Some(Admin), None),
        "/v1/runs/{run}/state"
        | "/v1/runs/{run}/live"
        | "/v1/runs/{run}/timeline"
        | "/v1/runs/{run}/series"
        | "/v1/runs/{run}/trajectories"
        | "/v1/runs/{run}/evaluation"
        | "/v1/runs/{run}/export" => m(Some(Read), None, None, None),
        _ => None,
    }
}

/// SHA-256 of a token, hex.
pub fn token_hash(token: &str) -> String {
    hex::encode(Sha256::digest(token.as_bytes()))
}

/// Whether `given` equals `expected`, in time independent of where they differ.
pub fn token_eq(given: &str, expected: &str) -> bool {
    let a = Sha256::digest(given.as_bytes());
    let b = Sha256::digest(expected.as_bytes());
    a.ct_eq(&b).into()
}

/// Whether the sha256 hex `hash` is that of `given`, in constant time.
pub fn hash_matches(given: &str, hash: &str) -> bool {
    token_hash(given).as_bytes().ct_eq(hash.as_bytes()).into()
}

/// The bearer token of a request: `Authorization: Bearer <token>`, the scheme in any case.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    let v = headers.get(header::AUTHORIZATION)?.to_str().ok()?.trim();
    let (scheme, token) = v.split_once(char::is_whitespace)?;
    scheme
        .eq_ignore_ascii_case("bearer")
        .then(|| token.trim())
        .filter(|t| !t.is_empty())
}

/// Whether the request carries the admin token (always true when none is configured).
pub fn is_admin(cfg: &AuthConfig, headers: &HeaderMap) -> bool {
    match &cfg.admin_token {
        None => true,
        Some(t) => bearer(headers).is_some_and(|b| token_eq(b, t)),
    }
}

/// 401 unless the request carries the admin token (when one is configured).
pub fn check_admin(cfg: &AuthConfig, headers: &HeaderMap) -> Result<(), ApiError> {
    if is_admin(cfg, headers) {
        Ok(())
    } else {
        Err(ApiError::Unauthorized(
            "this action needs the admin token: send `Authorization: Bearer <admin token>`".into(),
        ))
    }
}

fn check_read(cfg: &AuthConfig, headers: &HeaderMap) -> Result<(), ApiError> {
    if !cfg.reads_need_token() {
        return Ok(());
    }
    let ok = bearer(headers).is_some_and(|b| {
        // Both compared, so the time does not tell which one matched.
        let admin = cfg.admin_token.as_deref().is_some_and(|t| token_eq(b, t));
        let read = cfg.read_token.as_deref().is_some_and(|t| token_eq(b, t));
        admin | read
    });
    if ok {
        Ok(())
    } else {
        Err(ApiError::Unauthorized(
            "reading this server needs the read token: send `Authorization: Bearer <read token>` \
             (or `?access_token=` on the live websocket)"
                .into(),
        ))
    }
}

/// Normalises an origin (`scheme://host[:port]`, lower case, default port dropped).
pub fn parse_origin(o: &str) -> Result<String, String> {
    let uri: Uri = o
        .parse()
        .map_err(|e| format!("{o:?} is not an origin (scheme://host[:port]): {e}"))?;
    let (Some(scheme), Some(auth)) = (uri.scheme_str(), uri.authority()) else {
        return Err(format!("{o:?} is not an origin (scheme://host[:port])"));
    };
    if uri.path() != "/" && !uri.path().is_empty() || uri.query().is_some() {
        return Err(format!(
            "{o:?} has a path: an origin is scheme://host[:port]"
        ));
    }
    let scheme = scheme.to_ascii_lowercase();
    let host = auth.host().to_ascii_lowercase();
    let port = match (scheme.as_str(), auth.port_u16()) {
        ("http", Some(80)) | ("https", Some(443)) | (_, None) => String::new(),
        (_, Some(p)) => format!(":{p}"),
    };
    Ok(format!("{scheme}://{host}{port}"))
}

fn is_loopback_host(host: &str) -> bool {
    let h = host.trim_start_matches('[').trim_end_matches(']');
    h.eq_ignore_ascii_case("localhost")
        || h.parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// Whether a page of `origin` may act on this server: an allowed origin, or the server's
/// own origin (the `Host` the request was sent to). On a loopback server its own origin must
/// be a loopback name, so that a site that rebinds its DNS name to 127.0.0.1 is refused.
fn origin_allowed(cfg: &AuthConfig, origin: &str, host: Option<&str>) -> bool {
    let Ok(o) = parse_origin(origin) else {
        return false;
    };
    if cfg.allowed_origins.contains(&o) {
        return true;
    }
    let Some(host) = host else { return false };
    let authority = o.split_once("://").map_or("", |(_, a)| a);
    let same = authority.eq_ignore_ascii_case(host)
        || parse_origin(&format!("http://{host}")).is_ok_and(|h| h == o);
    let o_host = authority
        .rsplit_once(':')
        .filter(|(_, p)| p.chars().all(|c| c.is_ascii_digit()))
        .map_or(authority, |(h, _)| h);
    same && (!cfg.loopback || is_loopback_host(o_host))
}

fn is_json(ct: &str, ndjson_too: bool) -> bool {
    let mime = ct
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    mime == "application/json"
        || (mime.starts_with("application/") && mime.ends_with("+json"))
        || (ndjson_too && (mime == "application/x-ndjson" || mime == "application/jsonl"))
}

fn has_body(headers: &HeaderMap) -> bool {
    headers.contains_key(header::TRANSFER_ENCODING)
        || headers
            .get(header::CONTENT_LENGTH)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse::<u64>().ok())
            .is_some_and(|n| n > 0)
}

/// Moves `?access_token=` of a GET into the `Authorization` header.
fn token_from_query(req: &mut Request) {
    let Some(q) = req.uri().query() else { return };
    let mut token = None;
    let rest: Vec<&str> = q
        .split('&')
        .filter(|kv| match kv.split_once('=') {
            Some((k, v)) if k == TOKEN_QUERY_PARAM => {
                token = Some(v.to_string());
                false
            }
            _ => true,
        })
        .collect();
    let Some(token) = token else { return };
    let path = req.uri().path();
    let pq = if rest.is_empty() {
        path.to_string()
    } else {
        format!("{path}?{}", rest.join("&"))
    };
    let mut parts = req.uri().clone().into_parts();
    let Ok(pq) = pq.parse() else { return };
    parts.path_and_query = Some(pq);
    if let Ok(uri) = Uri::from_parts(parts) {
        *req.uri_mut() = uri;
    }
    if !req.headers().contains_key(header::AUTHORIZATION)
        && let Ok(v) = format!("Bearer {token}").parse()
    {
        req.headers_mut().insert(header::AUTHORIZATION, v);
    }
}

/// The middleware that enforces [`policy`], the origin allow-list and JSON bodies.
pub async fn authorize(State(state): State<AppState>, mut req: Request, next: Next) -> Response {
    match check(&state, &mut req) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

fn check(state: &AppState, req: &mut Request) -> Result<(), ApiError> {
    let cfg = &state.config.auth;
    let method = req.method().clone();
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_string());
    let Some(route) = route else {
        // The dashboard's files (or nothing): public, read-only.
        return Ok(());
    };
    let access = match policy(&method, &route) {
        None => {
            return Err(ApiError::Forbidden(format!(
                "{route} has no access rule; refused"
            )));
        }
        // axum answers 405 Method Not Allowed.
        Some(None) => return Ok(()),
        Some(Some(a)) => a,
    };
    let websocket = route == "/v1/runs/{run}/live";
    let changes_state = !matches!(method, Method::GET | Method::HEAD | Method::OPTIONS);
    if (changes_state || websocket)
        && let Some(origin) = req.headers().get(header::ORIGIN)
    {
        let origin = origin.to_str().unwrap_or("");
        let host = req
            .headers()
            .get(header::HOST)
            .and_then(|h| h.to_str().ok());
        if !origin_allowed(cfg, origin, host) {
            return Err(ApiError::Forbidden(format!(
                "requests from web pages of origin {:?} may not change state or open the live \
                 view; the operator can allow it with allowed_origins",
                crate::limits::truncate(origin, 100)
            )));
        }
    }
    if changes_state && has_body(req.headers()) {
        let ct = req
            .headers()
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("");
        let ndjson = access == Access::Robot;
        if !is_json(ct, ndjson) {
            return Err(ApiError::UnsupportedMediaType(format!(
                "the body must be JSON (Content-Type: application/json{}), got {:?}",
                if ndjson {
                    ", or application/x-ndjson"
                } else {
                    ""
                },
                crate::limits::truncate(ct, 100)
            )));
        }
    }
    if matches!(method, Method::GET | Method::HEAD) {
        token_from_query(req);
    }
    match access {
        Access::Public | Access::Enroll | Access::Robot => Ok(()),
        Access::Read => check_read(cfg, req.headers()),
        Access::Admin => check_admin(cfg, req.headers()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    #[test]
    fn bearer_scheme_in_any_case() {
        let mut h = HeaderMap::new();
        for v in ["Bearer abc", "bearer abc", "BEARER  abc ", "BeArEr\tabc"] {
            h.insert(header::AUTHORIZATION, HeaderValue::from_str(v).unwrap());
            assert_eq!(bearer(&h), Some("abc"), "{v:?}");
        }
        for v in ["Basic abc", "Bearer", "Bearer ", "abc"] {
            h.insert(header::AUTHORIZATION, HeaderValue::from_str(v).unwrap());
            assert_eq!(bearer(&h), None, "{v:?}");
        }
    }

    #[test]
    fn tokens_compare_whole() {
        assert!(token_eq("0123456789abcdef", "0123456789abcdef"));
        assert!(!token_eq("0123456789abcdeg", "0123456789abcdef"));
        assert!(!token_eq("0123456789abcde", "0123456789abcdef"));
        assert!(hash_matches("x", &token_hash("x")));
        assert!(!hash_matches("y", &token_hash("x")));
    }

    #[test]
    fn origins() {
        assert_eq!(
            parse_origin("HTTP://Example.com:80").unwrap(),
            "http://example.com"
        );
        assert_eq!(
            parse_origin("https://a.b:8443").unwrap(),
            "https://a.b:8443"
        );
        assert!(parse_origin("example.com").is_err());
        assert!(parse_origin("http://a.b/path").is_err());
        let local = AuthConfig {
            loopback: true,
            allowed_origins: vec!["https://ops.example.com".into()],
            ..AuthConfig::default()
        };
        let ok = |o: &str, h: &str| origin_allowed(&local, o, Some(h));
        assert!(ok("http://127.0.0.1:8080", "127.0.0.1:8080"));
        assert!(ok("http://localhost:8080", "localhost:8080"));
        assert!(ok("http://[::1]:8080", "[::1]:8080"));
        assert!(ok("https://ops.example.com", "127.0.0.1:8080"));
        // Another site, and a site whose name was rebound to 127.0.0.1.
        assert!(!ok("http://evil.example:8080", "127.0.0.1:8080"));
        assert!(!ok("http://evil.example:8080", "evil.example:8080"));
        assert!(!ok("http://localhost:9999", "localhost:8080"));
        assert!(!ok("null", "127.0.0.1:8080"));
        // A server on the network serves its own dashboard under its own name.
        let exposed = AuthConfig {
            loopback: false,
            ..AuthConfig::default()
        };
        assert!(origin_allowed(
            &exposed,
            "http://fleet.lan:8080",
            Some("fleet.lan:8080")
        ));
        assert!(!origin_allowed(
            &exposed,
            "http://evil.example",
            Some("fleet.lan:8080")
        ));
    }

    #[test]
    fn content_types() {
        assert!(is_json("application/json", false));
        assert!(is_json("Application/JSON; charset=utf-8", false));
        assert!(is_json("application/merge-patch+json", false));
        assert!(!is_json("text/plain", false));
        assert!(!is_json("", false));
        assert!(!is_json("application/x-ndjson", false));
        assert!(is_json("application/x-ndjson", true));
        assert!(!is_json("multipart/form-data", true));
    }

    #[test]
    fn every_documented_route_has_a_rule() {
        use utoipa::OpenApi;
        let doc = crate::openapi::ApiDoc::openapi();
        let mut n = 0;
        for (path, item) in &doc.paths.paths {
            let ops = [
                (Method::GET, item.get.is_some()),
                (Method::POST, item.post.is_some()),
                (Method::PUT, item.put.is_some()),
                (Method::DELETE, item.delete.is_some()),
            ];
            for (m, present) in ops {
                if present {
                    n += 1;
                    assert!(
                        matches!(policy(&m, path), Some(Some(_))),
                        "{m} {path} has no access rule"
                    );
                }
            }
        }
        assert!(n >= 19, "only {n} operations documented");
        assert_eq!(policy(&Method::GET, "/v1/secret"), None);
        assert_eq!(
            policy(&Method::GET, "/v1/runs/{run}/observations"),
            Some(None)
        );
        assert_eq!(
            policy(&Method::POST, "/v1/runs/{run}/robots"),
            Some(Some(Access::Enroll))
        );
    }

    #[test]
    fn reads_need_a_token_off_loopback() {
        let mut c = AuthConfig {
            loopback: true,
            ..AuthConfig::default()
        };
        assert!(!c.reads_need_token());
        c.loopback = false;
        assert!(c.reads_need_token());
        c.read_access = ReadAccess::Open;
        assert!(!c.reads_need_token());
        c.loopback = true;
        c.read_access = ReadAccess::Token;
        assert!(c.reads_need_token());
    }
}
