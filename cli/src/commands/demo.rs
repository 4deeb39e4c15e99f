//! `dpsa demo`: the main job on built-in scenes. One camera: simulate, reconstruct, compare,
//! write images. Then the paper's camera array on a short board: calibrate the three cameras
//! from flat planes and a lateral target, simulate the board through them, and stitch one
//! board height map in millimetres against the truth.

use super::{load_scene, open, out};
use anyhow::Result;
use dpsa_sim::{
    array::{record, record::ArrayRecording, scene::ArrayScene},
    board, calibration, files, images, reconstruct,
    reference::compare::compare_recording,
    simulation::simulate,
};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Working directory for the recording, stream, images and report.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Random seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Scene: `default` or a scene TOML file.
    #[arg(long, default_value = "default")]
    scene: String,
    /// Run only the camera array, on this array scene: `small` (built in:
    /// `scenes/array-paste.toml`, three 192 px cameras over a 20 x 13.9 mm printed board of
    /// 193 pads) or an array scene file, e.g. `scenes/paper-board.toml` (the paper's three
    /// 2048 px cameras over 220 x 168 mm: about 0.6 GB of recordings (585 MB measured) and several
    /// minutes). Without it the demo runs the single-camera scene, then the small array.
    #[arg(long)]
    array: Option<String>,
}

/// The built-in array scene of the demo: the small printed board, and its paste layer.
const SMALL_ARRAY: &str = include_str!("../../../scenes/array-paste.toml");
const SMALL_LAYER: &[u8] = include_bytes!("../../../scenes/array-small.paste.gbr");

pub fn run(a: Args, progress: bool) -> Result<()> {
    if let Some(spec) = &a.array {
        // `--array`: the array alone, not the single-camera scene first.
        return array(&a.out, a.seed, spec, 0, progress);
    }
    let (out, seed, scene) = (&a.out, a.seed, a.scene.as_str());
    let sc = load_scene(scene)?;
    let rec_dir = out.join("recording");
    out!(
        "1/8 simulating the {scene} scene (seed {seed}) into {}",
        rec_dir.display()
    );
    let s = simulate::simulate(&sc, seed, &rec_dir, progress)?;
    out!(
        "    {} frames of {} rows x {} px, {} solder-paste deposits, {:.0} um per fringe turn",
        s.frames,
        s.rows,
        s.width,
        s.deposits_placed,
        sc.height_per_turn_um
    );
    let rec = open(&rec_dir)?;
    out!("2/8 reconstructing with the fixed-point core (streaming, line by line)");
    let (stats, bytes, map) = reconstruct::reconstruct_map(&rec, progress)?;
    let stream = out.join("heights.dpsa");
    files::write_bytes(&stream, &bytes)?;
    out!(
        "    {} packets (stream header, rows, end), {} bytes -> {}; core state {} bytes",
        stats.packets,
        stats.bytes,
        stream.display(),
        stats.state_bytes
    );
    out!("3/8 comparing with the f64 reference, the 4-step PSP baseline and the ground truth");
    let cmp = compare_recording(&rec, progress)?;
    let report = out.join("compare.json");
    files::write_bytes(&report, serde_json::to_string_pretty(&cmp)?.as_bytes())?;
    out!("4/8 writing images");
    let png = out.join("heights.png");
    let colour = images::write_pngs(&map, &png)?;
    out!(
        "    {} (16-bit), {} (false colour)",
        png.display(),
        colour.display()
    );
    out!("");
    out!("{}", cmp.summary());
    out!("full report: {}", report.display());
    out!("");
    array(out, seed, "small", 4, progress)
}

/// The second part: the camera array, calibrated, and one stitched board map. `before`:
/// the steps already printed (4 after the single-camera part, 0 alone).
fn array(
    out: &std::path::Path,
    seed: u64,
    spec: &str,
    before: usize,
    progress: bool,
) -> Result<()> {
    let total = before + 4;
    let step = |k: usize| format!("{}/{total}", before + k);
    let (scene, name) = if spec == "small" {
        let mut scene = ArrayScene::from_toml_str(SMALL_ARRAY)?;
        // Its paste layer beside the recordings, where the scene finds it.
        std::fs::create_dir_all(out)?;
        files::write_bytes(&out.join("array-small.paste.gbr"), SMALL_LAYER)?;
        scene.scene_dir = Some(out.to_path_buf());
        (scene, "built-in small printed board")
    } else {
        (ArrayScene::load(std::path::Path::new(spec))?, spec)
    };
    super::warn(&scene.warnings());
    let cal_dir = out.join("array-calibration");
    out!(
        "{} the camera array ({name}: {} cameras, {} x {} mm board): recording the calibration planes at {:?} um and the lateral target into {}",
        step(1),
        scene.cameras.len(),
        scene.board_length_mm,
        scene.board_width_mm,
        scene.calibration.plane_heights_um,
        cal_dir.display()
    );
    let w = record::simulate_calibration(&scene, seed, &cal_dir)?;
    out!(
        "    {} frames, {:.0} MB; calibrating",
        w.frames,
        w.bytes as f64 / 1e6
    );
    let cal_rec = ArrayRecording::open(&cal_dir)?;
    let cal = calibration::calibrate(&cal_rec, calibration::FX_BUDGET_UM)?;
    let cal_path = out.join("array.cal.toml");
    files::write_bytes(&cal_path, cal.to_toml()?.as_bytes())?;
    let ev = calibration::evaluate::evaluate(&cal_rec, &cal)?;
    if let Some(h) = &ev.holdout {
        out!(
            "    {}: held-out plane at {} um measured with bias {:.3} um, rms {:.3} um",
            cal_path.display(),
            h.height_um,
            h.bias_um_max,
            h.rms_um
        );
    }
    if let Some(t) = &ev.truth_error {
        out!(
            "    against the simulator's truth: T_z {:.1e}, f_x {:.1e} relative, phi_0 {:.2} mrad rms, lateral {:.2} um rms",
            t.t_z_rel_max, t.f_x_rel_max, t.phi0_rms_mrad, t.lateral_rms_um
        );
    }
    let board_dir = out.join("array-board");
    out!(
        "{} a board with a {} um bow and {} through the array into {}",
        step(2),
        scene.warp_um,
        match &scene.paste_layer {
            Some(layer) => format!("the paste of {layer} printed on it (with defects)"),
            None => format!("{} deposits", scene.deposits),
        },
        board_dir.display()
    );
    let wb = record::simulate_board(&scene, seed, &board_dir)?;
    out!(
        "    {} frames, {:.0} MB (with the calibration: {:.0} MB of recordings)",
        wb.frames,
        wb.bytes as f64 / 1e6,
        (w.bytes + wb.bytes) as f64 / 1e6
    );
    let map_dir = out.join("board-map");
    out!(
        "{} the core on every camera, unwrapped, placed and blended into one map -> {}",
        step(3),
        map_dir.display()
    );
    let program = board_dir.join(record::PROGRAM_FILE);
    let paste = if program.is_file() {
        super::board::paste_of(&program)?
    } else {
        Default::default()
    };
    let r = board::run::run_shown(
        &board_dir,
        &cal,
        &map_dir,
        board::run::Source::Core,
        &board::run::Options {
            progress,
            paste,
            ..Default::default()
        },
    )?;
    files::write_bytes(
        &map_dir.join("report.json"),
        serde_json::to_string_pretty(&r)?.as_bytes(),
    )?;
    out!("{}", r.summary());
    if program.is_file() {
        let insp = out.join("inspection");
        out!(
            "{} inspecting every pad of the paste layer against {} -> {}",
            step(4),
            program.display(),
            insp.display()
        );
        let (report, _) = dpsa_sim::inspection::evaluate::inspect_dir_shown(
            &map_dir,
            &program,
            None,
            Some(&insp),
            1,
            true,
            progress,
        )?;
        out!("{}", report.summary());
        // A line for this board on loopback (`dpsa line init`), to start and feed in two
        // commands; the demo's own file, made anew each run (with fresh ports).
        let line = out.join("line.toml");
        let _ = std::fs::remove_file(&line);
        let m = dpsa_formats::array::ArrayManifest::load(&board_dir)?;
        let board = dpsa_line::config::InitBoard {
            length_mm: m.board_length_mm,
            width_mm: m.board_width_mm,
            pixel_mm: m.pixel_mm,
        };
        dpsa_line::config::init(&cal_path, &program, &out.join("line-data"), &board, &line)?;
        out!(
            "    the line for this board: {} (start it with `dpsa line run --config {}`, feed it \
             with `dpsa line send {} --config {}`)",
            line.display(),
            line.display(),
            board_dir.display(),
            line.display()
        );
    } else {
        out!(
            "{} (the scene has no paste layer: nothing to inspect)",
            step(4)
        );
    }
    if spec == "small" {
        out!("");
        out!("The paper's full board (three 2048 px cameras, 220 x 168 mm, 5,788 pads; about 0.6 GB of recordings and a few minutes):");
        out!("  dpsa demo --array scenes/paper-board.toml --out out/paper");
    }
    Ok(())
}
