//! Reviews of calls: who may make one, and the checks of a review's request before the store
//! is touched.
//!
//! - **Where from.** A browser sends `Sec-Fetch-Site` (older ones `Origin`) with a form's
//!   POST; one from another site (a page elsewhere posting to this loopback port) is refused,
//!   so a page on the internet cannot record reviews through an operator's browser. (Found by
//!   the browser test: under `Referrer-Policy: no-referrer` Chromium's same-site POST says
//!   `Origin: null`; the site's policy is `same-origin` now, and `Sec-Fetch-Site` decides.)
//! - **Token.** When the pages are served with a token (`dpsa serve --token-file`), every
//!   review carries it (the form's token field); compared in constant time. Served beyond
//!   loopback (`--bind` on another address) without a token, reviews are refused altogether:
//!   the pages can be read from the network, but nobody there can write.
//! - **What.** A decision (`confirmed` or `false_call`), a reviewer's name (1 to 100 bytes)
//!   and an optional note (at most 2,000 bytes); the body at most [`MAX_BODY`] bytes.

use axum::http::{header, HeaderMap, StatusCode};
use dpsa_line::store::Decision;

/// The largest request body the site reads, bytes.
pub const MAX_BODY: usize = 16 * 1024;

/// Who may review.
#[derive(Clone, Debug, Default)]
pub struct Policy {
    /// The token every review must carry (none: reviews need none, on loopback).
    pub token: Option<String>,
    /// The pages are served on an address beyond loopback.
    pub beyond_loopback: bool,
}

impl Policy {
    /// Whether the review form is offered at all.
    pub fn open(&self) -> bool {
        self.token.is_some() || !self.beyond_loopback
    }

    /// Whether the form asks for the token.
    pub fn needs_token(&self) -> bool {
        self.token.is_some()
    }
}

/// A review as the form posts it.
#[derive(Clone, Debug, serde::Deserialize)]
pub struct ReviewForm {
    /// `confirmed` or `false_call`.
    pub decision: String,
    /// Who reviews.
    pub reviewer: String,
    /// What they note.
    #[serde(default)]
    pub note: String,
    /// The site's token, when it has one.
    #[serde(default)]
    pub token: String,
}

/// Why a review was refused before the store.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum Refusal {
    /// Served beyond loopback without a token.
    #[error(
        "reviews are off: these pages are served beyond loopback without a token (start \
         dpsa serve with --token-file)"
    )]
    Closed,
    /// The request came from a page of another site.
    #[error("a review from another site's page ({0}) is refused")]
    CrossSite(String),
    /// The token is missing or wrong.
    #[error("the token is missing or wrong")]
    Token,
    /// The decision is not one.
    #[error("the decision must be confirmed or false_call, not {0:?}")]
    Decision(String),
}

impl Refusal {
    /// The HTTP status it is answered with.
    pub fn status(&self) -> StatusCode {
        match self {
            Refusal::Decision(_) => StatusCode::BAD_REQUEST,
            _ => StatusCode::FORBIDDEN,
        }
    }
}

/// Shortest token accepted, bytes.
pub const MIN_TOKEN: usize = 16;

/// The token in file `path` (its first line, trimmed: 16 to 256 bytes), or why not.
pub fn read_token(path: &std::path::Path) -> Result<String, String> {
    let bytes =
        dpsa_formats::files::read_capped(path, 4096, "token file").map_err(|e| e.to_string())?;
    let text = String::from_utf8(bytes)
        .map_err(|_| format!("{}: the token is not UTF-8 text", path.display()))?;
    let token = text.lines().next().unwrap_or("").trim().to_owned();
    if !(MIN_TOKEN..=256).contains(&token.len()) {
        return Err(format!(
            "{}: the token (its first line) must be {MIN_TOKEN} to 256 bytes, not {}",
            path.display(),
            token.len()
        ));
    }
    Ok(token)
}

/// Equal bytes, in a time that does not depend on where they differ.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |d, (x, y)| d | (x ^ y)) == 0
}

/// The host and port of an origin (`http://127.0.0.1:8080` to `127.0.0.1:8080`).
fn origin_host(origin: &str) -> &str {
    let rest = origin.split_once("://").map_or(origin, |(_, r)| r);
    rest.split('/').next().unwrap_or(rest)
}

/// Checks a review's request: the decision it asks for, or why it is refused.
pub fn check(policy: &Policy, headers: &HeaderMap, form: &ReviewForm) -> Result<Decision, Refusal> {
    if !policy.open() {
        return Err(Refusal::Closed);
    }
    let text = |h: header::HeaderName| headers.get(h).and_then(|v| v.to_str().ok());
    // The browser's own word first (every current browser sends it); `Origin` for one that
    // does not. A form posted under `Referrer-Policy: no-referrer` carries `Origin: null`
    // even from the same site, so `null` alone is refused only without the former.
    if let Some(site) = headers.get("sec-fetch-site").and_then(|v| v.to_str().ok()) {
        if site != "same-origin" && site != "none" {
            return Err(Refusal::CrossSite(site.to_owned()));
        }
    } else if let Some(origin) = text(header::ORIGIN) {
        let host = text(header::HOST).unwrap_or("");
        if origin == "null" || !origin_host(origin).eq_ignore_ascii_case(host) {
            return Err(Refusal::CrossSite(origin.to_owned()));
        }
    }
    if let Some(t) = &policy.token {
        if !same(t.as_bytes(), form.token.as_bytes()) {
            return Err(Refusal::Token);
        }
    }
    Decision::from_name(&form.decision).ok_or_else(|| Refusal::Decision(form.decision.clone()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn form(decision: &str, token: &str) -> ReviewForm {
        ReviewForm {
            decision: decision.into(),
            reviewer: "ana".into(),
            note: String::new(),
            token: token.into(),
        }
    }

    fn headers(pairs: &[(&'static str, &'static str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, HeaderValue::from_static(v));
        }
        h
    }

    #[test]
    fn the_policy_and_the_request_decide() {
        let local = Policy::default();
        let ok = headers(&[
            ("host", "127.0.0.1:8080"),
            ("origin", "http://127.0.0.1:8080"),
        ]);
        assert_eq!(
            check(&local, &ok, &form("false_call", "")),
            Ok(Decision::FalseCall)
        );
        assert_eq!(
            check(&local, &HeaderMap::new(), &form("confirmed", "")),
            Ok(Decision::Confirmed)
        );
        // Chromium's same-site form under no-referrer: Origin null, Sec-Fetch-Site same-origin.
        let chromium = headers(&[
            ("host", "127.0.0.1:8080"),
            ("origin", "null"),
            ("sec-fetch-site", "same-origin"),
        ]);
        assert_eq!(
            check(&local, &chromium, &form("confirmed", "")),
            Ok(Decision::Confirmed)
        );
        assert!(matches!(
            check(&local, &ok, &form("maybe", "")),
            Err(Refusal::Decision(_))
        ));
        // Another site's page.
        for bad in [
            headers(&[
                ("host", "127.0.0.1:8080"),
                ("origin", "http://evil.example"),
            ]),
            headers(&[
                ("host", "127.0.0.1:8080"),
                ("origin", "http://127.0.0.1:9999"),
            ]),
            headers(&[("host", "127.0.0.1:8080"), ("origin", "null")]),
            headers(&[("host", "127.0.0.1:8080"), ("sec-fetch-site", "cross-site")]),
            headers(&[("host", "127.0.0.1:8080"), ("sec-fetch-site", "same-site")]),
        ] {
            let e = check(&local, &bad, &form("confirmed", "")).unwrap_err();
            assert!(matches!(e, Refusal::CrossSite(_)), "{e}");
            assert_eq!(e.status(), StatusCode::FORBIDDEN);
        }
        // Beyond loopback: closed without a token; with one, it must match.
        let open = Policy {
            token: None,
            beyond_loopback: true,
        };
        assert!(!open.open());
        assert_eq!(
            check(&open, &ok, &form("confirmed", "")),
            Err(Refusal::Closed)
        );
        let tok = Policy {
            token: Some("s3cret-token".into()),
            beyond_loopback: true,
        };
        assert!(tok.open() && tok.needs_token());
        assert_eq!(
            check(&tok, &ok, &form("confirmed", "s3cret-token")),
            Ok(Decision::Confirmed)
        );
        for t in ["", "s3cret-tokem", "s3cret-token2", "S3CRET-TOKEN"] {
            assert_eq!(check(&tok, &ok, &form("confirmed", t)), Err(Refusal::Token));
        }
    }
}
