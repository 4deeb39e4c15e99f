//! Streams of every codec intra period the docs name (1, the default; 2; 8; 32, the codec
//! benchmark's) through the command line (issue 19): `dpsa reconstruct` and `dpsa target-run`
//! (the firmware under QEMU) write them, `dpsa decode` decodes every row with nothing corrupt,
//! and the heights are those of the intra-period-1 stream and of the core's rows in memory.
//! `--intra-period 0` is refused. A predicted row is never decoded against a row from before a
//! loss, even a loss of 256 rows (which the codec's 8-bit row sequence cannot see).
//!
//! The firmware runs need QEMU and the Cortex-M7 build (`bash firmware/build.sh --install`);
//! without them they fail with that advice unless `DPSA_SKIP_FIRMWARE=1` is set.

use dpsa_core::packets::{self, codec};
use dpsa_sim::heightmap::HeightRow;
use dpsa_sim::simulation::recording::Recording;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The intra periods README.md and docs/stream.md name.
const PERIODS: [u32; 4] = [1, 2, 8, packets::PREDICTED_INTRA_PERIOD];

fn dpsa(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(args)
        .output()
        .expect("run the dpsa binary")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

#[track_caller]
fn ok(args: &[&str]) -> String {
    let out = dpsa(args);
    let (so, se) = (text(&out.stdout), text(&out.stderr));
    assert!(
        out.status.success(),
        "dpsa {args:?} failed ({}):\nstdout: {so}\nstderr: {se}",
        out.status
    );
    so
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn skip_firmware() -> bool {
    let skip = std::env::var("DPSA_SKIP_FIRMWARE").is_ok_and(|v| v == "1");
    if skip {
        eprintln!("DPSA_SKIP_FIRMWARE=1: firmware test skipped");
    }
    skip
}

/// A small recording (W = 96, 432 board rows: more than 256, so the codec's 8-bit row
/// sequence wraps inside runs of predicted rows).
fn small_recording(dir: &Path) -> PathBuf {
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, "width = 96\nboard_length = 320\ndeposits = 8\n").unwrap();
    let rec = dir.join("rec");
    ok(&[
        "--quiet",
        "simulate",
        "--scene",
        s(&scene),
        "--seed",
        "2",
        "--out",
        s(&rec),
    ]);
    rec
}

/// Row packets of `stream` whose payload is a predicted row.
fn predicted_rows(stream: &[u8]) -> usize {
    packets::Stream::new(stream)
        .filter(|item| match item {
            packets::Item::Packet { packet, .. } => {
                packet.kind == packets::Kind::Row
                    && codec::peek(packet.payload)
                        .is_ok_and(|(k, _)| k == codec::RowKind::Predicted)
            }
            packets::Item::Damage { .. } => false,
        })
        .count()
}

/// `dpsa decode STREAM --json --png PNG`: the stream decodes cleanly, every row packet gives a
/// row; returns the rows decoded.
#[track_caller]
fn decodes_cleanly(what: &str, stream: &Path, png: &Path) -> u64 {
    let out = dpsa(&["--quiet", "decode", s(stream), "--json", "--png", s(png)]);
    let v: Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{what}: {e}: {}", text(&out.stderr)));
    assert_eq!(out.status.code(), Some(0), "{what}: {v}");
    assert_eq!(v["packets"]["corrupt"], 0, "{what}: {v}");
    assert_eq!(v["stream"]["rows_missing"], 0, "{what}: {v}");
    let rows = v["rows"]["decoded"].as_u64().unwrap();
    assert_eq!(
        v["stream"]["end_totals"]["rows"].as_u64(),
        Some(rows),
        "{what}: {v}"
    );
    // Rows, one trigger record per frame, the stream header and the end packet.
    let triggers = v["stream"]["triggers"].as_u64().unwrap();
    assert!(triggers > 0, "{what}: {v}");
    assert_eq!(
        v["packets"]["ok"].as_u64(),
        Some(rows + triggers + 2),
        "{what}: {v}"
    );
    rows
}

#[test]
fn reconstruct_and_decode_every_documented_intra_period() {
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    // The reference: the core's rows as they leave it, before any coding.
    let recording = Recording::open(&rec).unwrap();
    let mut core_rows: Vec<HeightRow> = Vec::new();
    dpsa_sim::reconstruct::reconstruct_rows(&recording, false, |r| {
        core_rows.push(r);
        Ok(())
    })
    .unwrap();
    assert!(core_rows.len() > 300, "{} rows", core_rows.len());

    let mut sizes = Vec::new();
    for k in PERIODS {
        let stream = dir.path().join(format!("k{k}.dpsa"));
        let rec_png = dir.path().join(format!("k{k}.reconstruct.png"));
        let png = dir.path().join(format!("k{k}.png"));
        let ks = k.to_string();
        ok(&[
            "--quiet",
            "reconstruct",
            s(&rec),
            "--intra-period",
            &ks,
            "--out",
            s(&stream),
            "--png",
            s(&rec_png),
        ]);
        let bytes = std::fs::read(&stream).unwrap();
        sizes.push(bytes.len());
        let predicted = predicted_rows(&bytes);
        if k == 1 {
            assert_eq!(predicted, 0);
        } else {
            // An intra row at least every K rows, and most rows predicted.
            let at_least = core_rows.len() - core_rows.len().div_ceil(k as usize);
            assert!(predicted >= at_least, "K {k}: {predicted} predicted rows");
        }
        let rows = decodes_cleanly(&format!("K {k}"), &stream, &png);
        assert_eq!(rows, core_rows.len() as u64, "K {k}");
        // The decoded heights are the core's rows, whatever the intra period.
        let (map, rep) = dpsa_sim::stream::decode_stream(&bytes, 0.25);
        assert_eq!(rep.corrupt, 0, "K {k}");
        assert_eq!(rep.stream.intra_period, Some(k));
        assert_eq!(map.rows.len(), core_rows.len(), "K {k}");
        for (a, b) in map.rows.iter().zip(&core_rows) {
            assert_eq!(
                (a.row, a.latch, a.flags, &a.valid, &a.heights),
                (b.row, b.latch, b.flags, &b.valid, &b.heights),
                "K {k}"
            );
        }
        // The PNGs of `decode` and of `reconstruct --png` are the intra-period-1 stream's.
        let first = std::fs::read(dir.path().join("k1.png")).unwrap();
        assert!(std::fs::read(&png).unwrap() == first, "K {k}: decode PNG");
        assert!(
            std::fs::read(&rec_png).unwrap() == first,
            "K {k}: reconstruct PNG"
        );
    }
    // Predicted rows make smaller streams.
    assert!(sizes[1..].iter().all(|&n| n < sizes[0]), "{sizes:?}");
}

#[test]
fn target_run_streams_of_every_documented_intra_period_decode() {
    if skip_firmware() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    let mut first_png = None;
    for k in PERIODS {
        let ks = k.to_string();
        let host = dir.path().join(format!("host{k}.dpsa"));
        let target = dir.path().join(format!("target{k}.dpsa"));
        ok(&[
            "--quiet",
            "reconstruct",
            s(&rec),
            "--intra-period",
            &ks,
            "--out",
            s(&host),
        ]);
        let out = dpsa(&[
            "--quiet",
            "target-run",
            s(&rec),
            "--intra-period",
            &ks,
            "--out",
            s(&target),
        ]);
        assert!(
            out.status.success(),
            "target-run --intra-period {k} failed; it needs QEMU and the Cortex-M7 build: run \
             `bash firmware/build.sh --install` or set DPSA_SKIP_FIRMWARE=1.\n{}",
            text(&out.stderr)
        );
        let bytes = std::fs::read(&target).unwrap();
        assert!(
            bytes == std::fs::read(&host).unwrap(),
            "K {k}: the firmware's stream differs from the host's"
        );
        assert_eq!(predicted_rows(&bytes) > 0, k > 1, "K {k}");
        let png = dir.path().join(format!("target{k}.png"));
        let rows = decodes_cleanly(&format!("target K {k}"), &target, &png);
        assert!(rows > 300, "K {k}: {rows} rows");
        let png = std::fs::read(&png).unwrap();
        let first = first_png.get_or_insert_with(|| png.clone());
        assert!(png == *first, "K {k}: heights differ from K 1");
    }
}

#[test]
fn intra_period_zero_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    let out_file = dir.path().join("zero.dpsa");
    for cmd in ["reconstruct", "target-run"] {
        let out = dpsa(&[cmd, s(&rec), "--intra-period", "0", "--out", s(&out_file)]);
        let se = text(&out.stderr);
        assert!(!out.status.success(), "{cmd}: {se}");
        assert!(
            se.contains("--intra-period") && se.contains("must be at least 1"),
            "{cmd}: {se}"
        );
        assert!(!se.contains("panicked"), "{cmd}: {se}");
        assert!(!out_file.exists(), "{cmd} wrote {}", out_file.display());
    }
    // Not a number.
    let out = dpsa(&[
        "reconstruct",
        s(&rec),
        "--intra-period",
        "eight",
        "--out",
        s(&out_file),
    ]);
    let se = text(&out.stderr);
    assert!(
        !out.status.success() && se.contains("whole number of rows"),
        "{se}"
    );
    // The library refuses it too.
    let recording = Recording::open(&rec).unwrap();
    let e = dpsa_sim::reconstruct::run_with(&recording, Vec::new(), 0, false)
        .expect_err("intra period 0 accepted");
    assert!(e.to_string().contains("at least 1"), "{e}");
}

/// A predicted stream (intra period 1000: no intra row after the first) that lost exactly 256
/// consecutive row packets: the codec's 8-bit row sequence wraps round and would take the row
/// after the loss for the next one; the decoder sees the packet sequence jump and reports the
/// rows after the loss as lost instead of decoding them against the wrong reference.
#[test]
fn a_loss_of_256_predicted_rows_is_not_decoded_against_the_wrong_reference() {
    use dpsa_core::row::{Row, RowHeader, StreamInfo};
    use dpsa_core::Sink as _;
    let w = 64usize;
    let n_rows = 600usize;
    // Smooth rows, each 0 to 2 LSB above its neighbours: every pixel is coded in the same
    // Rice context whichever row is the reference, so a row decoded against the wrong one
    // parses and comes out wrong by a little, not as a corrupt payload.
    let rows: Vec<Vec<i16>> = (0..n_rows)
        .map(|r| {
            (0..w)
                .map(|c| 100 + (r % 3) as i16 + (c / 4) as i16)
                .collect()
        })
        .collect();
    let valid = vec![0xFFu8; w / 8];
    let mut reference = codec::ReferenceRow::new(w);
    let enc = reference.encoder(1000).unwrap();
    let mut buf = vec![0u8; packets::max_packet_len(w)];
    let mut sink =
        dpsa_core::sink::PacketSink::new(dpsa_sim::reconstruct::IoLink(Vec::new()), enc, &mut buf);
    sink.start(&StreamInfo {
        camera: 0,
        n: 4,
        width: w as u16,
        rows: 40,
        max_step_rows: 10,
        ..StreamInfo::default()
    })
    .unwrap();
    for (r, h) in rows.iter().enumerate() {
        let header = RowHeader {
            camera: 0,
            n: 4,
            row: r as i64,
            latch: 0,
            flags: 0,
            width: w as u16,
        };
        sink.row(&Row {
            header,
            heights: h,
            valid: &valid,
        })
        .unwrap();
    }
    sink.end().unwrap();
    let stream = sink.into_link().0;
    // Drop the row packets of board rows 100 ..= 355 (256 rows; row r is packet r + 1).
    let mut damaged = Vec::new();
    let mut pos = 0;
    while pos < stream.len() {
        let (p, len) = packets::decode(&stream[pos..]).unwrap();
        let lost = p.kind == packets::Kind::Row && (100..356).contains(&p.header.row);
        if !lost {
            damaged.extend_from_slice(&stream[pos..pos + len]);
        }
        pos += len;
    }
    // The whole stream decodes (predicted rows, one intra row).
    let (map, rep) = dpsa_sim::stream::decode_stream(&stream, 0.25);
    assert_eq!((rep.corrupt, map.rows.len()), (0, n_rows));
    let (map, rep) = dpsa_sim::stream::decode_stream(&damaged, 0.25);
    assert_eq!(rep.stream.missing, 256, "{:?}", rep.stream);
    // Every row that decodes is the row that was sent.
    for r in &map.rows {
        assert_eq!(r.heights, rows[r.row as usize], "board row {}", r.row);
    }
    // Rows before the loss decode; the rows after it are lost (no intra row follows).
    assert_eq!(map.rows.len(), 100);
    assert_eq!(rep.corrupt, n_rows - 356);
}
