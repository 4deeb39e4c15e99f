//! The pages in a real browser: Debian's Chromium, headless, driven over WebDriver by its
//! chromedriver (fantoccini), against the site served on a loopback port. Each page renders
//! with nothing in the browser's console (no script error, no resource refused by the
//! Content-Security-Policy, no image that failed to load); the board's list of calls links to
//! the right pad's page; a review made in the form is stored; the pad's image is drawn; the
//! SPC page opens from the header. Each page is photographed whole: the screenshot is a
//! picture of the page's width, not blank; with `DPSA_SCREENSHOTS=DIR` they are kept there
//! (`docs/ui.md` shows them).
//!
//! Needs `chromedriver` and Chromium (the test command installs Debian's `chromium` and
//! `chromium-driver`); fails, saying so, without them.

mod common;

use common::store;
use dpsa_line::store::{Decision, Store};
use dpsa_web::Site;
use fantoccini::wd::WebDriverCompatibleCommand;
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::{json, Value};
use std::net::TcpListener;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// chromedriver on a free loopback port, killed when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn driver() -> Driver {
    let exe = ["chromedriver", "/usr/bin/chromedriver"]
        .into_iter()
        .find(|c| {
            Command::new(c)
                .arg("--version")
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status()
                .is_ok_and(|s| s.success())
        })
        .expect(
            "chromedriver not found: install Debian's chromium and chromium-driver (the test \
             command does)",
        );
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let child = Command::new(exe)
        .arg(format!("--port={port}"))
        .arg("--allowed-ips=127.0.0.1")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "chromedriver did not start"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    Driver {
        child,
        url: format!("http://127.0.0.1:{port}"),
    }
}

/// chromedriver's log of the browser's console since the last call (its `se/log` endpoint).
#[derive(Debug)]
struct BrowserLog;

impl WebDriverCompatibleCommand for BrowserLog {
    fn endpoint(
        &self,
        base: &url::Url,
        session: Option<&str>,
    ) -> Result<url::Url, url::ParseError> {
        base.join(&format!("session/{}/se/log", session.unwrap_or("")))
    }

    fn method_and_body(&self, _: &url::Url) -> (http::Method, Option<String>) {
        (
            http::Method::POST,
            Some(json!({"type": "browser"}).to_string()),
        )
    }
}

/// The console's entries since the last call, as `LEVEL message`: all but the software
/// rasteriser's notes on its own speed (this machine has no GPU: Chromium draws WebGL with
/// SwiftShader, and its driver says when reading pixels back stalls it).
async fn console(c: &Client) -> Vec<String> {
    let v = c.issue_cmd(BrowserLog).await.expect("the browser's log");
    v.as_array()
        .map(|a| {
            a.iter()
                .map(|e| format!("{} {}", e["level"].as_str().unwrap_or("?"), e["message"]))
                .filter(|m| !m.contains("GL Driver Message (OpenGL, Performance"))
                .collect()
        })
        .unwrap_or_default()
}

/// Opens `url`, waits for the page to have loaded (images too) and checks the console is
/// empty.
async fn open_clean(c: &Client, url: &str) {
    c.goto(url).await.unwrap();
    settle(c).await;
    let log = console(c).await;
    assert!(log.is_empty(), "{url}: the console says {log:?}");
}

/// A screenshot of the whole page (the window grown to the page's height, at most 3000 px):
/// a PNG as wide as the window with more than a few colours in it (a page drawn, not blank);
/// kept as `DIR/NAME.png` when `DPSA_SCREENSHOTS=DIR` is set.
async fn shot(c: &Client, name: &str) {
    let height = c
        .execute("return document.documentElement.scrollHeight;", vec![])
        .await
        .unwrap()
        .as_u64()
        .unwrap_or(900)
        .clamp(300, 3000);
    c.set_window_size(1100, height as u32).await.unwrap();
    let png_bytes = c.screenshot().await.unwrap();
    c.set_window_size(1100, 900).await.unwrap();
    let mut r = png::Decoder::new(std::io::Cursor::new(&png_bytes))
        .read_info()
        .unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    assert!(
        info.width >= 1000 && info.height >= 250,
        "{name}: a screenshot of {} x {}",
        info.width,
        info.height
    );
    let channels = info.color_type.samples();
    let colours: std::collections::HashSet<&[u8]> = buf[..info.buffer_size()]
        .chunks_exact(channels)
        .step_by(5)
        .collect();
    assert!(
        colours.len() > 30,
        "{name}: the screenshot has {} colours: blank",
        colours.len()
    );
    if let Some(dir) = std::env::var_os("DPSA_SCREENSHOTS") {
        std::fs::write(
            std::path::Path::new(&dir).join(format!("{name}.png")),
            &png_bytes,
        )
        .unwrap();
    }
}

/// The value of `script` once it is not null (20 s at most).
async fn wait_for(c: &Client, script: &str) -> Value {
    let t0 = Instant::now();
    loop {
        let v = c.execute(script, vec![]).await.unwrap();
        if !v.is_null() {
            return v;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "never: {script}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Until the document and its images have loaded.
async fn settle(c: &Client) {
    let t0 = Instant::now();
    loop {
        let done = c
            .execute("return document.readyState === 'complete';", vec![])
            .await
            .unwrap();
        if done == Value::Bool(true) {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "the page never loaded"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Clicks the element `css` selects, waits for the page it opens, checks it is `path` with
/// nothing in the console.
async fn click_to(c: &Client, css: &str, path: &str) {
    // The page before the click carries a mark; the new document does not. Until it is
    // there, `readyState` is still the old page's (and a form that posts back to its own
    // page keeps the same path).
    c.execute("window.dpsaBefore = true;", vec![])
        .await
        .unwrap();
    c.find(Locator::Css(css))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let t0 = Instant::now();
    loop {
        let gone = c
            .execute("return window.dpsaBefore === undefined;", vec![])
            .await
            .unwrap();
        if gone == Value::Bool(true) {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "{css}: no new page");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    settle(c).await;
    let src = c.source().await.unwrap();
    assert_eq!(c.current_url().await.unwrap().path(), path, "{src}");
    let log = console(c).await;
    assert!(log.is_empty(), "{path}: the console says {log:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_pages_work_in_chromium() {
    let dir = tempfile::tempdir().unwrap();
    // The boards' program (three openings named as the store's pads) and the second board's
    // measured map as the line keeps it: 4.8 x 3.2 mm at 2 um, five levels, paste on the
    // openings.
    let prog = common::mini_program(dir.path());
    let (loc, ids) = store(dir.path());
    // The drawing and the calls on the map need the boards' program: a site of its own whose
    // design stands for the store's program "p" (the SPC page, which reads the program's
    // pad names, is visited on the plain site).
    let mut design = dpsa_line::config::Design::load(&prog).unwrap();
    design.program_hash = "p".into();
    let maps = dir.path().join("maps");
    let shift = dpsa_formats::kept_map::DesignToBoard {
        rotation_rad: 0.0,
        tx_mm: 0.4,
        ty_mm: 0.3,
    };
    common::kept_map(
        &maps,
        "line-1",
        (ids[1], 0xa2),
        (2400, 1600, 0.002),
        &[(1.4, 1.3), (2.4, 1.3), (3.4, 2.3)],
        Some(shift),
    );
    let mut with_map = Site::new(loc.clone(), "line-1");
    with_map.designs = std::sync::Arc::new(dpsa_web::board_view::Designs::from(vec![design]));
    with_map.maps = Some(maps);
    let (map_addr, map_stop, map_h) = common::serve(with_map);
    let (addr, stop, h) = common::serve(Site::new(loc.clone(), "line-1"));
    let d = driver();
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({"args": ["--headless=new", "--no-sandbox", "--disable-gpu",
                        "--disable-dev-shm-usage", "--window-size=1100,900",
                        "--enable-unsafe-swiftshader"]}),
    );
    caps.insert("goog:loggingPrefs".into(), json!({"browser": "ALL"}));
    let c = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(caps)
        .connect(&d.url)
        .await
        .expect("a session of headless Chromium");
    let site = format!("http://{addr}");

    // The line; then an image that fails to load does show in the console (the check can
    // fail).
    open_clean(&c, &format!("{site}/")).await;
    c.execute(
        "var s = document.createElement('img'); s.src = '/no-such-image.png'; \
         document.body.appendChild(s);",
        vec![],
    )
    .await
    .unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let log = console(&c).await;
    assert!(
        log.iter().any(|l| l.contains("404")),
        "a failed image load is not in the log: {log:?}"
    );

    // The line, the board, from the board's list to the pad.
    open_clean(&c, &format!("{site}/")).await;
    let title = c.title().await.unwrap();
    assert_eq!(title, "Line line-1 - dpsa");
    shot(&c, "line").await;
    click_to(
        &c,
        &format!("a[href='/board/{}']", ids[1]),
        &format!("/board/{}", ids[1]),
    )
    .await;
    // The same board on the site with its program and maps: drawn, with its measured map.
    open_clean(&c, &format!("http://{map_addr}/board/{}", ids[1])).await;
    // The measured map: its tiles load (no error in the console), each call's ring sits on
    // its paste, zooming in and out changes the pyramid's level and loads that level's tiles.
    let tiles_at = |c: &Client| {
        let c = c.clone();
        async move {
            wait_for(
                &c,
                "const r = document.getElementById('mapview');                  if (r.dataset.error) { return ['error', r.dataset.error]; }                  if (!r.dataset.level) { return null; }                  const z = r.dataset.level;                  const imgs = [...document.querySelectorAll('#mapframe img.tile')];                  if (imgs.length === 0 || !imgs.every(i => i.complete && i.naturalWidth === 256                      && i.dataset.z === z)) { return null; }                  return [Number(z), Number(r.dataset.levels), imgs.length];",
            )
            .await
        }
    };
    let fit = tiles_at(&c).await;
    assert!(fit[0].is_number(), "the map: {fit}");
    let (z0, levels) = (fit[0].as_u64().unwrap(), fit[1].as_u64().unwrap());
    assert_eq!(levels, 5, "{fit}");
    assert!(z0 < 4, "the whole board drawn from its finest level: {fit}");
    let frame = c.find(Locator::Id("mapframe")).await.unwrap();
    let png_bytes = frame.screenshot().await.unwrap();
    let mut r = png::Decoder::new(std::io::Cursor::new(&png_bytes))
        .read_info()
        .unwrap();
    let mut px = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut px).unwrap();
    let rings = c
        .execute(
            "return [...document.querySelectorAll('a.mapcall')].map(a =>                  [a.getAttribute('href'), parseFloat(a.style.left), parseFloat(a.style.top), a.hidden]);",
            vec![],
        )
        .await
        .unwrap();
    let rings = rings.as_array().unwrap();
    assert_eq!(rings.len(), 2, "{rings:?}");
    let (lo, hi) = c
        .execute(
            "return fetch(document.getElementById('mapview').dataset.map).then(r => r.json())                  .then(j => j.range_um);",
            vec![],
        )
        .await
        .map(|v| (v[0].as_f64().unwrap(), v[1].as_f64().unwrap()))
        .unwrap();
    let paste = dpsa_formats::images::colour(((100.0 - lo) / (hi - lo)).clamp(0.0, 1.0));
    let bare = dpsa_formats::images::colour(((0.0 - lo) / (hi - lo)).clamp(0.0, 1.0));
    let at = |x: f64, y: f64| -> [u8; 3] {
        let (x, y) = (x.round() as usize, y.round() as usize);
        let i = y * info.line_size + x * (info.line_size / info.width as usize);
        [px[i], px[i + 1], px[i + 2]]
    };
    let close = |a: [u8; 3], b: [u8; 3]| (0..3).all(|i| a[i].abs_diff(b[i]) <= 12);
    for ring in rings {
        let (x, y) = (ring[1].as_f64().unwrap(), ring[2].as_f64().unwrap());
        assert_eq!(ring[3], false, "{ring}");
        assert!(
            close(at(x, y), paste),
            "{ring}: {:?} is not the paste's {paste:?}",
            at(x, y)
        );
        // 45 screen px below (90 to 180 map px at this level's scale, the paste reaching 75):
        // bare board, its bow taken off.
        assert!(
            close(at(x, y + 45.0), bare),
            "{ring}: {:?} is not bare board's {bare:?}",
            at(x, y + 45.0)
        );
    }
    c.find(Locator::Id("map-in"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let zoomed = tiles_at(&c).await;
    assert_eq!(zoomed[0].as_u64(), Some(z0 + 1), "{fit} then {zoomed}");
    c.execute(
        "const f = document.getElementById('mapframe');          f.dispatchEvent(new WheelEvent('wheel', {deltaY: 2000, clientX: 300, clientY: 300,          bubbles: true, cancelable: true}));",
        vec![],
    )
    .await
    .unwrap();
    let out = tiles_at(&c).await;
    assert!(out[0].as_u64().unwrap() < z0, "{fit} then {out}");
    c.find(Locator::Id("map-fit"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    assert_eq!(tiles_at(&c).await[0].as_u64(), Some(z0));
    let log = console(&c).await;
    assert!(log.is_empty(), "the board page with its map: {log:?}");
    shot(&c, "board").await;
    open_clean(&c, &format!("{site}/board/{}", ids[1])).await;
    // The first call listed is the failure, pad 2 (U<1>-3).
    let first = c
        .find(Locator::Css("table tr td a[href*='/pad/']"))
        .await
        .unwrap();
    assert_eq!(first.text().await.unwrap(), "U<1>-3");
    first.click().await.unwrap();
    settle(&c).await;
    assert_eq!(
        c.current_url().await.unwrap().path(),
        format!("/board/{}/pad/2", ids[1])
    );
    let log = console(&c).await;
    assert!(log.is_empty(), "the pad page: {log:?}");
    // The pad's image drawn: the crop's PNG decoded by the browser at its size.
    let size = c
        .execute(
            "const i = new Image(); \
             i.src = document.querySelector('image.crop').href.baseVal; \
             return i.decode().then(() => [i.naturalWidth, i.naturalHeight]);",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(size, json!([30, 20]));
    // The 3D view draws: WebGL in the browser, the library from the binary, the heights from
    // their route; the canvas is not blank (a tenth of it or more differs from the clear
    // colour), and nothing went to the console.
    let t0 = Instant::now();
    let drawn = loop {
        let v = c
            .execute(
                "const c = document.getElementById('pad3d');                  if (c.dataset.error) { return ['error', c.dataset.error]; }                  if (!c.dataset.triangles) { return null; }                  const t = document.createElement('canvas'); t.width = c.width;                  t.height = c.height; const x = t.getContext('2d'); x.drawImage(c, 0, 0);                  const d = x.getImageData(0, 0, t.width, t.height).data; let n = 0;                  for (let i = 0; i < d.length; i += 4) {                    if (Math.abs(d[i] - 247) + Math.abs(d[i + 1] - 247) + Math.abs(d[i + 2] - 250) > 30) { n++; } }                  return [Number(c.dataset.triangles), n, d.length / 4];",
                vec![],
            )
            .await
            .unwrap();
        if !v.is_null() {
            break v;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "the 3D view never drew"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(drawn[0].is_number(), "the 3D view: {drawn}");
    let (triangles, lit, all) = (
        drawn[0].as_f64().unwrap(),
        drawn[1].as_f64().unwrap(),
        drawn[2].as_f64().unwrap(),
    );
    // 30 x 20 samples, the first column invalid: 28 x 19 cells of two triangles.
    assert_eq!(triangles, 2.0 * 28.0 * 19.0, "{drawn}");
    assert!(lit > 0.1 * all, "the 3D view is blank: {drawn}");
    let log = console(&c).await;
    assert!(log.is_empty(), "the pad page with its 3D view: {log:?}");

    // A review from the form.
    for (field, text) in [
        ("reviewer", "Operator 7"),
        ("note", "paste on the mask, pad fine"),
    ] {
        c.find(Locator::Css(&format!("input[name='{field}']")))
            .await
            .unwrap()
            .send_keys(text)
            .await
            .unwrap();
    }
    click_to(
        &c,
        "button[value='false_call']",
        &format!("/board/{}/pad/2", ids[1]),
    )
    .await;
    let src = c.source().await.unwrap();
    assert!(
        src.contains("Operator 7") && src.contains("false call"),
        "{src}"
    );
    shot(&c, "pad").await;
    let stored = Store::open(&loc, "line-1")
        .unwrap()
        .reviews(ids[1])
        .unwrap();
    assert_eq!(stored.len(), 1);
    assert_eq!(
        (
            stored[0].pad,
            stored[0].decision,
            stored[0].reviewer.as_str()
        ),
        (2, Decision::FalseCall, "Operator 7")
    );
    assert_eq!(
        stored[0].note.as_deref(),
        Some("paste on the mask, pad fine")
    );
    // The line counts it.
    open_clean(&c, &format!("{site}/")).await;
    assert!(c.source().await.unwrap().contains("100.0 %"));
    // The SPC page, from the header's link.
    click_to(&c, "header a.nav", "/spc").await;
    assert_eq!(c.title().await.unwrap(), "SPC: mini - dpsa");
    settle(&c).await;
    shot(&c, "spc").await;

    c.close().await.unwrap();
    drop(d);
    stop.send(()).unwrap();
    h.join().unwrap();
    map_stop.send(()).unwrap();
    map_h.join().unwrap();
}
