//! The pages over a store written by the store's own API, served on a loopback port and read
//! by a plain HTTP/1.1 client: what each page shows, the links, the headers, what is refused,
//! and that serving leaves the store as it was.

use dpsa_inspect::print::PrintOffset;
use dpsa_line::printer::{Correction, Proposal};
use dpsa_line::store::{BoardStart, CameraLoss, Location, Outcome, PadRow, PrintRow, Store};
use dpsa_web::Site;
use std::io::{Read, Write};
use std::net::TcpStream;

fn pad(k: u32, name: &str, level: &str, volume_pct: Option<f64>) -> PadRow {
    PadRow {
        pad: k,
        name: name.to_owned(),
        level: level.to_owned(),
        class: (level != "pass").then(|| "insufficient".to_owned()),
        volume_um3: volume_pct.map(|v| v * 1e5),
        volume_pct,
        area_mm2: Some(0.1),
        area_pct: Some(99.0),
        height_um: Some(98.0),
        height_pct: Some(98.0),
        offset_x_um: Some(3.0),
        offset_y_um: Some(-2.0),
        coverage: 1.0,
        uncertainty_um3: volume_pct.map(|_| 1.5e5),
    }
}

fn print_row(x: f64) -> PrintRow {
    let c = |v: f64| Correction {
        x_um: v,
        y_um: -v,
        rotation_mdeg: 0.0,
    };
    PrintRow {
        placement: Some(PrintOffset {
            x_um: x,
            y_um: -4.0,
            rotation_mdeg: 1.5,
            stretch_ppm: 10.0,
            uncertainty: [0.4, 0.4, 2.0, 40.0],
            centre_mm: [10.0, 7.0],
            pads: 3,
            outliers: 0,
            scale_um: 2.0,
        }),
        proposal: Proposal {
            correction: c(x),
            change: c(x),
            estimate: c(x),
            estimate_uncertainty: c(0.4),
            held: [false, false, true],
            limited: [false; 3],
            reason: "x +12.5; y -12.5".to_owned(),
        },
    }
}

/// A store of three boards of line `line-1`: two inspected (the second with a warning and a
/// failure, one pad named to test the escaping), one incomplete; and a board of line `other`.
fn store(dir: &std::path::Path) -> (Location, Vec<i64>) {
    let loc = Location::Sqlite(dir.join("line.sqlite"));
    let mut s = Store::open(&loc, "line-1").unwrap();
    let cams = vec![CameraLoss {
        camera: 0,
        rows: 100,
        missing_rows: 2,
        missing_packets: 1,
        damaged_packets: 0,
    }];
    let mut ids = Vec::new();
    for (k, (run, pads)) in [
        (
            0xa1u64,
            vec![
                pad(0, "R1-1", "pass", Some(101.0)),
                pad(1, "R1-2", "pass", Some(99.0)),
                pad(2, "U<1>-3", "pass", Some(97.0)),
            ],
        ),
        (
            0xa2,
            vec![
                pad(0, "R1-1", "pass", Some(100.0)),
                pad(1, "R1-2", "warn", Some(72.0)),
                pad(2, "U<1>-3", "fail", Some(31.0)),
            ],
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let id = s
            .begin_board(&BoardStart {
                run_id: run,
                product: "mini".into(),
                program_hash: "p".into(),
                calibration_hash: "c".into(),
                started_unix_s: 1_700_000_000.0 + 30.0 * k as f64,
            })
            .unwrap();
        let verdict = if k == 0 { "pass" } else { "fail" };
        s.finish_board_with_print(
            id,
            1_700_000_010.0 + 30.0 * k as f64,
            &cams,
            &Outcome::Inspected {
                verdict: verdict.into(),
                pads,
            },
            Some(&print_row(12.5 * k as f64)),
        )
        .unwrap();
        ids.push(id);
    }
    let id = s
        .begin_board(&BoardStart {
            run_id: 0xa3,
            product: "mini".into(),
            program_hash: "p".into(),
            calibration_hash: "c".into(),
            started_unix_s: 1_700_000_060.0,
        })
        .unwrap();
    s.finish_board(
        id,
        1_700_000_070.0,
        &cams,
        &Outcome::Incomplete {
            reason: "camera 2 silent for 5 s".into(),
        },
    )
    .unwrap();
    ids.push(id);
    let mut other = Store::open(&loc, "other").unwrap();
    let id = other
        .begin_board(&BoardStart {
            run_id: 0xb1,
            product: "mini".into(),
            program_hash: "p".into(),
            calibration_hash: "c".into(),
            started_unix_s: 1_700_000_000.0,
        })
        .unwrap();
    ids.push(id);
    (loc, ids)
}

/// The site on a loopback port in a thread of its own; its address and its stop.
fn serve(
    site: Site,
) -> (
    String,
    tokio::sync::oneshot::Sender<()>,
    std::thread::JoinHandle<()>,
) {
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let (atx, arx) = std::sync::mpsc::channel();
    let h = std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async move {
            let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            atx.send(l.local_addr().unwrap().to_string()).unwrap();
            dpsa_web::serve_on(l, site, async {
                let _ = rx.await;
            })
            .await
            .unwrap();
        });
    });
    (arx.recv().unwrap(), tx, h)
}

/// GET `path`: status, headers (lowercase names), body.
fn get(addr: &str, path: &str) -> (u16, Vec<(String, String)>, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let text = String::from_utf8_lossy(&raw).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap();
    let mut lines = head.lines();
    let status = lines
        .next()
        .unwrap()
        .split(' ')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    let headers = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_owned()))
        .collect();
    (status, headers, body.to_owned())
}

fn header<'a>(h: &'a [(String, String)], name: &str) -> Option<&'a str> {
    h.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

#[test]
fn the_pages_show_the_line_a_board_and_a_pad() {
    let dir = tempfile::tempdir().unwrap();
    let (loc, ids) = store(dir.path());
    let Location::Sqlite(file) = &loc else {
        unreachable!()
    };
    let before = std::fs::read(file).unwrap();
    let (addr, stop, h) = serve(Site {
        store: loc.clone(),
        line: "line-1".into(),
    });

    // The line: its three boards newest first, linked; the yield of the inspected ones; the
    // incomplete board's reason; the printer's newest correction. Not the other line's.
    let (st, hd, body) = get(&addr, "/");
    assert_eq!(st, 200);
    assert_eq!(
        header(&hd, "content-type"),
        Some("text/html; charset=utf-8")
    );
    assert_eq!(header(&hd, "content-security-policy"), Some(dpsa_web::CSP));
    assert_eq!(header(&hd, "x-content-type-options"), Some("nosniff"));
    let table = &body[body.find("Newest boards").unwrap()..];
    let rows: Vec<usize> = ["00000000000000a3", "00000000000000a2", "00000000000000a1"]
        .iter()
        .map(|r| {
            table
                .find(r)
                .unwrap_or_else(|| panic!("{r} not on the line page: {body}"))
        })
        .collect();
    assert!(rows[0] < rows[1] && rows[1] < rows[2], "not newest first");
    assert!(
        !body.contains("00000000000000b1"),
        "another line's board shown"
    );
    for id in &ids[..3] {
        assert!(body.contains(&format!("href=\"/board/{id}\"")), "{body}");
    }
    assert!(body.contains("<b>50.0 %</b>"), "yield: {body}");
    assert!(body.contains("camera 2 silent for 5 s"));
    assert!(body.contains("x 12.5 um"), "printer: {body}");
    // 2 boards an hour apart in 60 s: 120 an hour.
    assert!(body.contains("<b>120.0</b> boards an hour"), "{body}");

    // A board: its failures first, linked to their pads, the name escaped; its print.
    let (st, _, body) = get(&addr, &format!("/board/{}", ids[1]));
    assert_eq!(st, 200);
    let fail = body.find("U&lt;1&gt;-3").expect("escaped pad name");
    let warn = body.find(">R1-2<").expect("the warned pad");
    assert!(fail < warn, "failures first");
    assert!(!body.contains("U<1>-3"));
    assert!(body.contains(&format!("href=\"/board/{}/pad/2\"", ids[1])));
    assert!(!body.contains(">R1-1<"), "a passed pad listed");
    assert!(body.contains("Placement x 12.5"), "{body}");
    // Volume uncertainty in points: 1.5e5 um^3 of a nominal 1e7.
    assert!(body.contains("<td>1.5</td>"), "{body}");
    let (_, _, inc) = get(&addr, &format!("/board/{}", ids[2]));
    assert!(inc.contains("Never inspected: camera 2 silent"));

    // A pad: its values and its history over both inspected boards, this one marked.
    let (st, _, body) = get(&addr, &format!("/board/{}/pad/2", ids[1]));
    assert_eq!(st, 200);
    assert!(body.contains("Pad U&lt;1&gt;-3"), "{body}");
    assert!(body.contains("<td>31.0</td>"));
    assert_eq!(body.matches("<circle").count(), 2);
    assert!(body.contains("1 of 2 failed"));

    // Refused: unknown boards and pads, another line's board, paths that are no page.
    for path in [
        "/board/999999".to_owned(),
        "/board/abc".to_owned(),
        format!("/board/{}", ids[3]),
        format!("/board/{}/pad/9", ids[1]),
        format!("/board/{}/pad/-1", ids[1]),
        "/style.css/../../Cargo.toml".to_owned(),
        "/%2e%2e/%2e%2e/etc/passwd".to_owned(),
        "/../line.sqlite".to_owned(),
    ] {
        let (st, hd, _) = get(&addr, &path);
        assert_eq!(st, 404, "{path}");
        assert_eq!(header(&hd, "content-security-policy"), Some(dpsa_web::CSP));
    }
    let (st, hd, css) = get(&addr, "/style.css");
    assert_eq!(st, 200);
    assert_eq!(header(&hd, "content-type"), Some("text/css; charset=utf-8"));
    assert!(css.contains(".fail"));

    stop.send(()).unwrap();
    h.join().unwrap();
    // Serving wrote nothing.
    assert_eq!(std::fs::read(file).unwrap(), before);
}

/// A store the pages cannot read gives an error page, not a panic or an empty line.
#[test]
fn a_store_that_is_gone_is_said() {
    let dir = tempfile::tempdir().unwrap();
    let (addr, stop, h) = serve(Site {
        store: Location::Sqlite(dir.path().join("none.sqlite")),
        line: "line-1".into(),
    });
    let (st, _, body) = get(&addr, "/");
    assert_eq!(st, 503);
    assert!(body.contains("could not be read"), "{body}");
    assert!(!dir.path().join("none.sqlite").exists());
    stop.send(()).unwrap();
    h.join().unwrap();
}
