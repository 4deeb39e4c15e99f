//! `dpsa decode` on damaged and hostile streams (issue 9, items 1, 2, 7, 10, 11): the reproductions
//! run the `dpsa` binary; the big hostile inputs run under `prlimit --as=512 MiB` when prlimit is
//! available. No test measures time: they must complete (linear time), and `cargo test`'s own
//! timeout is the bound.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("dpsa-decode-hostile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run(args: &[&str], cap_memory: bool) -> Output {
    let bin = env!("CARGO_BIN_EXE_dpsa");
    let prlimit = cap_memory
        && Command::new("prlimit")
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success());
    let mut c = if prlimit {
        let mut c = Command::new("prlimit");
        c.arg("--as=536870912").arg(bin);
        c
    } else {
        Command::new(bin)
    };
    c.args(args).output().expect("run dpsa")
}

/// `dpsa decode FILE --json`: (exit status, JSON).
fn decode(file: &Path, cap_memory: bool) -> (i32, Value) {
    let out = run(
        &["--quiet", "decode", file.to_str().unwrap(), "--json"],
        cap_memory,
    );
    let se = String::from_utf8_lossy(&out.stderr);
    assert!(!se.contains("panicked"), "{se}");
    let v: Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}\n{se}", String::from_utf8_lossy(&out.stdout)));
    (out.status.code().expect("exit status"), v)
}

/// A small recording reconstructed into a stream; returns (dir, stream bytes).
fn stream() -> (PathBuf, Vec<u8>) {
    let d = dir("rec");
    let scene = d.join("scene.toml");
    std::fs::write(&scene, "width = 64\nboard_length = 120\n").unwrap();
    let rec = d.join("rec");
    let out = run(
        &[
            "--quiet",
            "simulate",
            "--scene",
            scene.to_str().unwrap(),
            "--seed",
            "3",
            "--out",
            rec.to_str().unwrap(),
        ],
        false,
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let s = d.join("r.dpsa");
    let out = run(
        &[
            "--quiet",
            "reconstruct",
            rec.to_str().unwrap(),
            "--out",
            s.to_str().unwrap(),
        ],
        false,
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes = std::fs::read(&s).unwrap();
    (d, bytes)
}

/// Packets of a well-formed version 2 stream (docs/stream.md: 40-byte header, `L` at 32..36).
fn packets(bytes: &[u8]) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut pos = 0;
    while pos < bytes.len() {
        let plen = u32::from_le_bytes(bytes[pos + 32..pos + 36].try_into().unwrap()) as usize;
        out.push(bytes[pos..pos + 40 + plen + 4].to_vec());
        pos += 40 + plen + 4;
    }
    out
}

fn board_row(p: &[u8]) -> i64 {
    i64::from_le_bytes(p[12..20].try_into().unwrap())
}

#[test]
fn damaged_streams_are_reported_and_rows_keep_their_board_row() {
    let (d, bytes) = stream();
    let (code, v) = decode(&d.join("r.dpsa"), false);
    assert_eq!(code, 0, "{v}");
    assert_eq!(v["stream"]["version"], 2);
    assert_eq!(v["stream"]["truncated"], false);
    let pk = packets(&bytes);
    // Row packets (kinds 0 and 1); the rest are the stream header, the frames' trigger records
    // and the end packet.
    let is_row = |p: &[u8]| p[5] <= 1;
    let rows = pk.iter().filter(|p| is_row(p)).count();
    assert_eq!(
        pk.len() - rows - 2,
        v["stream"]["triggers"].as_u64().unwrap() as usize
    );
    let (clean, _) = dpsa_sim::stream::decode_stream(&bytes, 0.25);
    assert_eq!(clean.rows.len(), rows);

    // One flipped byte in a row packet's payload: that packet is lost and reported missing;
    // every later row keeps its board row (a hole, not a shift).
    let m = (pk.len() / 2..pk.len()).find(|&i| is_row(&pk[i])).unwrap();
    let mut c1 = bytes.clone();
    let at: usize = pk[..m].iter().map(Vec::len).sum::<usize>() + 45;
    c1[at] ^= 0x5a;
    let f = d.join("c1.dpsa");
    std::fs::write(&f, &c1).unwrap();
    let (code, v) = decode(&f, false);
    assert_eq!(code, 2, "{v}");
    assert_eq!(v["stream"]["missing"], 1, "{v}");
    assert_eq!(v["stream"]["rows_missing"], 1, "{v}");
    assert_eq!(v["packets"]["corrupt"], 1, "{v}");
    let (map, _) = dpsa_sim::stream::decode_stream(&c1, 0.25);
    let lost = board_row(&pk[m]);
    assert!(map.get(lost).is_none());
    for r in &clean.rows {
        if r.row != lost {
            assert_eq!(map.get(r.row), Some(r), "row {}", r.row);
        }
    }
    let png = d.join("c1.png");
    let out = run(
        &[
            "--quiet",
            "decode",
            f.to_str().unwrap(),
            "--png",
            png.to_str().unwrap(),
        ],
        false,
    );
    assert_eq!(out.status.code(), Some(2));
    let img = image::open(&png).unwrap();
    assert_eq!(
        img.height() as usize,
        rows,
        "the image keeps a hole for the lost row"
    );

    // A duplicate and a reorder.
    let mut dr = pk.clone();
    dr.insert(m, pk[m].clone());
    dr.swap(m + 3, m + 4);
    let f = d.join("dr.dpsa");
    std::fs::write(&f, dr.concat()).unwrap();
    let (code, v) = decode(&f, false);
    assert_eq!(code, 2, "{v}");
    assert_eq!(v["stream"]["duplicated"], 1, "{v}");
    assert_eq!(v["stream"]["reordered"], 1, "{v}");
    assert_eq!(v["stream"]["missing"], 0, "{v}");
    assert_eq!(v["rows"]["decoded"].as_u64().unwrap() as usize, rows);

    // Cut in the middle: no end packet.
    let f = d.join("cut.dpsa");
    std::fs::write(&f, pk[..m].concat()).unwrap();
    let (code, v) = decode(&f, false);
    assert_eq!(code, 2, "{v}");
    assert_eq!(v["stream"]["truncated"], true, "{v}");
    assert!(v["stream"]["end_totals"].is_null());

    // A stray packet of another width before the good stream costs only itself.
    let mut stray = pk.iter().find(|p| is_row(p)).unwrap().clone();
    stray[30..32].copy_from_slice(&8u16.to_le_bytes());
    let f = d.join("stray.dpsa");
    let mut b = stray;
    b.extend_from_slice(&bytes);
    std::fs::write(&f, &b).unwrap();
    let (_, v) = decode(&f, false);
    assert_eq!(v["rows"]["decoded"].as_u64().unwrap() as usize, rows, "{v}");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn hostile_floods_decode_in_bounded_memory_and_linear_time() {
    let d = dir("flood");
    // 10 MB of repeated "DPSA": every candidate rejected, the damage list capped.
    let f = d.join("dpsa.bin");
    std::fs::write(&f, b"DPSA".repeat(10 << 18)).unwrap();
    let (code, v) = decode(&f, true);
    assert_eq!(code, 3, "nothing decodable");
    assert_eq!(v["packets"]["corrupt"].as_u64(), Some(10 << 18));
    assert_eq!(v["damage"].as_array().unwrap().len(), 100);
    // 1 MB of "DPSA\x01\x8a\x00\x00": rejected from the header (width), no CRC per candidate.
    let f = d.join("v1flood.bin");
    std::fs::write(&f, b"DPSA\x01\x8a\x00\x00".repeat(1 << 17)).unwrap();
    let (code, v) = decode(&f, true);
    assert_eq!(code, 3);
    assert_eq!(v["packets"]["corrupt"].as_u64(), Some(1 << 17));
    // Without --json only the summary line is built.
    let out = run(&["--quiet", "decode", f.to_str().unwrap()], true);
    assert_eq!(out.status.code(), Some(3));
    assert!(out.stdout.len() < 1000);
    // 8 MiB of version 1 headers whose fields all look right (codec 1, width 8192, the
    // largest payload), one every 32 bytes: each would cost a 16 KB CRC, 4 GB in all. The
    // walk's CRC budget (8 bytes per stream byte) stops that; the rest is flagged unchecked.
    let mut head = b"DPSA\x01\x01\x00\x04".to_vec();
    head.extend_from_slice(&[0; 18]);
    head.extend_from_slice(&8192u16.to_le_bytes());
    head.extend_from_slice(&16386u32.to_le_bytes());
    let f = d.join("v1plausible.bin");
    std::fs::write(&f, head.repeat(1 << 18)).unwrap();
    let (code, v) = decode(&f, true);
    assert_eq!(code, 3);
    let damage = v["damage"].to_string();
    assert!(damage.contains("CRC mismatch"), "{damage}");
    assert!(damage.contains("not checked"), "{damage}");
    let _ = std::fs::remove_dir_all(&d);
}

/// A well-formed version 2 stream whose rows compress to almost nothing: 60,000 rows of 8,192
/// pixels (491 Mpx, 1.5 GB as a height map) in a few megabytes. `decode` keeps no heights
/// without `--png` and reports every row; with `--png` it refuses the map above its
/// documented pixel limit instead of running out of memory.
#[test]
fn a_small_stream_of_a_huge_map_decodes_in_bounded_memory() {
    use dpsa_core::packets::{self, codec};
    use dpsa_core::row::{Row, RowHeader, StreamInfo};
    use dpsa_core::Sink as _;
    let d = dir("huge-map");
    let w = 8192usize;
    let rows = 60_000i64;
    let mut reference = codec::ReferenceRow::new(w);
    let enc = reference.encoder(packets::STREAM_INTRA_PERIOD).unwrap();
    let mut buf = vec![0u8; packets::max_packet_len(w)];
    let file = std::io::BufWriter::new(std::fs::File::create(d.join("huge.dpsa")).unwrap());
    let mut sink =
        dpsa_core::sink::PacketSink::new(dpsa_sim::reconstruct::IoLink(file), enc, &mut buf);
    let info = StreamInfo {
        camera: 0,
        n: 4,
        width: w as u16,
        rows: 40,
        max_step_rows: 10,
        ..StreamInfo::default()
    };
    sink.start(&info).unwrap();
    let heights = vec![0i16; w];
    let valid = vec![0u8; w / 8];
    for b in 0..rows {
        let header = RowHeader {
            camera: 0,
            n: 4,
            row: b,
            latch: 0,
            flags: 0,
            width: w as u16,
        };
        sink.row(&Row {
            header,
            heights: &heights,
            valid: &valid,
        })
        .unwrap();
    }
    sink.end().unwrap();
    sink.flush().unwrap();
    drop(sink);
    let f = d.join("huge.dpsa");
    assert!(std::fs::metadata(&f).unwrap().len() < 8 << 20);
    let (code, v) = decode(&f, true);
    assert_eq!(code, 0, "{v}");
    assert_eq!(v["rows"]["decoded"].as_u64(), Some(rows as u64));
    assert_eq!(v["pixels"]["total"].as_u64(), Some(rows as u64 * w as u64));
    let png = d.join("huge.png");
    let out = run(
        &[
            "--quiet",
            "decode",
            f.to_str().unwrap(),
            "--png",
            png.to_str().unwrap(),
        ],
        true,
    );
    let se = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{se}");
    assert!(se.contains("64 Mpx"), "{se}");
    assert!(!png.exists());
    // codec-bench holds the map several times over: it refuses it from its documented limit.
    let out = run(&["--quiet", "codec-bench", f.to_str().unwrap()], true);
    let se = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{se}");
    assert!(se.contains("8 Mpx"), "{se}");
    let _ = std::fs::remove_dir_all(&d);
}
