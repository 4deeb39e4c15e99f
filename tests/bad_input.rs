//! Bad input: damaged recordings, inconsistent manifests, bad scene files and corrupt packet
//! streams give a clear error or flagged rows, never a panic and never wrong heights.

use dpsa_sim::heightmap::{flags, HeightMap};
use dpsa_sim::reference::compare::Comparison;
use dpsa_sim::reference::{self, compare::compare_recording};
use dpsa_sim::simulation::recording::load_frames;
use dpsa_sim::simulation::recording::{write_frame_png, Recording};
use dpsa_sim::simulation::scene::Scene;
use dpsa_sim::{reconstruct, stream};
use dpsa_tests::{
    assert_flags_agree, check_vs_truth, edit_manifest_json, flag_names, row_is_empty, simulate,
    small_scene, Sim,
};
use serde_json::json;

fn sim() -> Sim {
    simulate(&small_scene(), 21)
}

/// The error chain of a failed job, as the CLI prints it.
fn err_text<T>(r: dpsa_sim::Result<T>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => format!("{:#}", anyhow::Error::new(e)),
    }
}

#[track_caller]
fn assert_mentions(msg: &str, needles: &[&str]) {
    for n in needles {
        assert!(
            msg.contains(n),
            "error message does not mention {n:?}: {msg}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Damaged frame files: a clear error naming the frame.

#[test]
fn truncated_png_frame() {
    let s = sim();
    let path = s.path().join("frames/000003.png");
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let rec = s.reopen();
    let msg = err_text(reconstruct::reconstruct_bytes(&rec, false));
    assert_mentions(&msg, &["frame 3", "000003.png", "decode"]);
    let msg = err_text(compare_recording(&rec, false));
    assert_mentions(&msg, &["frame 3", "000003.png"]);
}

#[test]
fn frame_of_the_wrong_size() {
    let s = sim();
    let (rows, width) = (s.rec.rows(), s.rec.width());
    write_frame_png(
        &s.path().join("frames/000003.png"),
        rows,
        width + 8,
        &vec![100; rows * (width + 8)],
    )
    .unwrap();
    let msg = err_text(reconstruct::reconstruct_bytes(&s.rec, false));
    assert_mentions(
        &msg,
        &[
            "frame 3",
            "000003.png",
            &format!("{}", width + 8),
            &format!("expected {rows} x {width}"),
        ],
    );
    let msg = err_text(compare_recording(&s.rec, false));
    assert_mentions(&msg, &["frame 3", "000003.png"]);
}

#[test]
fn missing_frame_file() {
    let s = sim();
    std::fs::remove_file(s.path().join("frames/000003.png")).unwrap();
    let msg = err_text(reconstruct::reconstruct_bytes(&s.rec, false));
    assert_mentions(&msg, &["frame 3", "000003.png", "missing"]);
    let msg = err_text(compare_recording(&s.rec, false));
    assert_mentions(&msg, &["frame 3", "missing"]);
}

// ---------------------------------------------------------------------------------------------
// Manifests.

#[test]
fn manifest_with_unknown_keys() {
    for (edit, key) in [
        (
            Box::new(|v: &mut serde_json::Value| v["camera"]["exposure_us"] = json!(100))
                as Box<dyn Fn(&mut serde_json::Value)>,
            "exposure_us",
        ),
        (
            Box::new(|v: &mut serde_json::Value| v["comment"] = json!("hello")),
            "comment",
        ),
        (
            Box::new(|v: &mut serde_json::Value| v["frames"][2]["latchh"] = json!(5)),
            "latchh",
        ),
        (
            Box::new(|v: &mut serde_json::Value| {
                let p = v["processing"].as_object_mut().unwrap();
                let x = p.remove("min_modulation").unwrap();
                p.insert("min_modulaton".into(), x);
            }),
            "min_modulaton",
        ),
    ] {
        let s = sim();
        edit_manifest_json(s.path(), edit);
        let err = Recording::open(s.path()).unwrap_err().to_string();
        assert_mentions(&err, &[key, "manifest.json"]);
    }
}

/// Runs the core, the reference and the comparison on an edited recording; the two
/// implementations must agree exactly on rows and flags and within 1 LSB on heights.
fn run_edited(s: &Sim) -> (Comparison, HeightMap) {
    let rec = s.reopen();
    let cmp = compare_recording(&rec, false).expect("an edited manifest is still processed");
    let (_, _, fixed) = reconstruct::reconstruct_map(&rec, false).expect("core");
    let f = &cmp.fixed_vs_ref;
    assert_eq!(
        (
            f.rows_only_fixed,
            f.rows_only_ref,
            f.row_validity_mismatch,
            f.valid_mismatch
        ),
        (0, 0, 0, 0),
        "{f:?}"
    );
    assert!(f.max_abs_lsb.unwrap_or(0.0) <= 1.0, "{f:?}");
    // Row by row: the same rows, the same validity, compatible flags.
    let frames = load_frames(&rec, false).unwrap();
    assert_flags_agree(&fixed, &reference::reconstruct(&rec.manifest, &frames));
    // Rows come out contiguous, each once, and invalid rows carry no heights.
    for w in fixed.rows.windows(2) {
        assert_eq!(w[1].row, w[0].row + 1);
    }
    for r in fixed.rows.iter().filter(|r| !r.is_valid()) {
        assert!(
            row_is_empty(r),
            "invalid row {} ({}) carries heights",
            r.row,
            flag_names(r.flags)
        );
    }
    (cmp, fixed)
}

/// Every valid pixel and row of `fixed` matches the truth.
#[track_caller]
fn assert_heights_true(s: &Sim, fixed: &HeightMap, what: &str) {
    let check = check_vs_truth(&s.rec.manifest, &s.truth(), fixed, |_| true);
    check.assert_ok(what);
    assert!(check.rows >= 250, "{what}: {check:?}");
}

/// A real encoder reversal: the board moved back between frames 20 and 21. Frames 20 and 21
/// are swapped in the manifest (files and latches; seq stays increasing), so the latches match
/// the frame contents and decrease once.
#[test]
fn encoder_reversal_swapped_frames() {
    let s = sim();
    edit_manifest_json(s.path(), |v| {
        let f = v["frames"].as_array_mut().unwrap();
        for key in ["latch", "file"] {
            let a = f[20][key].clone();
            f[20][key] = f[21][key].clone();
            f[21][key] = a;
        }
    });
    let (cmp, fixed) = run_edited(&s);
    assert!(cmp.rows.encoder_reversal > 0, "{}", cmp.summary());
    assert_heights_true(&s, &fixed, "swapped frames");
}

/// One latch jumps backwards (a glitch): the frame's content no longer matches its latch, so
/// every row whose window contains it must be flagged rather than computed.
#[test]
fn encoder_latch_goes_backwards() {
    let s = sim();
    edit_manifest_json(s.path(), |v| {
        let f = v["frames"].as_array_mut().unwrap();
        let prev = f[24]["latch"].as_i64().unwrap();
        f[25]["latch"] = json!(prev - 30);
    });
    let (cmp, fixed) = run_edited(&s);
    assert!(cmp.rows.encoder_reversal >= 8, "{}", cmp.summary());
    assert_heights_true(&s, &fixed, "latch backwards");
}

/// The conveyor stalls for two frames: frames 31 and 32 repeat frame 30 (same latch, same
/// image), then the motion continues from where it really is. Rows whose window is degenerate
/// are flagged; the rest are correct.
#[test]
fn repeated_latches_stalled_conveyor() {
    let s = sim();
    // Frames 31 and 32 repeat frame 30 (latch and image); every entry keeps its own file,
    // as a manifest requires.
    edit_manifest_json(s.path(), |v| {
        let f = v["frames"].as_array_mut().unwrap();
        for k in [31, 32] {
            f[k]["latch"] = f[30]["latch"].clone();
        }
    });
    for k in [31, 32] {
        std::fs::copy(
            s.path().join("frames/000030.png"),
            s.path().join(format!("frames/{k:06}.png")),
        )
        .unwrap();
    }
    let (cmp, fixed) = run_edited(&s);
    let flagged = fixed.rows_with(flags::ILL_CONDITIONED | flags::SKIPPED | flags::INCOMPLETE);
    assert!(cmp.rows.ill_conditioned > 0, "{}", cmp.summary());
    assert!(flagged > 0);
    assert_heights_true(&s, &fixed, "repeated latches");
}

/// Latches repeated without the images (the encoder stuck while the board moved): the
/// recording lies about the motion; the core must still agree with the reference, flag the
/// degenerate windows and not panic.
#[test]
fn repeated_latches_stuck_encoder() {
    let s = sim();
    edit_manifest_json(s.path(), |v| {
        let f = v["frames"].as_array_mut().unwrap();
        for k in [31, 32, 33] {
            f[k]["latch"] = f[30]["latch"].clone();
        }
    });
    let (cmp, _) = run_edited(&s);
    assert!(cmp.rows.ill_conditioned > 0, "{}", cmp.summary());
}

/// Frame 40 was lost: it is dropped from the manifest and the others keep their `seq`, so
/// there is a gap 39 -> 41.
#[test]
fn sequence_gap_gives_frame_gap_rows() {
    let s = sim();
    edit_manifest_json(s.path(), |v| {
        let f = v["frames"].as_array_mut().unwrap();
        assert_eq!(f[40]["seq"], json!(40));
        f.remove(40);
    });
    let rec = s.reopen();
    assert_eq!(rec.manifest.frames[40].seq, 41);
    let (cmp, fixed) = run_edited(&s);
    assert!(cmp.rows.frame_gap >= 8, "{}", cmp.summary());
    assert_heights_true(&s, &fixed, "seq gap");
}

// ---------------------------------------------------------------------------------------------
// Scene files.

#[test]
fn unknown_scene_key_is_named() {
    for (text, key) in [
        ("width = 64\nwidht = 64\n", "widht"),
        ("[[stalls]]\nframe = 3\nframs = 2\n", "frams"),
        (
            "[[patches]]\nrow = 0\ncol = 0\nrows = 4\ncols = 4\ncontrst = 0.0\n",
            "contrst",
        ),
    ] {
        let err = Scene::from_toml_str(text).unwrap_err().to_string();
        assert_mentions(&err, &[key]);
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.toml");
    std::fs::write(&file, "board_length = 300\nmean_stp_px = 4.0\n").unwrap();
    let err = Scene::load(&file).unwrap_err().to_string();
    assert_mentions(&err, &["mean_stp_px", "bad.toml"]);
}

#[test]
fn out_of_range_scene_knob_is_named() {
    let err = Scene::from_toml_str("n = 12\n").unwrap_err().to_string();
    assert_mentions(&err, &["`n`", "12"]);
    let err = Scene::from_toml_str("jitter_pct = -3.0\n")
        .unwrap_err()
        .to_string();
    assert_mentions(&err, &["jitter_pct"]);
}

// ---------------------------------------------------------------------------------------------
// Packet streams.

/// Byte offsets of the packets of a well-formed (version 2) stream, from the documented layout:
/// a 40-byte header whose bytes 32..36 are the payload length, the payload and a 4-byte CRC.
fn packet_offsets(bytes: &[u8]) -> Vec<usize> {
    let mut out = Vec::new();
    let mut pos = 0;
    while pos < bytes.len() {
        assert_eq!(&bytes[pos..pos + 4], b"DPSA", "sync word at {pos}");
        out.push(pos);
        let plen = u32::from_le_bytes(bytes[pos + 32..pos + 36].try_into().unwrap()) as usize;
        pos += 40 + plen + 4;
    }
    assert_eq!(pos, bytes.len());
    out
}

#[test]
fn corrupt_packet_stream() {
    let s = sim();
    let (_, bytes) = reconstruct::reconstruct_bytes(&s.rec, false).unwrap();
    let lsb = s.rec.manifest.calibration.height_lsb_um;
    let (clean, rep) = stream::decode_stream(&bytes, lsb);
    assert_eq!((rep.corrupt, rep.resynced), (0, 0));
    let offsets = packet_offsets(&bytes);
    assert_eq!(rep.ok, offsets.len());
    // The stream header first and the end packet last; rows and the frames' trigger records
    // (kind 5, one per frame) in between.
    let rows: Vec<usize> = (0..offsets.len())
        .filter(|&i| bytes[offsets[i] + 5] <= 1)
        .collect();
    assert_eq!(clean.rows.len(), rows.len());
    let triggers = (0..offsets.len()).filter(|&i| bytes[offsets[i] + 5] == 5);
    assert_eq!(triggers.count(), s.rec.manifest.frames.len());
    assert_eq!(rows.len() + s.rec.manifest.frames.len() + 2, offsets.len());
    assert!(!rep.stream.truncated && rep.stream.missing == 0);
    let m = rows.len() / 2;

    // Damage four row packets in the middle of the stream, each in a different place.
    let mut bad = bytes.clone();
    let which = [m - 20, m - 7, m, m + 13];
    let damaged = which.map(|k| rows[k]);
    bad[offsets[damaged[0]]] ^= 0xff; // sync word
    bad[offsets[damaged[1]] + 32] ^= 0x40; // payload length
    bad[offsets[damaged[2]] + 40 + 17] ^= 0x01; // payload (one bit)
    let end = offsets[damaged[3] + 1];
    bad[end - 2] ^= 0x10; // CRC
    let (map, rep) = stream::decode_stream(&bad, lsb);
    assert_eq!(rep.corrupt, 4, "{rep:?}");
    assert_eq!(rep.damage.len(), 4);
    for (d, &i) in rep.damage.iter().zip(&damaged) {
        assert_eq!(d.offset, offsets[i], "{rep:?}");
    }
    assert_eq!(rep.ok, offsets.len() - 4, "{rep:?}");
    // The lost packets are reported as missing (sequence numbers), the stream as incomplete.
    assert_eq!(rep.stream.missing, 4, "{rep:?}");
    assert!(rep.stream.truncated);
    assert_eq!(rep.stream.rows_missing, 4);
    // Every other row decodes exactly as before.
    let lost: Vec<i64> = which.iter().map(|&k| clean.rows[k].row).collect();
    let expected: Vec<_> = clean
        .rows
        .iter()
        .filter(|r| !lost.contains(&r.row))
        .collect();
    assert_eq!(map.rows.len(), expected.len());
    for (a, b) in map.rows.iter().zip(expected) {
        assert_eq!(a, b);
    }

    // Garbage between packets and a truncated last packet.
    let mut bad = bytes[..offsets[10]].to_vec();
    bad.extend_from_slice(b"noise\x00\x01DPS");
    bad.extend_from_slice(&bytes[offsets[10]..bytes.len() - 5]);
    let (map, rep) = stream::decode_stream(&bad, lsb);
    assert_eq!(rep.ok, offsets.len() - 1, "{rep:?}");
    assert_eq!(rep.corrupt, 2, "{rep:?}");
    // The cut packet is the end packet: every row decodes, the stream is truncated.
    assert_eq!(map.rows[..], clean.rows[..]);
    assert!(rep.stream.truncated && rep.stream.end_totals.is_none());
}
