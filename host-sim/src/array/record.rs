//! Array recordings on disk: one directory, `array.json`, one single-camera recording per
//! camera (and per calibration pass), and the array truth (`docs/calibration.md`).

use crate::array::frames::{self, FrameFormat};
use crate::array::print::{paste_height, Deposit, DepositIndex, Print};
use crate::array::render::{place_deposits, CameraRenderer, MmDeposit, Surface};
use crate::array::scene::{load_paste_layer, ArrayScene, CameraModel};
use crate::simulation::recording::{
    self, BoardId, FrameEntry, Manifest, Recording, TruthInfo, FORMAT, TRUTH_BACKGROUND_FILE,
    TRUTH_CONTRAST_FILE, TRUTH_HEIGHT_FILE, VERSION,
};
use crate::{At, Result, SimError};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

pub use dpsa_formats::array::{
    ArrayManifest, DesignCamera, Kind, Pass, PassKind, TargetInfo, ARRAY_FILE, ARRAY_FORMAT,
    ARRAY_VERSION,
};
/// The array truth (simulated recordings only).
pub const ARRAY_TRUTH_FILE: &str = "truth/array.json";
/// The board height raster (simulated board recordings only), f32 um, row-major along x.
pub const BOARD_TRUTH_FILE: &str = "truth/board_height_um.f32";
/// The paste layer a board was printed with (a copy of the scene's `paste_layer`).
pub const PASTE_LAYER_FILE: &str = "paste.gbr";
/// The print of a board with a paste layer ([`Print`], JSON): deposits and truth per pad.
pub const PRINT_FILE: &str = "print.json";
/// The inspection program of a board recording with a paste layer (`dpsa inspect --program`).
pub const PROGRAM_FILE: &str = "program.toml";

/// The inspection program matching a board scene: its layer (as copied into the recording),
/// stencil, nominal placement and fiducials, the default windows, and the print truth.
pub fn inspection_program(scene: &ArrayScene) -> crate::inspection::program::Program {
    let mut p = crate::inspection::program::Program::new(PASTE_LAYER_FILE);
    // Named after the board design: its paste layer's file name without `.gbr` / `.paste`.
    p.name = scene.paste_layer.as_ref().map(|l| {
        let f = Path::new(l)
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default();
        let f = f.strip_suffix(".gbr").unwrap_or(&f);
        f.strip_suffix(".paste").unwrap_or(f).to_string()
    });
    p.stencil_um = scene.print.stencil_um;
    p.placement = scene.placement.design();
    p.fiducials.points_mm = scene.fiducials.clone();
    p.fiducials.diameter_mm = scene.fiducial_diameter_mm;
    // The search covers the placement error (3 sigma of offset plus the rotation's reach
    // over the board) with room.
    let reach = 3.0 * scene.placement.offset_sigma_mm
        + 3.0
            * scene.placement.rotation_sigma_deg.to_radians()
            * scene.board_length_mm.hypot(scene.board_width_mm)
            / 2.0;
    p.fiducials.search_mm = (reach + 0.5).clamp(0.5, 20.0);
    p.truth = Some(PRINT_FILE.to_string());
    if let Some(m) = scene.scatter {
        p.measure.lateral_sigma_um = m.lateral_sigma_um;
        p.measure.row_sigma_um = m.row_sigma_um;
        p.measure.row_correlation = m.row_correlation;
    }
    if let Some(r) = scene.reflectance {
        p.reflectance.background_step = r.background_step;
    }
    p
}

/// The board truth raster: `rows x cols` f32 heights at `((i + 1/2) pitch, (j + 1/2) pitch)`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BoardTruthFile {
    /// The raster file, relative to the recording ([`BOARD_TRUTH_FILE`]).
    pub file: String,
    /// Raster pitch on the board (both directions), mm.
    pub pitch_mm: f64,
    /// Rows along the motion.
    pub rows: u32,
    /// Columns across the board.
    pub cols: u32,
}

/// Contents of `truth/array.json`: everything the simulator knew.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ArrayTruth {
    /// True encoder scale, counts per mm of conveyor travel.
    pub counts_per_mm: f64,
    /// The true model of every camera, camera `i` at index `i`.
    pub cameras: Vec<CameraModel>,
    /// Board bow at the centre, um (0 for a calibration recording).
    pub warp_um: f64,
    /// Random-box deposits (scenes without a paste layer; a printed board's deposits are in
    /// [`ArrayManifest::print`]).
    pub deposits: Vec<MmDeposit>,
    /// Per camera: the true background `B` (with illumination) per column of a bare plane, DN.
    pub plane_background_dn: Vec<Vec<f64>>,
    /// Per camera: the true modulation `C M` (with illumination) per column of a bare plane, DN.
    pub plane_modulation_dn: Vec<Vec<f64>>,
    /// The board height raster (board recordings only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board: Option<BoardTruthFile>,
    /// The scene that was rendered.
    pub scene: ArrayScene,
    /// The run's seed (noise, conveyor, placement).
    pub seed: u64,
}

/// An opened array recording.
#[derive(Clone, Debug)]
pub struct ArrayRecording {
    /// The recording's directory.
    pub dir: PathBuf,
    /// Its `array.json`.
    pub manifest: ArrayManifest,
}

impl ArrayRecording {
    /// Opens the array recording `dir`: reads and checks its `array.json`
    /// ([`ArrayManifest::load`]).
    pub fn open(dir: &Path) -> Result<ArrayRecording> {
        Ok(ArrayRecording {
            dir: dir.to_path_buf(),
            manifest: ArrayManifest::load(dir)?,
        })
    }

    /// Directory of camera `cam`'s recording of `pass` (`None`: the board recording).
    pub fn camera_dir(&self, cam: usize, pass: Option<&str>) -> PathBuf {
        let d = self.dir.join(format!("cam{cam}"));
        match pass {
            Some(p) => d.join(p),
            None => d,
        }
    }

    /// The board identity of a board recording with its cameras' recordings `cams` (camera
    /// `i` at index `i`): `array.json`'s `board_id`, which every camera manifest must carry
    /// too (a camera directory of another board is refused). `None` for a recording written
    /// before board identities (neither `array.json` nor any camera has one).
    pub fn board_id(&self, cams: &[Recording]) -> Result<Option<BoardId>> {
        let want = self.manifest.board_id;
        for (i, r) in cams.iter().enumerate() {
            let have = r.manifest.board_id;
            if have != want {
                let show =
                    |b: Option<BoardId>| b.map_or_else(|| "none".to_string(), |b| b.to_string());
                return Err(SimError::Refused(format!(
                    "camera {i}'s recording {} is not of this board: its board id is {}, {} says {}",
                    r.dir.display(),
                    show(have),
                    self.dir.join(ARRAY_FILE).display(),
                    show(want)
                )));
            }
        }
        Ok(want)
    }

    /// The simulator truth, if present.
    pub fn truth(&self) -> Result<Option<ArrayTruth>> {
        let path = self.dir.join(ARRAY_TRUTH_FILE);
        match crate::files::read_capped_io(&path, 1 << 30) {
            Ok(b) => {
                Ok(Some(serde_json::from_slice(&b).at(|| {
                    format!("{}: not a valid array truth", path.display())
                })?))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(SimError::Refused(format!(
                "{} {}",
                path.display(),
                crate::files::io_cause(&e)
            ))),
        }
    }
}

/// Refuses camera recordings that are not at their place: the recording at index `i`
/// (directory `cam{i}`) must say `camera.id = i` in its manifest. Swapped camera directories
/// would otherwise be measured with each other's calibration.
pub fn check_camera_ids(recs: &[Recording], array_dir: &Path) -> Result<()> {
    for (i, r) in recs.iter().enumerate() {
        let id = r.manifest.camera.id;
        if usize::from(id) != i {
            return Err(SimError::Refused(format!(
                "{} is camera {i}'s place in {}, but its manifest says camera.id = {id}: the camera directories are swapped or misnamed",
                r.dir.display(),
                array_dir.display()
            )));
        }
    }
    Ok(())
}

/// What a write produced (sizes and times measured while writing).
#[derive(Clone, Debug, Default, Serialize)]
pub struct WriteSummary {
    /// Cameras written.
    pub cameras: usize,
    /// Frames written, all cameras and passes.
    pub frames: usize,
    /// Pixels in those frames.
    pub pixels: u64,
    /// Bytes written to disk.
    pub bytes: u64,
    /// Wall-clock time of the whole write, s.
    pub seconds: f64,
}

/// Conveyor travel of every frame of a pass from `s_start` while `s <= s_end`, mm.
pub fn conveyor(scene: &ArrayScene, seed: u64, stream: u64, s_start: f64, s_end: f64) -> Vec<f64> {
    crate::simulation::simulate::travel(
        &mut crate::simulation::simulate::rng(seed, stream),
        s_start,
        s_end,
        scene.step_mm(),
        scene.jitter_pct,
        &scene.stalls,
        1_000_000,
    )
}

/// Whether `dir` holds an array recording (its `array.json` of format [`ARRAY_FORMAT`]).
pub fn is_array_recording(dir: &Path) -> bool {
    crate::files::read_capped_io(&dir.join(ARRAY_FILE), crate::files::MAX_MANIFEST_BYTES)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .is_some_and(|v| v.get("format").and_then(|f| f.as_str()) == Some(ARRAY_FORMAT))
}

/// An array recording directory, for [`crate::files::OutputDir`]: written whole into a hidden
/// directory beside the destination (new, empty or an earlier array recording) and swapped in.
pub const DIR_KIND: crate::files::DirKind = crate::files::DirKind {
    format: ARRAY_FORMAT,
    noun: "array recording",
    ours: is_array_recording,
};

/// Renders and writes one camera's recording of one pass into `dir`: frames and truth; the
/// manifest is returned, validated, for the caller to save (a board's cameras get their board
/// identity first).
#[allow(clippy::too_many_arguments)]
fn write_camera(
    scene: &ArrayScene,
    seed: u64,
    cam: usize,
    model: &CameraModel,
    surface: Surface<'_>,
    positions: &[f64],
    stream: u64,
    dir: &Path,
    truth_rows: Option<(i64, i64)>,
) -> Result<(usize, u64, Manifest)> {
    std::fs::create_dir_all(dir.join("frames"))
        .at(|| format!("cannot create {}", dir.display()))?;
    let renderer = CameraRenderer::new(scene, model, surface);
    let ext = scene.frame_format.extension();
    let (rows, width) = (model.rows as usize, model.width as usize);
    let frames_list: Vec<FrameEntry> = positions
        .iter()
        .enumerate()
        .map(|(k, &s)| FrameEntry {
            seq: k as u32,
            latch: (s * scene.counts_per_mm).round() as i64,
            file: format!("frames/{k:06}.{ext}"),
        })
        .collect();
    let next = AtomicUsize::new(0);
    let bytes = AtomicU64::new(0);
    let error: Mutex<Option<SimError>> = Mutex::new(None);
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(positions.len())
        .max(1);
    std::thread::scope(|sc| {
        for _ in 0..threads {
            sc.spawn(|| loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                if k >= positions.len() || error.lock().map(|e| e.is_some()).unwrap_or(true) {
                    break;
                }
                let data = renderer.render(positions[k], seed, stream + k as u64);
                let path = dir.join(&frames_list[k].file);
                let res = match scene.frame_format {
                    FrameFormat::Png => recording::write_frame_png(&path, rows, width, &data)
                        .map_err(SimError::from),
                    FrameFormat::Zfr => frames::encode(rows, width, &data)
                        .map_err(SimError::from)
                        .and_then(|b| Ok(crate::files::write_bytes(&path, &b)?)),
                };
                match res.at(|| format!("writing frame {k}")) {
                    Ok(()) => {
                        let len = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
                        bytes.fetch_add(len, Ordering::Relaxed);
                    }
                    Err(e) => {
                        if let Ok(mut slot) = error.lock() {
                            slot.get_or_insert(e);
                        }
                    }
                }
            });
        }
    });
    if let Some(e) = error.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e);
    }
    let mut total = bytes.into_inner();
    let mut truth = None;
    if let Some((first, last)) = truth_rows {
        let n_rows = (last - first).max(1) as usize;
        let mut h = vec![0f32; n_rows * width];
        let mut bg = vec![0f32; n_rows * width];
        let mut ct = vec![0f32; n_rows * width];
        let r_w = f64::from(model.rows) - (f64::from(scene.max_step_rows()) + 1.0) / 2.0;
        for i in 0..n_rows {
            let b = first + i as i64;
            let s = (b as f64 - r_w) * model.counts_per_pixel / scene.counts_per_mm;
            for c in 0..width {
                let (x, y) = model.board_point(s, r_w, c as f64);
                let j = i * width + c;
                let (height, paste) = renderer.height_at(x, y);
                h[j] = height as f32;
                let (b0, c0) = if paste {
                    (scene.paste_background, scene.paste_contrast)
                } else {
                    (scene.background, scene.contrast)
                };
                bg[j] = (model.illumination[c] * b0) as f32;
                ct[j] = (model.illumination[c] * c0 * renderer.modulation_factor(c)) as f32;
            }
        }
        std::fs::create_dir_all(dir.join("truth"))?;
        for (name, data) in [
            (TRUTH_HEIGHT_FILE, &h),
            (TRUTH_BACKGROUND_FILE, &bg),
            (TRUTH_CONTRAST_FILE, &ct),
        ] {
            recording::write_f32(&dir.join(name), data)?;
            total += data.len() as u64 * 4;
        }
        truth = Some(TruthInfo {
            first_row: first,
            rows: n_rows as u32,
        });
    }
    let manifest = Manifest {
        format: FORMAT.into(),
        version: VERSION,
        camera: scene.camera_block(cam),
        calibration: scene.nominal_calibration(cam),
        processing: scene.processing(),
        frames: frames_list,
        noise: Some(scene.noise()),
        truth,
        board_id: None,
    };
    manifest
        .validate()
        .at(|| "internal error: sub-recording manifest")?;
    Ok((positions.len(), total, manifest))
}

/// The identity of a board recording (how `dpsa simulate` chooses it; a line would take the
/// board's serial number): FNV-1a 64 of the array manifest and then every camera's manifest,
/// each in its canonical JSON form without a board id. The camera manifests are part of it
/// because two boards of one scene have the same `array.json`; their frames' latches differ.
/// Never 0 (0 is "no run id" in a stream header).
pub fn board_identity(array: &ArrayManifest, cameras: &[Manifest]) -> Result<BoardId> {
    let mut a = array.clone();
    a.board_id = None;
    let mut bytes = serde_json::to_vec(&a)?;
    for m in cameras {
        let mut m = m.clone();
        m.board_id = None;
        bytes.push(b'\n');
        bytes.extend(serde_json::to_vec(&m)?);
    }
    Ok(BoardId(dpsa_core::frames::fnv1a64(&bytes).max(1)))
}

fn models(scene: &ArrayScene) -> Vec<CameraModel> {
    (0..scene.cameras.len())
        .map(|i| scene.camera_model(i))
        .collect()
}

fn design(scene: &ArrayScene) -> Vec<DesignCamera> {
    scene
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| DesignCamera {
            id: i as u8,
            width: c.width,
            rows: scene.rows,
            x_mm: c.x_mm,
            y_mm: c.y_mm,
        })
        .collect()
}

fn plane_truth(scene: &ArrayScene, models: &[CameraModel]) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    models
        .iter()
        .map(|m| {
            let r = CameraRenderer::new(scene, m, Surface::Plane { height_um: 0.0 });
            let w = m.width as usize;
            (
                (0..w)
                    .map(|c| m.illumination[c] * scene.background)
                    .collect(),
                (0..w)
                    .map(|c| m.illumination[c] * scene.contrast * r.modulation_factor(c))
                    .collect(),
            )
        })
        .unzip()
}

/// Largest `|rotation|` slack of a camera's ROI along the motion, mm.
fn slack(models: &[CameraModel]) -> f64 {
    models
        .iter()
        .map(|m| f64::from(m.width) * m.pitch_mm * m.rotation_rad.sin().abs() + 3.0 * m.pitch_mm)
        .fold(0.0, f64::max)
}

fn write_json<T: Serialize>(path: &Path, v: &T) -> Result<u64> {
    let mut text = serde_json::to_string_pretty(v)?;
    text.push('\n');
    crate::files::write_bytes(path, text.as_bytes())?;
    Ok(text.len() as u64)
}

/// The deposits of a board scene: the random boxes (scenes without a paste layer; also
/// returned for the truth), or the print of the scene's paste layer with its bytes.
#[allow(clippy::type_complexity)]
pub fn board_deposits(
    scene: &ArrayScene,
    seed: u64,
) -> Result<(Vec<MmDeposit>, Vec<Deposit>, Option<(Print, Vec<u8>)>)> {
    let Some(path) = scene.paste_layer_path() else {
        let boxes = place_deposits(scene, seed);
        let deposits = boxes
            .iter()
            .map(|b| b.to_deposit(scene.deposit_corner_mm, scene.deposit_edge_mm))
            .collect();
        return Ok((boxes, deposits, None));
    };
    let layer = crate::files::read_capped_io(&path, 256 << 20).map_err(|e| {
        SimError::Refused(format!(
            "paste layer {} {}",
            path.display(),
            crate::files::io_cause(&e)
        ))
    })?;
    let pads = load_paste_layer(&path)?;
    if pads.is_empty() {
        return Err(SimError::Refused(format!(
            "paste layer {}: no pads",
            path.display()
        )));
    }
    let (length, width) = (scene.board_length_mm, scene.board_width_mm);
    let inside = |b: [f64; 4]| b[0] >= 0.0 && b[1] >= 0.0 && b[2] <= length && b[3] <= width;
    // The nominal placement must put the whole layer on the board.
    let nominal = scene.placement.nominal();
    let off: Vec<&crate::inspection::pads::Pad> = pads
        .iter()
        .filter(|p| !inside(p.outline.transformed(&nominal).bbox()))
        .collect();
    if let Some(first) = off.first() {
        let c = nominal.apply(first.outline.centroid());
        return Err(SimError::Refused(format!(
            "paste layer {}: {} of {} pads fall outside the {length} x {width} mm board under the nominal [placement] (first: {} at [{:.3}, {:.3}] mm on the board); check placement.design_origin_mm and orientation_deg",
            path.display(),
            off.len(),
            pads.len(),
            first.name(),
            c[0],
            c[1]
        )));
    }
    for f in &scene.fiducials {
        let c = nominal.apply(*f);
        let r = scene.fiducial_diameter_mm / 2.0;
        if !inside([c[0] - r, c[1] - r, c[0] + r, c[1] + r]) {
            return Err(SimError::Refused(format!(
                "fiducial at [{}, {}] (design) falls outside the board under the nominal [placement]",
                f[0],
                f[1]
            )));
        }
    }
    let t = scene.placement.design_to_board(length, width, seed);
    // The print is the board's own (its `[print] seed` when given: the same board every
    // run, as a repeatability study needs); the placement and the noise are the run's.
    let print_seed = scene.print.seed.unwrap_or(seed);
    let print = crate::array::print::print(
        &pads,
        &scene.fiducials,
        &scene.print_params(),
        &t,
        print_seed,
    )
    .at(|| format!("printing {}", path.display()))?;
    if let Some(d) = print.deposits.iter().find(|d| !inside(d.reach_bbox())) {
        return Err(SimError::Refused(format!(
            "the board's placement error (placement.offset_sigma_mm, rotation_sigma_deg) moves {} off the board; lower them or keep the layer further from the board edges",
            d.pad.map_or_else(|| "a fiducial or bridge".to_string(), |i| pads[i].name())
        )));
    }
    let deposits = print.deposits.clone();
    Ok((Vec::new(), deposits, Some((print, layer))))
}

/// Simulates the board of an array scene into `out`: `array.json`, `cam{i}/` (a recording
/// each tool reads), `truth/`.
pub fn simulate_board(scene: &ArrayScene, seed: u64, out: &Path) -> Result<WriteSummary> {
    scene.validate()?;
    let t0 = Instant::now();
    // The print first: a layer that cannot be printed leaves no directory behind.
    let (boxes, deposits, printed) = board_deposits(scene, seed)?;
    let staging = crate::files::OutputDir::create(out, DIR_KIND)?;
    let out = staging.path();
    let models = models(scene);
    let sl = slack(&models);
    let s0 = models
        .iter()
        .map(|m| -m.x0_mm - m.pitch_mm * f64::from(m.rows))
        .fold(f64::INFINITY, f64::min)
        - sl;
    let s1 = scene.board_length_mm - models.iter().map(|m| m.x0_mm).fold(f64::INFINITY, f64::min)
        + (f64::from(scene.n) * f64::from(scene.max_step_rows()) + 2.0) * scene.pixel_mm
        + sl;
    let positions = conveyor(scene, seed, 2, s0, s1);
    let mut sum = WriteSummary {
        cameras: models.len(),
        ..WriteSummary::default()
    };
    let mut manifests = Vec::with_capacity(models.len());
    for (i, m) in models.iter().enumerate() {
        let rows = scene.camera_truth.then(|| {
            let first = (s0 * scene.counts_per_mm / m.counts_per_pixel).floor() as i64;
            let last =
                (s1 * scene.counts_per_mm / m.counts_per_pixel).ceil() as i64 + i64::from(m.rows);
            (first, last)
        });
        let (frames, bytes, manifest) = write_camera(
            scene,
            seed,
            i,
            m,
            Surface::Board {
                deposits: &deposits,
            },
            &positions,
            (1 << 32) + ((i as u64) << 24),
            &out.join(format!("cam{i}")),
            rows,
        )?;
        manifests.push(manifest);
        sum.frames += frames;
        sum.bytes += bytes;
        sum.pixels += frames as u64 * u64::from(m.rows) * u64::from(m.width);
    }
    std::fs::create_dir_all(out.join("truth"))?;
    let tp = scene.truth_pitch_mm;
    let (tr, tc) = (
        (scene.board_length_mm / tp).ceil() as usize,
        (scene.board_width_mm / tp).ceil() as usize,
    );
    let index = DepositIndex::new(&deposits);
    let mut raster = vec![0f32; tr * tc];
    for (i, row) in raster.chunks_exact_mut(tc).enumerate() {
        let x = (i as f64 + 0.5) * tp;
        for (j, v) in row.iter_mut().enumerate() {
            let y = (j as f64 + 0.5) * tp;
            *v = (scene.warp(x, y) + paste_height(&deposits, &index, [x, y]).0) as f32;
        }
    }
    recording::write_f32(&out.join(BOARD_TRUTH_FILE), &raster)?;
    sum.bytes += raster.len() as u64 * 4;
    let (pb, pm) = plane_truth(scene, &models);
    let truth = ArrayTruth {
        counts_per_mm: scene.counts_per_mm,
        cameras: models,
        warp_um: scene.warp_um,
        deposits: boxes,
        plane_background_dn: pb,
        plane_modulation_dn: pm,
        board: Some(BoardTruthFile {
            file: BOARD_TRUTH_FILE.into(),
            pitch_mm: tp,
            rows: tr as u32,
            cols: tc as u32,
        }),
        scene: scene.clone(),
        seed,
    };
    sum.bytes += write_json(&out.join(ARRAY_TRUTH_FILE), &truth)?;
    if let Some((_, layer)) = &printed {
        crate::files::write_bytes(&out.join(PASTE_LAYER_FILE), layer)?;
        sum.bytes += layer.len() as u64;
        let program = inspection_program(scene);
        let text = program.to_toml_string();
        crate::files::write_bytes(&out.join(PROGRAM_FILE), text.as_bytes())?;
        sum.bytes += text.len() as u64;
    }
    let mut manifest = ArrayManifest {
        format: ARRAY_FORMAT.into(),
        version: ARRAY_VERSION,
        kind: Kind::Board,
        cameras: design(scene),
        pixel_mm: scene.pixel_mm,
        nominal_counts_per_mm: scene.nominal_counts_per_mm,
        board_length_mm: scene.board_length_mm,
        board_width_mm: scene.board_width_mm,
        passes: Vec::new(),
        target: None,
        board_id: None,
        paste_layer: printed.as_ref().map(|_| PASTE_LAYER_FILE.to_string()),
        print: printed.as_ref().map(|_| PRINT_FILE.to_string()),
    };
    // One identity for the board, in every camera's manifest and in array.json (written
    // last, as before: a recording without it is incomplete).
    let id = board_identity(&manifest, &manifests)?;
    manifest.board_id = Some(id);
    if let Some((mut print, _)) = printed {
        print.board_id = Some(id);
        sum.bytes += write_json(&out.join(PRINT_FILE), &print)?;
    }
    for (i, mut m) in manifests.into_iter().enumerate() {
        m.board_id = Some(id);
        m.save(&out.join(format!("cam{i}")))?;
    }
    sum.bytes += write_json(&out.join(ARRAY_FILE), &manifest)?;
    staging.commit()?;
    sum.seconds = t0.elapsed().as_secs_f64();
    Ok(sum)
}

/// Simulates the calibration recordings of an array scene into `out`: for every camera, each
/// plane of `calibration.plane_heights_um`, the held-out plane and the lateral target.
pub fn simulate_calibration(scene: &ArrayScene, seed: u64, out: &Path) -> Result<WriteSummary> {
    scene.validate()?;
    let staging = crate::files::OutputDir::create(out, DIR_KIND)?;
    let out = staging.path();
    let t0 = Instant::now();
    let models = models(scene);
    let plan = &scene.calibration;
    let mut passes: Vec<Pass> = plan
        .plane_heights_um
        .iter()
        .enumerate()
        .map(|(j, &h)| Pass {
            name: format!("plane{j}"),
            kind: PassKind::Plane,
            height_um: h,
        })
        .collect();
    passes.push(Pass {
        name: "holdout".into(),
        kind: PassKind::Holdout,
        height_um: plan.holdout_height_um,
    });
    passes.push(Pass {
        name: "target".into(),
        kind: PassKind::Target,
        height_um: 0.0,
    });
    let sl = slack(&models);
    let lo = models
        .iter()
        .map(|m| -m.x0_mm)
        .fold(f64::NEG_INFINITY, f64::max)
        + sl;
    let hi_off = models
        .iter()
        .map(|m| m.x0_mm + m.pitch_mm * f64::from(m.rows))
        .fold(f64::NEG_INFINITY, f64::max)
        + sl;
    let mut sum = WriteSummary {
        cameras: models.len(),
        ..WriteSummary::default()
    };
    for (pi, pass) in passes.iter().enumerate() {
        let length = if pass.kind == PassKind::Target {
            plan.target_length_mm
        } else {
            plan.plane_length_mm
        };
        let positions = conveyor(scene, seed, 0x200 + pi as u64, lo, length - hi_off);
        if positions.len() < usize::from(scene.n) + 2 {
            return Err(SimError::Refused(format!(
                "calibration pass {}: {length} mm is too short for the cameras' fields (only {} frames); lengthen it",
                pass.name,
                positions.len()
            )));
        }
        for (i, m) in models.iter().enumerate() {
            let surface = match pass.kind {
                PassKind::Target => Surface::Target { plan },
                _ => Surface::Plane {
                    height_um: pass.height_um,
                },
            };
            let dir = out.join(format!("cam{i}")).join(&pass.name);
            let (frames, bytes, manifest) = write_camera(
                scene,
                seed,
                i,
                m,
                surface,
                &positions,
                (2 << 32) + ((pi as u64) << 28) + ((i as u64) << 24),
                &dir,
                None,
            )?;
            manifest.save(&dir)?;
            sum.frames += frames;
            sum.bytes += bytes;
            sum.pixels += frames as u64 * u64::from(m.rows) * u64::from(m.width);
        }
    }
    std::fs::create_dir_all(out.join("truth"))?;
    let (pb, pm) = plane_truth(scene, &models);
    let truth = ArrayTruth {
        counts_per_mm: scene.counts_per_mm,
        cameras: models,
        warp_um: 0.0,
        deposits: Vec::new(),
        plane_background_dn: pb,
        plane_modulation_dn: pm,
        board: None,
        scene: scene.clone(),
        seed,
    };
    sum.bytes += write_json(&out.join(ARRAY_TRUTH_FILE), &truth)?;
    let manifest = ArrayManifest {
        format: ARRAY_FORMAT.into(),
        version: ARRAY_VERSION,
        kind: Kind::Calibration,
        cameras: design(scene),
        pixel_mm: scene.pixel_mm,
        nominal_counts_per_mm: scene.nominal_counts_per_mm,
        board_length_mm: scene.board_length_mm,
        board_width_mm: scene.board_width_mm,
        passes,
        target: Some(TargetInfo {
            pitch_mm: plan.target_pitch_mm,
            origin_mm: plan.target_origin_mm,
            length_mm: plan.target_length_mm,
        }),
        board_id: None,
        paste_layer: None,
        print: None,
    };
    sum.bytes += write_json(&out.join(ARRAY_FILE), &manifest)?;
    staging.commit()?;
    sum.seconds = t0.elapsed().as_secs_f64();
    Ok(sum)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::array::print::Defect;

    #[test]
    fn the_paper_board_prints_its_generated_layer() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/paper-board.toml");
        let scene = ArrayScene::load(&path).unwrap();
        let t0 = Instant::now();
        let (boxes, deposits, printed) = board_deposits(&scene, scene.seed).unwrap();
        let secs = t0.elapsed().as_secs_f64();
        assert!(boxes.is_empty());
        let (print, layer) = printed.unwrap();
        assert_eq!(
            layer,
            std::fs::read(path.with_file_name("paper-board.paste.gbr")).unwrap()
        );
        assert_eq!(print.pads.len(), 5788);
        assert_eq!(deposits, print.deposits);
        for d in [
            Defect::Missing,
            Defect::Insufficient,
            Defect::Excess,
            Defect::Offset,
            Defect::Smear,
        ] {
            assert_eq!(print.count(d), 5, "{d:?}");
        }
        assert_eq!(print.count(Defect::Bridge), 10);
        assert_eq!(print.fiducials.len(), 3);
        assert!(secs < 20.0, "{secs}");
    }
}
