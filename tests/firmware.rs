//! The firmware under QEMU (Cortex-M7, mps2-an500) against the host.
//!
//! - Bit-exactness: on four recordings (the default scene and `scenes/jitter.toml`,
//!   `scenes/defects.toml`, `scenes/fullframe.toml`) the packet stream the firmware emits is
//!   byte for byte the one `dpsa reconstruct` writes on the host, and it decodes into rows that
//!   show what the scene was made to contain; the same with a per-column height scale (the
//!   feed's height-scale table), whose heights are the uniform run's scaled by `T_z(c) / T_z`.
//! - With the FPGA front end: on the same recordings, the rows computed by the RTL's Verilator
//!   model (`fpga/`) give the core's stream on the host, and the firmware fed with them (the
//!   fabric log) emits it byte for byte; a log of another recording is refused.
//! - Bad input: a truncated feed, a corrupt header, a corrupt reference table and a corrupt,
//!   out-of-range or truncated height-scale table make the firmware exit with a failure status and a logged error naming the fault, never a
//!   panic or a hang.
//!
//! These tests need the cross toolchain and `qemu-system-arm` (`bash firmware/build.sh
//! --install` installs both; `tests/run.sh` does it first). Without them they fail with that
//! advice, unless `DPSA_SKIP_FIRMWARE=1` is set.

use dpsa_core::frames::feed;
use dpsa_core::offload::RowCoder;
use dpsa_core::packets;
use dpsa_fpga::front::{Coder, Fabric};
use dpsa_fpga::model::Model;
use dpsa_sim::heightmap::{flags, HeightMap};
use dpsa_sim::reconstruct;
use dpsa_sim::simulation::scene::Scene;
use dpsa_sim::target::{self, Echo, RunOptions};
use dpsa_tests::{flag_names, simulate, small_scene, Sim};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// The firmware ELF (built once per test binary), or `None` when `DPSA_SKIP_FIRMWARE=1`.
/// Panics with what to install when QEMU or the cross build is missing.
fn elf() -> Option<PathBuf> {
    if std::env::var("DPSA_SKIP_FIRMWARE").is_ok_and(|v| v == "1") {
        eprintln!("DPSA_SKIP_FIRMWARE=1: firmware test skipped");
        return None;
    }
    static ELF: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    let r = ELF.get_or_init(|| {
        let qemu = std::process::Command::new(target::QEMU)
            .arg("--version")
            .output();
        match qemu {
            Ok(o) if o.status.success() => {}
            Ok(o) => {
                return Err(format!(
                    "{} --version failed: {}",
                    target::QEMU,
                    String::from_utf8_lossy(&o.stderr)
                ))
            }
            Err(e) => return Err(format!("{} cannot be run: {e}", target::QEMU)),
        }
        target::firmware_elf(true).map_err(|e| format!("{e:#}"))
    });
    match r {
        Ok(p) => Some(p.clone()),
        Err(e) => panic!(
            "the firmware tests need QEMU and the Cortex-M7 build of the firmware:\n{e}\n\
             Install what is missing with `bash firmware/build.sh --install` (tests/run.sh does), \
             or set DPSA_SKIP_FIRMWARE=1 to skip these tests."
        ),
    }
}

fn scene_file(name: &str) -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    Scene::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Echo the decoded firmware log (the test harness shows it for a failing test).
const ECHO: Echo = Echo {
    log: true,
    progress: false,
};

/// Index, start offset and board row of the packet of `stream` that holds byte `offset`.
fn packet_at(stream: &[u8], offset: usize) -> (usize, usize, Option<i64>) {
    let (mut pos, mut index) = (0, 0);
    while pos < stream.len() {
        match packets::decode(&stream[pos..]) {
            Ok((p, len)) if offset < pos + len => return (index, pos, Some(p.header.row)),
            Ok((_, len)) => pos += len,
            Err(_) => break,
        }
        index += 1;
    }
    (index, pos, None)
}

/// Asserts that the target's stream is the host's, byte for byte; on a difference, says
/// where (byte offset, packet index and board row in the host stream).
#[track_caller]
fn assert_identical(what: &str, host: &[u8], target: &[u8]) {
    if host == target {
        return;
    }
    let offset = host
        .iter()
        .zip(target)
        .position(|(a, b)| a != b)
        .unwrap_or(host.len().min(target.len()));
    let (index, start, row) = packet_at(host, offset);
    panic!(
        "{what}: the firmware's stream differs from the host's at byte {offset} (host packet {index}, \
         which starts at byte {start}, board row {row:?}); host {} bytes, target {} bytes",
        host.len(),
        target.len()
    );
}

/// Host and target streams of one recording, compared; returns the decoded target stream.
fn host_and_target(what: &str, sim: &Sim, elf: &Path) -> HeightMap {
    let (stats, host) = reconstruct::run(&sim.rec, Vec::new(), false).expect("host reconstruction");
    let out = target::run(
        &sim.rec,
        elf,
        RunOptions {
            echo: ECHO,
            ..RunOptions::default()
        },
    )
    .unwrap_or_else(|e| panic!("{what}: firmware run failed: {e:#}"));
    assert!(
        out.outcome.success() && out.outcome.errors().next().is_none(),
        "{what}: {:?}",
        out.outcome
    );
    assert!(stats.packets > 0, "{what}: the host emitted no packets");
    assert_identical(what, &host, &out.stream);

    let (map, rep) =
        dpsa_sim::stream::decode_stream(&out.stream, sim.rec.manifest.calibration.height_lsb_um);
    assert_eq!(
        rep.corrupt, 0,
        "{what}: damaged packets in the firmware's stream: {:?}",
        rep.damage
    );
    assert_eq!(rep.ok as u64, stats.packets, "{what}");
    assert_eq!(map.width, sim.rec.width(), "{what}");
    // Both tag the stream with the recording's identity (the feed carries it to the target).
    assert_eq!(rep.stream.run_id, Some(sim.rec.run_id()), "{what}");
    assert_ne!(sim.rec.run_id(), 0, "{what}");
    // Every packet carries the recording's n.
    let mut pos = 0;
    while pos < out.stream.len() {
        let (p, len) = packets::decode(&out.stream[pos..]).expect("packet");
        assert_eq!(
            p.header.n, sim.rec.manifest.processing.n,
            "{what}: packet at byte {pos}"
        );
        pos += len;
    }
    map
}

fn count(map: &HeightMap, flag: u16) -> usize {
    map.rows.iter().filter(|r| r.flags & flag != 0).count()
}

fn valid_rows(map: &HeightMap) -> usize {
    map.rows.iter().filter(|r| r.is_valid()).count()
}

fn flag_summary(map: &HeightMap) -> String {
    let mut seen = std::collections::BTreeMap::<String, usize>::new();
    for r in &map.rows {
        *seen.entry(flag_names(r.flags)).or_default() += 1;
    }
    format!("{seen:?}")
}

// ---------------------------------------------------------------------------------------------
// Bit-exactness.

#[test]
fn default_scene_is_bit_exact() {
    let Some(elf) = elf() else { return };
    let sim = simulate(&Scene::default(), 1);
    let map = host_and_target("default scene", &sim, &elf);
    // Most of the board is valid and has height.
    let valid = valid_rows(&map);
    assert!(
        valid >= Scene::default().board_length as usize * 9 / 10,
        "{valid} valid rows: {}",
        flag_summary(&map)
    );
    assert!(
        map.valid_pixels() > valid * map.width * 9 / 10,
        "{}",
        map.valid_pixels()
    );
    assert!(
        map.rows
            .iter()
            .any(|r| r.is_valid() && r.heights.iter().any(|&h| h > 200)),
        "no deposit heights"
    );
    assert_eq!(
        count(&map, flags::ILL_CONDITIONED),
        0,
        "{}",
        flag_summary(&map)
    );
}

#[test]
fn jitter_scene_is_bit_exact() {
    let Some(elf) = elf() else { return };
    let scene = scene_file("jitter.toml");
    assert_eq!(scene.n, 5);
    assert_eq!(scene.jitter_pct, 20.0);
    assert_ne!(scene.fringe_period_px, Scene::default().fringe_period_px);
    let sim = simulate(&scene, scene.seed);
    // The steps really are jittered by up to +/-20 %.
    let cpp = sim.rec.manifest.calibration.counts_per_pixel;
    let steps: Vec<f64> = sim
        .rec
        .manifest
        .frames
        .windows(2)
        .map(|f| (f[1].latch - f[0].latch) as f64 / cpp)
        .collect();
    let (lo, hi) = steps
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &s| (a.min(s), b.max(s)));
    let m = scene.mean_step_px;
    assert!(
        lo < 0.9 * m && hi > 1.1 * m && lo >= 0.8 * m - 0.5 && hi <= 1.2 * m + 0.5,
        "steps {lo}..{hi}"
    );
    let map = host_and_target("jitter scene", &sim, &elf);
    let valid = valid_rows(&map);
    assert!(
        valid >= scene.board_length as usize * 9 / 10,
        "{valid} valid rows: {}",
        flag_summary(&map)
    );
}

#[test]
fn defects_scene_is_bit_exact() {
    let Some(elf) = elf() else { return };
    let scene = scene_file("defects.toml");
    let sim = simulate(&scene, scene.seed);
    let map = host_and_target("defects scene", &sim, &elf);
    let summary = flag_summary(&map);
    for (flag, name) in [
        (flags::ILL_CONDITIONED, "ILL_CONDITIONED"),
        (flags::SATURATED, "SATURATED"),
        (flags::LOW_MODULATION, "LOW_MODULATION"),
    ] {
        assert!(count(&map, flag) > 0, "no {name} row: {summary}");
    }
    // The saturated and unmodulated pixels are invalid in otherwise valid rows, inside the
    // patches that made them.
    for (flag, patch) in [
        (flags::SATURATED, &scene.patches[0]),
        (flags::LOW_MODULATION, &scene.patches[1]),
    ] {
        let rows: Vec<_> = map
            .rows
            .iter()
            .filter(|r| r.is_valid() && r.flags & flag != 0)
            .collect();
        assert!(!rows.is_empty(), "{}: {summary}", flag_names(flag));
        for r in rows {
            assert!(
                patch.contains_row(r.row),
                "row {} flagged {} outside its patch",
                r.row,
                flag_names(flag)
            );
            let c = (patch.col + i64::from(patch.cols) / 2) as usize;
            assert!(
                !r.pixel_valid(c),
                "row {}: the patch centre (column {c}) is valid",
                r.row
            );
        }
    }
}

#[test]
fn fullframe_scene_is_bit_exact() {
    let Some(elf) = elf() else { return };
    let scene = scene_file("fullframe.toml");
    // The paper's geometry at the full sensor width: the line pool (15.2 MiB) is in the
    // firmware's external RAM.
    assert_eq!((scene.width, scene.rows, scene.n), (2048, 2048, 4));
    let sim = simulate(&scene, scene.seed);
    let frames = sim.rec.len();
    assert!((6..=12).contains(&frames), "{frames} frames");
    let map = host_and_target("full-frame scene", &sim, &elf);
    // The windows span most of the frame: thousands of valid rows from a handful of frames.
    let valid = valid_rows(&map);
    assert!(
        valid > scene.rows as usize,
        "{valid} valid rows: {}",
        flag_summary(&map)
    );
    assert_eq!(
        count(&map, flags::ILL_CONDITIONED),
        0,
        "{}",
        flag_summary(&map)
    );
}

/// `T_z(c)` of a per-column table for width `w`: +-2 % around the recording's 500 um.
fn per_column_tz(w: usize) -> Vec<f64> {
    (0..w)
        .map(|c| 500.0 * (1.0 + 0.02 * (c as f64 * 0.07 + 0.5).sin()))
        .collect()
}

/// A calibration with a per-column height per turn: the feed carries the core's table, the
/// firmware's stream is the host's byte for byte, and its heights are the uniform run's
/// scaled per column by `T_z(c) / T_z` (within the two roundings).
#[test]
fn per_column_height_scale_is_bit_exact() {
    let Some(elf) = elf() else { return };
    let mut sim = simulate(&small_scene(), 6);
    let plain = host_and_target("uniform height scale", &sim, &elf);
    let tz = per_column_tz(sim.rec.width());
    sim.rec.manifest.calibration.height_per_turn_um_per_column = Some(tz.clone());
    sim.rec.manifest.validate().unwrap();
    let scaled = host_and_target("per-column height scale", &sim, &elf);
    let turn_lsb = 500.0 / 0.25;
    let (mut pixels, mut worst) = (0usize, 0f64);
    for (a, b) in plain.rows.iter().zip(&scaled.rows) {
        assert_eq!((a.row, a.flags), (b.row, b.flags));
        for (c, &t) in tz.iter().enumerate() {
            assert_eq!(a.pixel_valid(c), b.pixel_valid(c), "row {} col {c}", a.row);
            let h = f64::from(a.heights[c]);
            // Away from the wrap at half a turn, where the two scales wrap differently.
            if !a.pixel_valid(c) || h.abs() > 0.45 * turn_lsb {
                continue;
            }
            let want = h * t / 500.0;
            worst = worst.max((f64::from(b.heights[c]) - want).abs());
            pixels += 1;
        }
    }
    assert!(pixels > 50_000, "{pixels}");
    // Each run rounds once (0.5 LSB, the uniform one's scaled by up to 1.02) and the table
    // quantises k_c (< 0.01 LSB).
    assert!(worst <= 1.03, "per-column heights off by {worst} LSB");
}

/// The small scene with a latch jump of +1e12 counts at frame 20 and a reversal at frame 45.
fn jump_and_reversal() -> Sim {
    let mut sim = simulate(&small_scene(), 5);
    let frames = &mut sim.rec.manifest.frames;
    assert!(frames.len() > 60, "{} frames", frames.len());
    for f in frames.iter_mut().skip(20) {
        f.latch += 1_000_000_000_000;
    }
    frames[45].latch = frames[43].latch - 50;
    sim
}

/// `--intra-period` reaches the firmware through the recording header: predicted rows are
/// bit-exact too, and make a different (smaller) stream.
/// Encoder faults: a latch jump of +1e12 counts at frame 20 and a reversal at frame 45. The
/// firmware emits the host's stream byte for byte: one gap record for the jump (not one packet
/// per skipped row), flagged rows around both faults, and at most K packets per frame.
#[test]
fn encoder_jump_and_reversal_are_bit_exact_and_bounded() {
    let Some(elf) = elf() else { return };
    let sim = jump_and_reversal();
    let map = host_and_target("encoder jump and reversal", &sim, &elf);
    let (_, host) = reconstruct::run(&sim.rec, Vec::new(), false).unwrap();
    let (_, rep) = dpsa_sim::stream::decode_stream(&host, 0.25);
    assert_eq!(rep.stream.gap_records, 1, "{:?}", rep.stream);
    assert!(rep.stream.gap_rows > 1_000_000_000, "{:?}", rep.stream);
    assert!(!rep.stream.truncated && rep.stream.missing == 0);
    assert!(
        count(&map, flags::ENCODER_FAULT) > 0,
        "{}",
        flag_summary(&map)
    );
    assert!(
        count(&map, flags::ENCODER_REVERSAL) > 0,
        "{}",
        flag_summary(&map)
    );
    assert!(valid_rows(&map) > 100, "{}", flag_summary(&map));
    let cfg = &sim.rec.manifest;
    let k = dpsa_core::frames::registration::max_output_per_frame(
        cfg.processing.n,
        sim.rec.manifest.camera.rows as u16,
    );
    let packets = rep.ok as u64;
    assert!(
        // K items per frame plus its trigger record, the header and the end.
        packets <= (sim.rec.manifest.frames.len() as u64 + 1) * (k + 1) + 2,
        "{packets} packets"
    );
}

#[test]
fn predicted_rows_are_bit_exact() {
    let Some(elf) = elf() else { return };
    let sim = simulate(&small_scene(), 4);
    let (_, host) = reconstruct::run_with(&sim.rec, Vec::new(), 8, false).unwrap();
    let (_, intra) = reconstruct::run(&sim.rec, Vec::new(), false).unwrap();
    assert!(host.len() < intra.len());
    let out = target::run(
        &sim.rec,
        &elf,
        RunOptions {
            intra_period: 8,
            echo: ECHO,
            ..RunOptions::default()
        },
    )
    .unwrap();
    assert_identical("intra period 8", &host, &out.stream);
}

// ---------------------------------------------------------------------------------------------
// With the FPGA front end: the RTL's Verilator model computes the rows (`dpsa_fpga::front`).

/// The front end's logs of one run: computed rows, and the row codec's payloads.
struct Logs {
    rows: PathBuf,
    payloads: Option<PathBuf>,
}

impl Logs {
    fn fabric(&self) -> target::FabricLogs<'_> {
        target::FabricLogs {
            rows: &self.rows,
            payloads: self.payloads.as_deref(),
        }
    }
}

/// The recording through the RTL's models as the pipeline's front end (the pixel units, and
/// the row codec when `codec`): their logs (in `dir`), the host's stream with them, and the
/// rows the pixel model computed.
fn fabric_run(sim: &Sim, intra_period: u32, codec: bool, dir: &Path) -> (Logs, Vec<u8>, u64) {
    let core = reconstruct::config(&sim.rec.manifest).unwrap();
    let create = |name: &str| -> Box<dyn std::io::Write> {
        Box::new(std::io::BufWriter::new(
            std::fs::File::create(dir.join(name)).unwrap(),
        ))
    };
    let model = Model::repo().unwrap_or_else(|e| panic!("the RTL's Verilator model: {e}"));
    let mut fabric = Fabric::new(&model, core.cfg, &core.ref_phase, core.columns()).unwrap();
    fabric
        .log_to(create("fabric.dpsf"), sim.rec.run_id())
        .unwrap();
    let mut coder = codec.then(|| {
        let model = Model::codec_repo().unwrap_or_else(|e| panic!("the codec's model: {e}"));
        let mut c = Coder::new(&model, core.cfg.width as usize, intra_period).unwrap();
        c.log_to(create("payloads.dpsp"), sim.rec.run_id()).unwrap();
        c
    });
    let res = reconstruct::run_front_end(
        &sim.rec,
        Vec::new(),
        intra_period,
        &mut fabric,
        coder.as_mut().map(|c| c as &mut dyn RowCoder),
        false,
    );
    let stream = match res {
        Ok((_, s)) => s,
        Err(e) => panic!(
            "front-end run: {e} ({:?}, {:?})",
            fabric.error(),
            coder.as_ref().map(|c| c.error())
        ),
    };
    let rows = fabric.rows;
    fabric.finish().unwrap();
    if let Some(c) = coder {
        c.finish().unwrap();
    }
    let logs = Logs {
        rows: dir.join("fabric.dpsf"),
        payloads: codec.then(|| dir.join("payloads.dpsp")),
    };
    (logs, stream, rows)
}

/// The firmware with the front end on one recording: the host's stream through the RTL is the
/// core's, and the firmware fed by the RTL's logs emits the same bytes, every computed row (and
/// with `codec` every payload) taken from the fabric.
fn front_end_is_bit_exact(
    what: &str,
    sim: &Sim,
    intra_period: u32,
    codec: bool,
    elf: &Path,
) -> u64 {
    let (_, host) = reconstruct::run_with(&sim.rec, Vec::new(), intra_period, false).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (logs, through_rtl, rows) = fabric_run(sim, intra_period, codec, dir.path());
    assert_identical(&format!("{what}: host with the RTL"), &host, &through_rtl);
    let opts = RunOptions {
        intra_period,
        echo: ECHO,
        ..RunOptions::default()
    };
    let out = target::run_with_fabric(&sim.rec, elf, opts, Some(logs.fabric()))
        .unwrap_or_else(|e| panic!("{what}: firmware run with the front end failed: {e:#}"));
    assert_identical(
        &format!("{what}: firmware with the front end"),
        &host,
        &out.stream,
    );
    let said = |m: &str| out.outcome.log.iter().any(|l| l.message == m);
    assert!(
        said(&format!("front end: {rows} rows from the fabric")),
        "{what}: the firmware did not take all {rows} rows from the fabric"
    );
    let (mut pos, mut row_packets) = (0, 0);
    while pos < host.len() {
        let (p, len) = packets::decode(&host[pos..]).expect("packet");
        row_packets += usize::from(p.kind == packets::Kind::Row);
        pos += len;
    }
    let payloads = format!("front end: {row_packets} payloads from the fabric's row codec");
    assert_eq!(said(&payloads), codec, "{what}: {payloads}");
    rows
}

/// The firmware's test recordings (the default, jitter, defects and full-frame scenes, a
/// per-column height scale, an encoder jump and reversal, predicted rows) with the rows
/// computed and coded by the RTL: every stream is the core's, byte for byte; the default
/// scene also with the rows coded on the MCU.
#[test]
fn the_front_end_is_bit_exact_on_the_firmware_recordings() {
    let Some(elf) = elf() else { return };
    let mut rows = 0;
    let default = simulate(&Scene::default(), 1);
    rows += front_end_is_bit_exact("default scene", &default, 1, true, &elf);
    front_end_is_bit_exact("default scene, MCU codec", &default, 1, false, &elf);
    for name in ["jitter.toml", "defects.toml", "fullframe.toml"] {
        let scene = scene_file(name);
        rows += front_end_is_bit_exact(name, &simulate(&scene, scene.seed), 1, true, &elf);
    }
    let mut sim = simulate(&small_scene(), 6);
    sim.rec.manifest.calibration.height_per_turn_um_per_column =
        Some(per_column_tz(sim.rec.width()));
    rows += front_end_is_bit_exact("per-column height scale", &sim, 1, true, &elf);
    let sim = jump_and_reversal();
    rows += front_end_is_bit_exact("encoder jump and reversal", &sim, 1, true, &elf);
    let sim = simulate(&small_scene(), 4);
    rows += front_end_is_bit_exact("intra period 8", &sim, 8, true, &elf);
    assert!(rows > 5_000, "{rows} rows through the RTL");
}

/// Logs that are not the feed's (another recording's, truncated ones) stop the firmware with an
/// error naming them, never a stream built from the wrong rows or payloads.
#[test]
fn a_fabric_log_of_another_recording_is_refused() {
    let Some(elf) = elf() else { return };
    let dir = tempfile::tempdir().unwrap();
    let sim = simulate(&small_scene(), 8);
    let (logs, _, _) = fabric_run(&sim, 1, true, dir.path());
    let other = simulate(&small_scene(), 9);
    assert_ne!(sim.rec.run_id(), other.rec.run_id());
    let opts = RunOptions {
        echo: ECHO,
        ..RunOptions::default()
    };
    let refused = |rec: &Sim, logs: target::FabricLogs<'_>, needles: &[&str]| {
        let err = target::run_with_fabric(&rec.rec, &elf, opts, Some(logs)).unwrap_err();
        let msg = format!("{err:#}");
        for n in needles {
            assert!(msg.contains(n), "{n:?} not in: {msg}");
        }
        assert!(!msg.to_lowercase().contains("panic"), "{msg}");
    };
    refused(&other, logs.fabric(), &["fabric log", "run id"]);
    let cut = |p: &Path, name: &str| -> PathBuf {
        let bytes = std::fs::read(p).unwrap();
        let out = dir.path().join(name);
        std::fs::write(&out, &bytes[..bytes.len() / 2]).unwrap();
        out
    };
    let rows = cut(&logs.rows, "cut.dpsf");
    let payloads = logs.payloads.clone().unwrap();
    let fabric = |rows: &Path, payloads: &Path| -> Logs {
        Logs {
            rows: rows.to_path_buf(),
            payloads: Some(payloads.to_path_buf()),
        }
    };
    refused(&sim, fabric(&rows, &payloads).fabric(), &["fabric log"]);
    let short = cut(&payloads, "cut.dpsp");
    refused(&sim, fabric(&logs.rows, &short).fabric(), &["row codec"]);
    // The payload log of another recording.
    let other_dir = dir.path().join("other");
    std::fs::create_dir(&other_dir).unwrap();
    let (other_logs, _, _) = fabric_run(&other, 1, true, &other_dir);
    let theirs = other_logs.payloads.unwrap();
    refused(
        &sim,
        fabric(&logs.rows, &theirs).fabric(),
        &["payload log", "run id"],
    );
}

// ---------------------------------------------------------------------------------------------
// Bad input.

/// A feed of a small scene, and its header.
fn exported(dir: &Path) -> (PathBuf, feed::Header, Vec<u8>) {
    let sim = simulate(&small_scene(), 21);
    let path = dir.join("recording.dpsr");
    target::write_feed(&sim.rec, 1, &path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let header = feed::Header::decode(&bytes).expect("the export's header decodes");
    assert_eq!(header.frames as usize, sim.rec.len());
    assert_eq!(
        bytes.len(),
        feed::HEADER_LEN + header.table_len() + header.frames as usize * header.frame_len()
    );
    assert_eq!(header.frames_at(), feed::HEADER_LEN + header.table_len());
    (path, header, bytes)
}

/// A feed with a per-column height-scale table, and its header.
fn exported_with_table(dir: &Path) -> (feed::Header, Vec<u8>) {
    let mut sim = simulate(&small_scene(), 22);
    sim.rec.manifest.calibration.height_per_turn_um_per_column =
        Some(per_column_tz(sim.rec.width()));
    let path = dir.join("recording-table.dpsr");
    target::write_feed(&sim.rec, 1, &path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let header = feed::Header::decode(&bytes).expect("the export's header decodes");
    assert!(header.column_scale.is_some());
    assert_eq!(
        bytes.len(),
        header.frames_at() + header.frames as usize * header.frame_len()
    );
    (header, bytes)
}

/// Runs the firmware on `bytes` as a recording: it must fail, log an error that contains
/// every one of `needles`, not panic, and the error of [`target::run_files`] must carry it.
#[track_caller]
fn assert_refused(elf: &Path, dir: &Path, what: &str, bytes: &[u8], needles: &[&str]) {
    let rec = dir.join(format!("{what}.dpsr"));
    let out = dir.join(format!("{what}.dpsa"));
    std::fs::write(&rec, bytes).unwrap();
    let err = target::run_files(elf, &rec, &out, None, None, ECHO).expect_err(what);
    let msg = format!("{err:#}");
    for n in needles {
        assert!(
            msg.contains(n),
            "{what}: the error does not mention {n:?}:\n{msg}"
        );
    }
    assert!(
        !msg.to_lowercase().contains("panic") && !msg.contains("hard fault"),
        "{what}: {msg}"
    );
    // The same run, looked at directly: a failure status (not killed), and an ERROR log line.
    let args = [
        rec.to_str().unwrap().to_string(),
        out.to_str().unwrap().to_string(),
    ];
    let o = target::qemu(elf, &args, None, ECHO).unwrap();
    assert!(
        matches!(o.code, Some(c) if c != 0),
        "{what}: exit {:?}",
        o.code
    );
    let errors: Vec<String> = o.errors().map(|l| l.message.clone()).collect();
    assert!(
        errors.iter().any(|e| needles.iter().all(|n| e.contains(n))),
        "{what}: error lines {errors:?}"
    );
    assert_eq!(o.malformed, 0, "{what}: undecodable log frames");
}

#[test]
fn truncated_recording_is_refused() {
    let Some(elf) = elf() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (_, h, bytes) = exported(dir.path());
    let frames_at = feed::HEADER_LEN + h.table_len();
    let line_bytes = h.line_len();
    // In the middle of line 7 of frame 5 (0-based), and at the start of frame 9.
    let mid = frames_at + 5 * h.frame_len() + feed::TRIGGER_LEN + 7 * line_bytes + line_bytes / 2;
    let needle = format!("feed truncated in frame 5 at line 7 (byte {mid})");
    assert_refused(&elf, dir.path(), "mid-line", &bytes[..mid], &[&needle]);
    let at = frames_at + 9 * h.frame_len();
    let needle = format!("feed truncated in frame 9 at line 0 (byte {at})");
    assert_refused(&elf, dir.path(), "frame-boundary", &bytes[..at], &[&needle]);
    // Inside the header: the header cannot even be read.
    assert_refused(
        &elf,
        dir.path(),
        "short-header",
        &bytes[..40],
        &["opening the feed", "length does not match the feed layout"],
    );
}

#[test]
fn corrupt_header_and_table_are_refused() {
    let Some(elf) = elf() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (_, h, bytes) = exported(dir.path());
    // One bit of the width: the header CRC catches it.
    let mut b = bytes.clone();
    b[8] ^= 0x10;
    assert_refused(
        &elf,
        dir.path(),
        "header-bit",
        &b,
        &["opening the feed", "header CRC does not match"],
    );
    // Not a feed at all.
    let mut b = bytes.clone();
    b[..4].copy_from_slice(b"PNG\0");
    assert_refused(
        &elf,
        dir.path(),
        "magic",
        &b,
        &["opening the feed", "not a feed"],
    );
    // One reference-phase entry: the table CRC catches it.
    let mut b = bytes.clone();
    b[feed::HEADER_LEN + 4 * 17] ^= 0x01;
    assert_refused(
        &elf,
        dir.path(),
        "table",
        &b,
        &[
            "opening the feed",
            "reference-phase table CRC does not match",
        ],
    );
    // The per-column height-scale table: one flipped bit (its CRC), and a table whose CRC is
    // right but whose entry is four times the configuration's scale.
    let (ht, tbytes) = exported_with_table(dir.path());
    let at = feed::HEADER_LEN + ht.table_len();
    let mut b = tbytes.clone();
    b[at + 2 * 5] ^= 0x01;
    assert_refused(
        &elf,
        dir.path(),
        "scale-table",
        &b,
        &[
            "opening the feed",
            "per-column height-scale table CRC does not match",
        ],
    );
    let w = ht.cfg.width as usize;
    let mut mantissa: Vec<u16> = b[at..at + 2 * w]
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    mantissa[9] /= 4;
    let mut b = tbytes.clone();
    feed::encode_scale_table(&mantissa, &mut b[at..at + 2 * w + 4]).unwrap();
    assert_refused(
        &elf,
        dir.path(),
        "scale-range",
        &b,
        &[
            "opening the feed",
            "per-column height scale: column 9",
            "factor of 2",
        ],
    );
    // A truncated table.
    assert_refused(
        &elf,
        dir.path(),
        "scale-short",
        &tbytes[..at + 100],
        &["opening the feed", "length does not match the feed layout"],
    );

    // A valid header (CRC and all) whose configuration the core refuses.
    let mut bad = h;
    bad.cfg.max_step_rows = bad.cfg.rows + 1;
    let mut b = bytes.clone();
    b[..feed::HEADER_LEN].copy_from_slice(&bad.encode());
    assert_refused(
        &elf,
        dir.path(),
        "config",
        &b,
        &["opening the feed", "max_step_rows is out of range"],
    );
}
