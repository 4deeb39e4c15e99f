//! The operator's web pages over the line's store (`dpsa serve`, `docs/web.md`).
//!
//! Server-rendered HTML from the store, opened read-only for every page
//! ([`dpsa_line::store::Store::open_read_only`]): the line (its newest boards, yield,
//! throughput, the printer's last correction, the false calls per family), a board (its
//! verdict, cameras, print placement and every pad that warned or failed, each linked, with
//! its review) and a pad (its values and uncertainty, the heights kept around it with the
//! profile, its history on the line with a chart, its reviews and the review form). The
//! board's measured map, when the line kept it, zooms and pans ([`tiles`]). JavaScript only
//! for that and the pad's 3D view ([`view3d`]), no file from disk but the kept maps: the
//! style sheet and the scripts are in the binary.
//!
//! - [`html`]: escaping, the page frame, the history chart (inline SVG).
//! - [`crop`]: a pad's kept heights drawn (an image, axes, colour bar, profile).
//! - [`pages`]: what each page reads from the store and how it is laid out.
//! - [`review`]: who may review, and the checks of a review's request.
//!
//! Why axum: the tokio team's router on hyper, the framework the Rust ecosystem converges on;
//! its handlers are plain async functions and its router a value the tests call directly.
//! The store is synchronous (rusqlite, postgres), so each page runs on tokio's blocking pool.
//!
//! Security: the default address is loopback ([`DEFAULT_BIND`]); every response carries a
//! Content-Security-Policy that allows nothing but this site's style sheet, images and forms,
//! and inline SVG, `X-Content-Type-Options: nosniff` and `Referrer-Policy: same-origin`; no
//! route reads a file (a path with `..` or anything unknown is a 404); the pages open the
//! store read-only. The one write is a review ([`review`]): refused from another site, and
//! with a token required whenever one is set, and always when the pages are served beyond
//! loopback.

pub mod board_view;
pub mod crop;
pub mod html;
pub mod pages;
pub mod review;
pub mod spc;
pub mod tiles;
pub mod view3d;

use axum::extract::{DefaultBodyLimit, Path, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Form, Router};
use dpsa_line::store::Location;
use std::net::SocketAddr;
use std::sync::Arc;

/// The address `dpsa serve` listens on unless told otherwise: loopback only.
pub const DEFAULT_BIND: &str = "127.0.0.1:8080";

/// The Content-Security-Policy of every response.
pub const CSP: &str = "default-src 'none'; style-src 'self'; img-src 'self' data:; \
                       script-src 'self'; connect-src 'self'; frame-ancestors 'none'; \
                       base-uri 'none'; form-action 'self'";

/// Why the site could not be served.
#[derive(Debug, thiserror::Error)]
pub enum WebError {
    /// The address could not be bound, or the server failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The store.
    #[error(transparent)]
    Store(#[from] dpsa_line::store::StoreError),
}

/// What the pages show: a line's boards in a store.
#[derive(Clone, Debug)]
pub struct Site {
    /// The store.
    pub store: Location,
    /// The line whose boards are shown.
    pub line: String,
    /// Who may review calls.
    pub reviews: review::Policy,
    /// The programs whose boards are drawn (a board is drawn by the program of its hash).
    pub designs: Arc<board_view::Designs>,
    /// The newest SPC study made, kept until a newer board comes.
    pub spc: Arc<spc::Cache>,
    /// The directory of the measured maps the line keeps (`[maps]`), if any.
    pub maps: Option<std::path::PathBuf>,
    /// The maps' pyramids and tiles drawn so far.
    pub map_cache: Arc<tiles::MapCache>,
}

impl Site {
    /// The pages of `line` in `store`, reviews open to anyone who reaches them (loopback).
    pub fn new(store: Location, line: &str) -> Site {
        Site {
            store,
            line: line.to_owned(),
            reviews: review::Policy::default(),
            designs: Arc::default(),
            spc: Arc::default(),
            maps: None,
            map_cache: Arc::default(),
        }
    }
}

/// The site's routes.
pub fn router(site: Site) -> Router {
    Router::new()
        .route("/", get(line))
        .route("/board/{id}", get(board))
        .route("/board/{id}/pad/{pad}", get(pad))
        .route("/board/{id}/pad/{pad}/crop.png", get(crop_png))
        .route("/board/{id}/pad/{pad}/heights.json", get(heights_json))
        .route("/board/{id}/map/{run}/{file}", get(map_info))
        .route("/board/{id}/map/{run}/{z}/{x}/{file}", get(map_tile))
        .route(tiles::SCRIPT_PATH, get(mapview_js))
        .route(view3d::LIBRARY_PATH, get(library_js))
        .route(view3d::SCRIPT_PATH, get(view3d_js))
        .route(
            "/board/{id}/pad/{pad}/review",
            axum::routing::post(post_review),
        )
        .route("/spc", get(spc_newest))
        .route("/spc/{product}", get(spc_product))
        .route("/spc/{product}/chart/{kind}/{k}/{file}", get(spc_chart))
        .route("/style.css", get(style))
        .route("/icon.svg", get(icon))
        .fallback(not_found)
        .layer(DefaultBodyLimit::max(review::MAX_BODY))
        .with_state(Arc::new(site))
}

/// Serves `site` on `listener` until `shutdown` completes.
pub async fn serve_on(
    listener: tokio::net::TcpListener,
    site: Site,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), WebError> {
    axum::serve(listener, router(site))
        .with_graceful_shutdown(shutdown)
        .await?;
    Ok(())
}

/// `dpsa serve`: checks the store opens read-only, then serves `site` on `bind` until Ctrl-C
/// or SIGTERM.
pub fn run(site: Site, bind: SocketAddr) -> Result<(), WebError> {
    drop(dpsa_line::store::Store::open_read_only(
        &site.store,
        &site.line,
    )?);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(bind).await?;
        tracing::info!(address = %listener.local_addr()?, "serving the line's pages");
        serve_on(listener, site, async {
            let mut term =
                tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).ok();
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = async {
                    match term.as_mut() {
                        Some(t) => { t.recv().await; }
                        None => std::future::pending::<()>().await,
                    }
                } => {}
            }
        })
        .await
    })
}

/// Serves `site` on `bind` from a thread of its own, for as long as the process runs (the
/// line service's pages, `dpsa line run --web`): the address it listens on (the port chosen
/// when `bind`'s is 0). The address is bound before this returns, so a port in use is said at
/// once.
pub fn spawn(site: Site, bind: SocketAddr) -> Result<SocketAddr, WebError> {
    let listener = std::net::TcpListener::bind(bind)?;
    listener.set_nonblocking(true)?;
    let at = listener.local_addr()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    std::thread::Builder::new()
        .name("web".into())
        .spawn(move || {
            rt.block_on(async move {
                let served = match tokio::net::TcpListener::from_std(listener) {
                    Ok(l) => serve_on(l, site, std::future::pending()).await,
                    Err(e) => Err(e.into()),
                };
                if let Err(e) = served {
                    tracing::error!("the line's pages stopped: {e}");
                }
            })
        })?;
    Ok(at)
}

/// A response with the site's headers.
fn respond(status: StatusCode, content_type: &'static str, body: impl IntoResponse) -> Response {
    let mut r = (status, body).into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("same-origin"),
    );
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    r
}

const HTML: &str = "text/html; charset=utf-8";

/// What a route makes on the blocking pool, served: `Some` with `content_type`, `None` a 404,
/// an error a 503 page that says `failed` and why (logged), a panic a 500. The one shape of
/// every route that reads the store or a kept map.
async fn on_pool<B, E>(
    content_type: &'static str,
    (title, failed): (&'static str, &'static str),
    make: impl FnOnce() -> Result<Option<B>, E> + Send + 'static,
) -> Response
where
    B: IntoResponse + Send + 'static,
    E: std::fmt::Display + Send + 'static,
{
    match tokio::task::spawn_blocking(make).await {
        Ok(Ok(Some(body))) => respond(StatusCode::OK, content_type, body),
        Ok(Ok(None)) => not_found().await,
        Ok(Err(e)) => {
            tracing::error!("{failed}: {e}");
            message(
                StatusCode::SERVICE_UNAVAILABLE,
                title,
                &format!("{failed}: {e}"),
            )
        }
        Err(e) => message(StatusCode::INTERNAL_SERVER_ERROR, "Error", &e.to_string()),
    }
}

/// What a route that reads the store says when it cannot.
const STORE: (&str, &str) = ("Store unavailable", "The store could not be read");

/// A page rendered on the blocking pool, or its error page.
async fn page(
    site: Arc<Site>,
    render: impl FnOnce(&Site) -> Result<Option<String>, pages::PageError> + Send + 'static,
) -> Response {
    on_pool(HTML, STORE, move || render(&site)).await
}

/// A page of one sentence (escaped here) with `status`.
fn message(status: StatusCode, title: &str, text: &str) -> Response {
    respond(
        status,
        HTML,
        html::frame(title, &format!("<p>{}</p>", html::esc(text))),
    )
}

async fn line(State(site): State<Arc<Site>>) -> Response {
    page(site, |s| pages::line(s).map(Some)).await
}

async fn board(State(site): State<Arc<Site>>, Path(id): Path<String>) -> Response {
    let Ok(id) = id.parse::<i64>() else {
        return not_found().await;
    };
    page(site, move |s| pages::board(s, id)).await
}

async fn pad(State(site): State<Arc<Site>>, Path((id, pad)): Path<(String, String)>) -> Response {
    let (Ok(id), Ok(pad)) = (id.parse::<i64>(), pad.parse::<u32>()) else {
        return not_found().await;
    };
    page(site, move |s| pages::pad(s, id, pad)).await
}

/// The pad's kept heights as a PNG (`crop::png`), or a 404.
async fn crop_png(
    State(site): State<Arc<Site>>,
    Path((id, pad)): Path<(String, String)>,
) -> Response {
    let (Ok(id), Ok(pad)) = (id.parse::<i64>(), pad.parse::<u32>()) else {
        return not_found().await;
    };
    on_pool("image/png", STORE, move || pages::crop_png(&site, id, pad)).await
}

/// A review of a call: checked ([`review::check`]), stored, and the pad's page again (303).
async fn post_review(
    State(site): State<Arc<Site>>,
    Path((id, pad)): Path<(String, String)>,
    headers: HeaderMap,
    form: Result<Form<review::ReviewForm>, axum::extract::rejection::FormRejection>,
) -> Response {
    let (Ok(id), Ok(pad)) = (id.parse::<i64>(), pad.parse::<u32>()) else {
        return not_found().await;
    };
    // A form that does not parse (or is over the size limit) gets the site's page and
    // headers, not the framework's bare text.
    let form = match form {
        Ok(Form(f)) => f,
        Err(e) => {
            tracing::warn!(board = id, pad, "review form refused: {e}");
            return message(e.status(), "Review refused", &e.body_text());
        }
    };
    let decision = match review::check(&site.reviews, &headers, &form) {
        Ok(d) => d,
        Err(refusal) => {
            tracing::warn!(board = id, pad, "review refused: {refusal}");
            return respond(
                refusal.status(),
                HTML,
                html::frame(
                    "Review refused",
                    &format!(
                        "<p>{}</p><p><a href=\"/board/{id}/pad/{pad}\">Back to the pad</a>.</p>",
                        html::esc(&refusal.to_string())
                    ),
                ),
            );
        }
    };
    let out = tokio::task::spawn_blocking(move || {
        let mut store = dpsa_line::store::Store::open(&site.store, &site.line)?;
        store.add_review(
            id,
            pad,
            decision,
            &form.reviewer,
            dpsa_line::boards::unix_now(),
            Some(form.note.as_str()),
        )
    })
    .await;
    match out {
        Ok(Ok(rid)) => {
            tracing::info!(board = id, pad, review = rid, "call reviewed");
            let mut r = respond(StatusCode::SEE_OTHER, HTML, String::new());
            if let Ok(v) = HeaderValue::from_str(&format!("/board/{id}/pad/{pad}")) {
                r.headers_mut().insert(header::LOCATION, v);
            }
            r
        }
        Ok(Err(dpsa_line::store::StoreError::Invalid { why, .. })) => {
            message(StatusCode::BAD_REQUEST, "Review refused", &why)
        }
        Ok(Err(e)) => {
            tracing::error!("review: {e}");
            message(
                StatusCode::SERVICE_UNAVAILABLE,
                "Store unavailable",
                &format!("The review was not stored: {e}"),
            )
        }
        Err(e) => message(StatusCode::INTERNAL_SERVER_ERROR, "Error", &e.to_string()),
    }
}

async fn spc_newest(State(site): State<Arc<Site>>) -> Response {
    spc_page(site, None).await
}

async fn spc_product(State(site): State<Arc<Site>>, Path(product): Path<String>) -> Response {
    spc_page(site, Some(product)).await
}

async fn spc_page(site: Arc<Site>, product: Option<String>) -> Response {
    on_pool(
        HTML,
        ("SPC unavailable", "The study could not be made"),
        move || spc::page(&site, product.as_deref()),
    )
    .await
}

/// An SPC chart as PNG (`spc::chart_png`), or a 404.
async fn spc_chart(
    State(site): State<Arc<Site>>,
    Path((product, kind, k, file)): Path<(String, String, String, String)>,
) -> Response {
    let (Ok(k), Some(metric)) = (
        k.parse::<usize>(),
        file.strip_suffix(".png").map(str::to_owned),
    ) else {
        return not_found().await;
    };
    on_pool(
        "image/png",
        ("SPC unavailable", "The chart could not be drawn"),
        move || spc::chart_png(&site, &product, &kind, k, &metric),
    )
    .await
}

async fn style() -> Response {
    respond(
        StatusCode::OK,
        "text/css; charset=utf-8",
        html::STYLE.to_owned(),
    )
}

/// The 3D view's library (npm, bundled at build time); a 404 in a build without it.
async fn library_js() -> Response {
    if view3d::LIBRARY.is_empty() {
        return not_found().await;
    }
    script(view3d::LIBRARY)
}

async fn mapview_js() -> Response {
    script(tiles::SCRIPT)
}

/// Board `id`'s run id as the map routes take it: 16 lowercase hex digits.
fn run_hex(run: &str) -> Option<String> {
    (run.len() == 16 && run.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')))
        .then(|| run.to_owned())
}

/// What the map viewer needs of board `id`'s kept map of run `run`
/// (`/board/ID/map/RUN/info.json`; the pyramid built on the first request), or a 404 when
/// none of that run is kept.
async fn map_info(
    State(site): State<Arc<Site>>,
    Path((id, run, file)): Path<(String, String, String)>,
) -> Response {
    let (Ok(id), Some(run), true, Some(dir)) = (
        id.parse::<i64>(),
        run_hex(&run),
        file == "info.json",
        site.maps.clone(),
    ) else {
        return not_found().await;
    };
    on_pool("application/json", MAP, move || {
        if !site.map_cache.has(id, &run) && !pages::board_has_run(&site, id, &run)? {
            return Ok(None);
        }
        site.map_cache
            .pyramid(&dir, &site.line, id, &run)
            .map(|p| p.map(|p| p.json()))
            .map_err(MapError::Map)
    })
    .await
}

/// A tile of board `id`'s kept map of run `run` (`/board/ID/map/RUN/Z/X/Y.png`, every part
/// parsed: integers and 16 hex digits), or a 404. The map's files are named from the parsed
/// id only.
async fn map_tile(
    State(site): State<Arc<Site>>,
    Path((id, run, z, x, file)): Path<(String, String, String, String, String)>,
) -> Response {
    let (Ok(id), Some(run), Ok(z), Ok(x), Some(Ok(y)), Some(dir)) = (
        id.parse::<i64>(),
        run_hex(&run),
        z.parse::<u8>(),
        x.parse::<u32>(),
        file.strip_suffix(".png").map(str::parse::<u32>),
        site.maps.clone(),
    ) else {
        return not_found().await;
    };
    let mut r = on_pool("image/png", MAP, move || {
        if !site.map_cache.has(id, &run) && !pages::board_has_run(&site, id, &run)? {
            return Ok(None);
        }
        site.map_cache
            .tile_png(&dir, &site.line, id, &run, z, x, y)
            .map(|t| t.map(|png| png.as_ref().clone()))
            .map_err(MapError::Map)
    })
    .await;
    if r.status() == StatusCode::OK {
        // A board's map never changes once kept, and its run is in the path.
        r.headers_mut().insert(
            header::CACHE_CONTROL,
            HeaderValue::from_static("private, max-age=3600"),
        );
    }
    r
}

/// Why a map route could not answer.
#[derive(Debug, thiserror::Error)]
enum MapError {
    /// The store, asked whose board the id is.
    #[error("the store could not be read: {0}")]
    Store(#[from] dpsa_line::store::StoreError),
    /// The kept map.
    #[error("the kept map cannot be read: {0}")]
    Map(dpsa_formats::kept_map::KeptMapError),
}

/// What the map routes say when the store or the kept map cannot be read (never drawn).
const MAP: (&str, &str) = ("Map unavailable", "The map could not be drawn");

async fn view3d_js() -> Response {
    script(view3d::SCRIPT)
}

/// A script of the binary's own: cached for a day (the library's path names its version).
fn script(text: &'static str) -> Response {
    let mut r = respond(
        StatusCode::OK,
        "text/javascript; charset=utf-8",
        text.to_owned(),
    );
    r.headers_mut().insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("public, max-age=86400"),
    );
    r
}

/// A pad's kept heights as JSON (`pages::heights_json`), or a 404.
async fn heights_json(
    State(site): State<Arc<Site>>,
    Path((id, pad)): Path<(String, String)>,
) -> Response {
    let (Ok(id), Ok(pad)) = (id.parse::<i64>(), pad.parse::<u32>()) else {
        return not_found().await;
    };
    on_pool("application/json", STORE, move || {
        pages::heights_json(&site, id, pad)
    })
    .await
}

async fn icon() -> Response {
    respond(StatusCode::OK, "image/svg+xml", html::ICON.to_owned())
}

async fn not_found() -> Response {
    respond(
        StatusCode::NOT_FOUND,
        HTML,
        html::frame(
            "Not found",
            "<p>No such page. <a href=\"/\">The line</a>.</p>",
        ),
    )
}
