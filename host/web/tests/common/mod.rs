//! What the page tests and the browser test share: a store written by the store's own API,
//! the site on a loopback port, a plain HTTP/1.1 client.
#![allow(dead_code)]

use dpsa_inspect::crop::PadCrop;
use dpsa_inspect::print::PrintOffset;
use dpsa_line::printer::{Correction, Proposal};
use dpsa_line::store::{
    BoardStart, CameraLoss, Location, Outcome, PadImage, PadRow, PrintRow, Store,
};
use dpsa_web::Site;
use std::io::{Read, Write};
use std::net::TcpStream;

pub fn pad(k: u32, name: &str, level: &str, volume_pct: Option<f64>) -> PadRow {
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

pub fn print_row(x: f64) -> PrintRow {
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

/// Pad `k`'s kept heights: 30 x 20 samples of 25 um, a 0.5 x 0.25 mm deposit of `paste_um`
/// on a bare board at 0 in the middle, the first column invalid.
pub fn image(k: u32, family: &str, paste_um: f32) -> PadImage {
    let (nx, ny) = (30, 20);
    PadImage {
        pad: k,
        family: Some(family.to_owned()),
        crop: PadCrop {
            x0_mm: 4.0,
            y0_mm: 6.0,
            pitch_mm: 0.025,
            nx,
            ny,
            heights_um: (0..nx * ny)
                .map(|s| {
                    let (ix, iy) = (s / ny, s % ny);
                    if ix == 0 {
                        f32::NAN
                    } else if (5..25).contains(&ix) && (5..15).contains(&iy) {
                        paste_um
                    } else {
                        0.0
                    }
                })
                .collect(),
            outline: dpsa_gerber::pads::Outline::RoundRect {
                centre: [4.3625, 6.2375],
                size: [0.5, 0.25],
                radius: 0.0,
                rotation_deg: 0.0,
            },
        },
    }
}

/// A store of three boards of line `line-1`: two inspected (the second with a warning and a
/// failure, one pad named to test the escaping, and both pads' heights kept), one incomplete;
/// and a board of line `other`.
pub fn store(dir: &std::path::Path) -> (Location, Vec<i64>) {
    store_of(dir, "p")
}

/// [`store`] with its boards under the program of hash `program_hash`.
pub fn store_of(dir: &std::path::Path, program_hash: &str) -> (Location, Vec<i64>) {
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
                program_hash: program_hash.into(),
                calibration_hash: "c".into(),
                started_unix_s: 1_700_000_000.0 + 30.0 * k as f64,
            })
            .unwrap();
        let verdict = if k == 0 { "pass" } else { "fail" };
        let images = if k == 0 {
            vec![]
        } else {
            vec![image(1, "R_0603", 72.0), image(2, "QFN-16", 31.0)]
        };
        s.finish_board_with_images(
            id,
            1_700_000_010.0 + 30.0 * k as f64,
            &cams,
            &Outcome::Inspected {
                verdict: verdict.into(),
                pads,
            },
            Some(&print_row(12.5 * k as f64)),
            &images,
        )
        .unwrap();
        ids.push(id);
    }
    let id = s
        .begin_board(&BoardStart {
            run_id: 0xa3,
            product: "mini".into(),
            program_hash: program_hash.into(),
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
            program_hash: program_hash.into(),
            calibration_hash: "c".into(),
            started_unix_s: 1_700_000_000.0,
        })
        .unwrap();
    ids.push(id);
    (loc, ids)
}

/// The site on a loopback port in a thread of its own; its address and its stop.
pub fn serve(
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
pub fn get(addr: &str, path: &str) -> (u16, Vec<(String, String)>, String) {
    let (st, h, body) = request(addr, "GET", path, &[], "");
    (st, h, String::from_utf8_lossy(&body).into_owned())
}

/// A request with `headers` and a `body` (form-encoded when not empty): status, headers
/// (lowercase names), body bytes.
pub fn request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> (u16, Vec<(String, String)>, Vec<u8>) {
    let mut s = TcpStream::connect(addr).unwrap();
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    if method == "POST" {
        head.push_str(&format!(
            "Content-Type: application/x-www-form-urlencoded\r\nContent-Length: {}\r\n",
            body.len()
        ));
    }
    head.push_str("\r\n");
    s.write_all(head.as_bytes()).unwrap();
    s.write_all(body.as_bytes()).unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let split = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a response head");
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let body = raw[split + 4..].to_vec();
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
    (status, headers, body)
}

pub fn header<'a>(h: &'a [(String, String)], name: &str) -> Option<&'a str> {
    h.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

/// Keeps a measured map for line `line`'s board `board` of run id `run` in `dir` as the line
/// does: `rows x
/// width` pixels of `pitch_mm` from the board's origin, a board bowed by 20 um along x, and a
/// 100 um deposit of 0.4 x 0.3 mm centred on each of `deposits` (board mm).
pub fn kept_map(
    dir: &std::path::Path,
    line: &str,
    (board, run): (i64, u64),
    (rows, width, pitch_mm): (usize, usize, f64),
    deposits: &[(f64, f64)],
    design_to_board: Option<dpsa_formats::kept_map::DesignToBoard>,
) -> dpsa_formats::kept_map::KeptMap {
    let grid = dpsa_formats::grid::BoardGrid {
        x0_mm: 0.0,
        y0_mm: 0.0,
        pitch_mm,
        rows,
        width,
    };
    let mut data = vec![0f32; rows * width];
    for r in 0..rows {
        for c in 0..width {
            let (x, y) = grid.centre(r, c);
            let t = r as f64 / rows as f64 - 0.5;
            let mut h = 20.0 * (1.0 - 4.0 * t * t);
            if deposits
                .iter()
                .any(|&(dx, dy)| (x - dx).abs() < 0.2 && (y - dy).abs() < 0.15)
            {
                h += 100.0;
            }
            data[r * width + c] = h as f32;
        }
    }
    let heights = dpsa_formats::grid::Grid { width, rows, data };
    std::fs::create_dir_all(dir).unwrap();
    dpsa_formats::kept_map::write(dir, line, board, run, &grid, &heights, design_to_board).unwrap()
}

/// The test's program: three openings (a 0.6 x 0.3 mm rectangle at (1, 1) and (2, 1), a
/// 0.4 mm disc at (3, 2)) in `dir/paste.gbr`, its program `dir/program.toml` (returned).
pub fn mini_program(dir: &std::path::Path) -> std::path::PathBuf {
    std::fs::write(
        dir.join("paste.gbr"),
        "%FSLAX46Y46*%\n%MOMM*%\n%ADD10R,0.6X0.3*%\n%ADD11C,0.4*%\nD10*\n\
         X1000000Y1000000D03*\nX2000000Y1000000D03*\nD11*\nX3000000Y2000000D03*\nM02*\n",
    )
    .unwrap();
    let prog = dir.join("program.toml");
    std::fs::write(&prog, "paste_layer = \"paste.gbr\"\nstencil_um = 100.0\n").unwrap();
    prog
}

/// Inspected boards of line `line-1` in `loc`, one per `(run id, program hash)`, each with
/// [`mini_program`]'s three pads: R1-1 passed, R1-2 warned, U<1>-3 failed. Their ids.
pub fn mini_boards(loc: &Location, boards: &[(u64, &str)]) -> Vec<i64> {
    let mut s = Store::open(loc, "line-1").unwrap();
    let mut ids = Vec::new();
    for &(run, hash) in boards {
        let id = s
            .begin_board(&BoardStart {
                run_id: run,
                product: "mini".into(),
                program_hash: hash.into(),
                calibration_hash: "c".into(),
                started_unix_s: 1_700_000_000.0,
            })
            .unwrap();
        s.finish_board(
            id,
            1_700_000_001.0,
            &[],
            &Outcome::Inspected {
                verdict: "fail".into(),
                pads: vec![
                    pad(0, "R1-1", "pass", Some(100.0)),
                    pad(1, "R1-2", "warn", Some(72.0)),
                    pad(2, "U<1>-3", "fail", Some(31.0)),
                ],
            },
        )
        .unwrap();
        ids.push(id);
    }
    ids
}
