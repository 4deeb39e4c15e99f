//! `LINE.toml`: what `dpsa line run` serves (the cameras' addresses, the calibration, the
//! products and their programs, the data directory, the timeouts), read and checked whole
//! before anything starts; and `dpsa line init`, which writes a working one.
//!
//! Paths are relative to the file's directory. Every key is documented in `docs/line.md`; an
//! unknown key, a missing one or a value out of range is refused with a sentence naming it.

use crate::printer::LoopConfig;
use crate::store::Location;
use crate::LineError;
use dpsa_formats::calibration::CalFile;
use dpsa_formats::grid::BoardGrid;
use dpsa_gerber::pads::Pad;
use dpsa_inspect::program::Program;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

/// The file as written (see the module docs and `docs/line.md`).
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct LineFile {
    /// The array's calibration file (`dpsa calibrate`).
    pub calibration: PathBuf,
    /// Where the line keeps its store (`line.sqlite`, unless `store` says otherwise) and, by
    /// default, its CFX spool.
    pub data: PathBuf,
    /// The board map's pixel, mm (the array's design pitch, `array.json`'s `pixel_mm`).
    pub pixel_mm: f64,
    /// The product of a board when the line is told none ([`PRODUCT_FILE`]; format v2
    /// streams carry no product id).
    pub default_product: String,
    /// The line's name, which its boards are stored under (default `line-1`): each line of
    /// one store needs its own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line: Option<String>,
    /// The store: a PostgreSQL URL (`postgres://...`, one database for many lines); absent,
    /// the SQLite file `DATA/line.sqlite`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub store: Option<String>,
    /// One per camera of the calibration.
    pub camera: Vec<CameraEntry>,
    /// The products the line inspects.
    pub product: Vec<ProductEntry>,
    /// How long the line waits.
    #[serde(default)]
    pub timeouts: Timeouts,
    /// Where finished boards' CFX messages go.
    #[serde(default, skip_serializing_if = "CfxEntry::is_default")]
    pub cfx: CfxEntry,
    /// The loop back to the printer (`docs/spc.md`): its settings.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub printer: Option<PrinterEntry>,
    /// The measured maps kept for the pages' zoom and pan.
    #[serde(default, skip_serializing_if = "MapsEntry::is_default")]
    pub maps: MapsEntry,
    /// How long the store keeps every pad's row.
    #[serde(default, skip_serializing_if = "RetentionEntry::is_default")]
    pub retention: RetentionEntry,
}

/// `[printer]`: the loop back to the printer; every key optional, the defaults those of
/// [`LoopConfig::default`].
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PrinterEntry {
    /// Weight of the newest board in the estimate of the printer's error, (0, 1].
    pub gain: f64,
    /// Boards printed but not yet measured when a board is measured (the conveyor's), 0..=100.
    pub delay_boards: usize,
    /// Dead band of the translation, um, and of the rotation, millidegrees.
    pub dead_band_um: f64,
    /// See `dead_band_um`.
    pub dead_band_mdeg: f64,
    /// The dead band's width in the estimate's standard uncertainties, at least.
    pub dead_band_sigmas: f64,
    /// Largest change at one proposal, um and millidegrees.
    pub max_step_um: f64,
    /// See `max_step_um`.
    pub max_step_mdeg: f64,
    /// Largest correction from zero, um and millidegrees.
    pub max_total_um: f64,
    /// See `max_total_um`.
    pub max_total_mdeg: f64,
}

impl Default for PrinterEntry {
    fn default() -> Self {
        let d = LoopConfig::default();
        PrinterEntry {
            gain: d.gain,
            delay_boards: d.delay,
            dead_band_um: d.dead_band[0],
            dead_band_mdeg: d.dead_band[1],
            dead_band_sigmas: d.sigmas,
            max_step_um: d.max_step[0],
            max_step_mdeg: d.max_step[1],
            max_total_um: d.max_total[0],
            max_total_mdeg: d.max_total[1],
        }
    }
}

impl PrinterEntry {
    /// The loop's settings, each key checked.
    fn check(&self, path: &Path) -> Result<LoopConfig, LineError> {
        let key = |s: &str| format!("printer.{s}");
        if !(self.gain.is_finite() && self.gain > 0.0 && self.gain <= 1.0) {
            return Err(bad(
                path,
                &key("gain"),
                format!("{} is not in (0, 1]", self.gain),
            ));
        }
        if self.delay_boards > 100 {
            return Err(bad(
                path,
                &key("delay_boards"),
                format!("{} boards is more than 100", self.delay_boards),
            ));
        }
        for (name, v, min) in [
            ("dead_band_um", self.dead_band_um, 0.0),
            ("dead_band_mdeg", self.dead_band_mdeg, 0.0),
            ("dead_band_sigmas", self.dead_band_sigmas, 0.0),
        ] {
            if !(v.is_finite() && v >= min && v <= 10_000.0) {
                return Err(bad(path, &key(name), format!("{v} is not in [0, 10000]")));
            }
        }
        for (name, v) in [
            ("max_step_um", self.max_step_um),
            ("max_step_mdeg", self.max_step_mdeg),
            ("max_total_um", self.max_total_um),
            ("max_total_mdeg", self.max_total_mdeg),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 10_000.0) {
                return Err(bad(path, &key(name), format!("{v} is not in (0, 10000]")));
            }
        }
        Ok(LoopConfig {
            gain: self.gain,
            delay: self.delay_boards,
            dead_band: [self.dead_band_um, self.dead_band_mdeg],
            sigmas: self.dead_band_sigmas,
            max_step: [self.max_step_um, self.max_step_mdeg],
            max_total: [self.max_total_um, self.max_total_mdeg],
        })
    }
}

/// `[[camera]]`: where a camera's frame grabber connects.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CameraEntry {
    /// The camera's id (its place in the calibration).
    pub id: u8,
    /// The address the line listens on for this camera's stream (TCP).
    pub listen: SocketAddr,
}

/// `[[product]]`: a product and its inspection program.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ProductEntry {
    /// The product's id.
    pub id: String,
    /// Its inspection program (`program.toml`, `dpsa program`).
    pub program: PathBuf,
    /// The board's length along the conveyor, mm.
    pub board_length_mm: f64,
    /// The board's width across it, mm.
    pub board_width_mm: f64,
}

/// `[timeouts]`, seconds.
#[derive(Clone, Copy, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Timeouts {
    /// A connection that sends no stream header within this is closed.
    pub header_s: f64,
    /// A camera of an open board that sends nothing for this long (or never begins): the
    /// board is incomplete.
    pub silent_s: f64,
    /// A board open longer than this is incomplete.
    pub board_s: f64,
}

impl Default for Timeouts {
    fn default() -> Self {
        Timeouts {
            header_s: 5.0,
            silent_s: 5.0,
            board_s: 120.0,
        }
    }
}

/// `[cfx]`.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CfxEntry {
    /// The spool directory `UnitsInspected` messages are written into, one file per finished
    /// board (default `DATA/cfx`).
    pub spool: Option<PathBuf>,
}

impl CfxEntry {
    fn is_default(&self) -> bool {
        self.spool.is_none()
    }
}

/// `[maps]`: the newest finished boards' measured maps (inspected, or left incomplete because
/// the design could not be registered on them), kept for the board page's zoom and pan
/// (`dpsa_formats::kept_map`: about 45 MB a paper board).
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct MapsEntry {
    /// The directory (default `DATA/maps`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dir: Option<PathBuf>,
    /// How many of the newest boards' maps are kept (default [`DEFAULT_KEEP_MAPS`]; 0: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keep_boards: Option<usize>,
}

impl MapsEntry {
    fn is_default(&self) -> bool {
        self.dir.is_none() && self.keep_boards.is_none()
    }
}

/// `[retention]`: the store's pad rows (every pad of every board, about 120 bytes each in
/// SQLite: 62 GB a day at a board a second of 6,000 pads) are deleted once their board ended
/// `pad_days` days ago; the boards' rows, their cameras' losses, the prints and the per-pad
/// running aggregates (`pad_stats`) are kept for ever. The line's keeper deletes after each
/// board it stores, at most [`crate::keeper::PRUNE_BOARDS_PER_BOARD`] boards' pads, the
/// oldest first.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RetentionEntry {
    /// Days a board's pad rows are kept after it ended (absent: for ever).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pad_days: Option<f64>,
}

impl RetentionEntry {
    fn is_default(&self) -> bool {
        self.pad_days.is_none()
    }
}

/// The retention [`crate::config::init`] writes: 30 days, what the scale asks the
/// store to be designed for (1.9 TB of pad rows in SQLite at a board a second of 6,000
/// pads; a smaller board or a slower line takes proportionally less).
pub const INIT_PAD_DAYS: f64 = 30.0;
/// Most days `[retention] pad_days` may say (a century).
pub const MAX_PAD_DAYS: f64 = 36_500.0;

/// The file in the data directory that tells the line the product of the boards that begin
/// from now on (their streams carry none: format v2): one product id of LINE.toml; absent, the
/// `default_product`. `dpsa line product` writes it (atomically); a line controller or MES may
/// write it too. Read at each board's start; a board begun while it names no product of the
/// configuration is stored incomplete with the reason, never inspected against another
/// product's program.
pub const PRODUCT_FILE: &str = "product";

/// Boards whose maps the line keeps unless `[maps] keep_boards` says otherwise.
pub const DEFAULT_KEEP_MAPS: usize = 10;
/// Most boards' maps `[maps] keep_boards` may ask for.
pub const MAX_KEEP_MAPS: usize = 10_000;

/// The maps the line keeps.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Maps {
    /// Their directory.
    pub dir: PathBuf,
    /// How many boards' (0: none).
    pub keep_boards: usize,
}

/// A product ready to inspect.
pub struct Product {
    /// Its id.
    pub id: String,
    /// The program.
    pub program: Program,
    /// The program's file.
    pub program_path: PathBuf,
    /// The pads of its paste layer (names from its placement file).
    pub pads: Vec<Pad>,
    /// Each pad's package family (`dpsa_inspect::teach::pad_families`).
    pub families: Vec<Option<String>>,
    /// The board map's grid.
    pub grid: BoardGrid,
    /// FNV-1a 64 of the program file and its paste layer, 16 hex digits.
    pub program_hash: String,
}

/// The checked configuration: everything loaded.
pub struct LineConfig {
    /// The file's path.
    pub path: PathBuf,
    /// The calibration.
    pub cal: CalFile,
    /// FNV-1a 64 of the calibration file, 16 hex digits.
    pub calibration_hash: String,
    /// The data directory.
    pub data: PathBuf,
    /// The line's name.
    pub line: String,
    /// The store.
    pub store: Location,
    /// The CFX spool directory.
    pub spool: PathBuf,
    /// Listening address per camera, in camera order.
    pub listen: Vec<SocketAddr>,
    /// The products.
    pub products: Vec<Product>,
    /// Index of the default product in `products`.
    pub default_product: usize,
    /// The timeouts.
    pub timeouts: Timeouts,
    /// Per camera: the configuration hash its streams must carry.
    pub config_hashes: Vec<u64>,
    /// The loop back to the printer.
    pub printer: LoopConfig,
    /// The measured maps kept for the pages.
    pub maps: Maps,
    /// Days a board's pad rows are kept after it ended (`None`: for ever).
    pub pad_days: Option<f64>,
}

/// FNV-1a 64 of some byte strings, as 16 hex digits.
pub fn fnv_hex(parts: &[&[u8]]) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for p in parts {
        for &b in *p {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    format!("{h:016x}")
}

fn bad(path: &Path, key: &str, why: impl std::fmt::Display) -> LineError {
    LineError::Config {
        path: path.to_path_buf(),
        why: format!("{key}: {why}"),
    }
}

/// A program with what the line and the pages take from it: its paste layer's pads (named
/// from its placement file), each pad's package family, and the hash that boards carry.
pub struct Design {
    /// The program's file, as given.
    pub path: PathBuf,
    /// The program.
    pub program: Program,
    /// Its paste layer's pads, in the layer's order (a pad row's index).
    pub pads: Vec<Pad>,
    /// Each pad's package family (`dpsa_inspect::teach::pad_families`).
    pub families: Vec<Option<String>>,
    /// FNV-1a 64 of the program file and its paste layer, 16 hex digits: the stored boards'
    /// `program_hash`.
    pub program_hash: String,
}

impl Design {
    /// Reads the program at `program_path` and its paste layer (and placement file).
    pub fn load(program_path: &Path) -> Result<Design, LineError> {
        let bad = |e: String| LineError::Config {
            path: program_path.to_path_buf(),
            why: e,
        };
        let prog_bytes = read(program_path, "inspection program", 16 << 20)?;
        let mut program = Program::load(program_path).map_err(|e| bad(e.to_string()))?;
        let layer_path = program.paste_layer_path(program_path);
        let layer_bytes = read(&layer_path, "paste layer", 256 << 20)?;
        let (mut pads, _) = dpsa_inspect::run::paste_layer_pads(&program, program_path)
            .map_err(|e| bad(e.to_string()))?;
        dpsa_inspect::teach::apply_components(&mut program, program_path, &mut pads)
            .map_err(|e| bad(dpsa_inspect::InspectError::from(e).to_string()))?;
        let families = dpsa_inspect::teach::pad_families(&program, program_path, &pads)
            .map_err(|e| bad(dpsa_inspect::InspectError::from(e).to_string()))?;
        Ok(Design {
            path: program_path.to_path_buf(),
            program,
            pads,
            families,
            program_hash: fnv_hex(&[&prog_bytes, &layer_bytes]),
        })
    }
}

fn read(path: &Path, what: &str, max: u64) -> Result<Vec<u8>, LineError> {
    dpsa_formats::files::read_capped(path, max, what).map_err(LineError::File)
}

impl LineConfig {
    /// Reads and checks `path`: the keys, the calibration, every product's program and paste
    /// layer, the cameras against the calibration; creates the data and spool directories.
    pub fn load(path: &Path) -> Result<LineConfig, LineError> {
        let bytes = read(path, "line configuration", 1 << 20)?;
        let text = String::from_utf8(bytes).map_err(|_| bad(path, "the file", "not UTF-8"))?;
        let f: LineFile = toml::from_str(&text).map_err(|e| LineError::Config {
            path: path.to_path_buf(),
            why: e.to_string().trim().replace('\n', " "),
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        let at = |p: &Path| base.join(p);
        // The line and the store first: they need nothing loaded.
        let line = f
            .line
            .clone()
            .unwrap_or_else(|| crate::store::DEFAULT_LINE.to_owned());
        crate::store::check_line_name(&line).map_err(|why| bad(path, "line", why))?;
        let store = match &f.store {
            None => Location::Sqlite(at(&f.data).join(crate::service::STORE_FILE)),
            Some(text) => Location::postgres(text).map_err(|why| {
                bad(
                    path,
                    "store",
                    format!(
                        "{why}; leave the key out for the SQLite file {}",
                        Path::new("DATA").join(crate::service::STORE_FILE).display()
                    ),
                )
            })?,
        };

        let cal_path = at(&f.calibration);
        let cal_bytes = read(&cal_path, "calibration file", 64 << 20)
            .map_err(|e| bad(path, "calibration", e))?;
        let cal = CalFile::load(&cal_path).map_err(|e| bad(path, "calibration", e))?;
        let calibration_hash = fnv_hex(&[&cal_bytes]);

        if !(f.pixel_mm.is_finite() && f.pixel_mm > 0.0 && f.pixel_mm <= 1.0) {
            return Err(bad(
                path,
                "pixel_mm",
                format!("{} is not a pixel pitch in (0, 1] mm", f.pixel_mm),
            ));
        }
        let n = cal.camera.len();
        if f.camera.len() != n {
            return Err(bad(
                path,
                "camera",
                format!("{} cameras listed; the calibration has {n}", f.camera.len()),
            ));
        }
        let mut listen: Vec<Option<SocketAddr>> = vec![None; n];
        for (k, c) in f.camera.iter().enumerate() {
            let i = usize::from(c.id);
            if i >= n {
                return Err(bad(
                    path,
                    &format!("camera[{k}].id"),
                    format!(
                        "{} is not a camera of the calibration (0..={})",
                        c.id,
                        n - 1
                    ),
                ));
            }
            if listen[i].is_some() {
                return Err(bad(
                    path,
                    &format!("camera[{k}].id"),
                    format!("camera {} listed twice", c.id),
                ));
            }
            if f.camera
                .iter()
                .take(k)
                .any(|o| o.listen == c.listen && c.listen.port() != 0)
            {
                return Err(bad(
                    path,
                    &format!("camera[{k}].listen"),
                    format!("{} is another camera's address too", c.listen),
                ));
            }
            listen[i] = Some(c.listen);
        }
        let listen: Vec<SocketAddr> = listen.into_iter().flatten().collect();
        let t = f.timeouts;
        for (key, v, max) in [
            ("timeouts.header_s", t.header_s, 3600.0),
            ("timeouts.silent_s", t.silent_s, 3600.0),
            ("timeouts.board_s", t.board_s, 86_400.0),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= max) {
                return Err(bad(path, key, format!("{v} s is not in (0, {max}] s")));
            }
        }
        if f.product.is_empty() {
            return Err(bad(
                path,
                "product",
                "no product: list at least one [[product]]",
            ));
        }
        let mut products = Vec::with_capacity(f.product.len());
        for (k, p) in f.product.iter().enumerate() {
            let key = |s: &str| format!("product[{k}].{s}");
            if p.id.is_empty() || products.iter().any(|q: &Product| q.id == p.id) {
                return Err(bad(
                    path,
                    &key("id"),
                    format!("{:?} is empty or given twice", p.id),
                ));
            }
            for (name, v) in [
                ("board_length_mm", p.board_length_mm),
                ("board_width_mm", p.board_width_mm),
            ] {
                if !(v.is_finite() && v > 0.0 && v <= 2000.0) {
                    return Err(bad(
                        path,
                        &key(name),
                        format!("{v} mm is not a board size in (0, 2000] mm"),
                    ));
                }
            }
            let grid = BoardGrid {
                x0_mm: 0.0,
                y0_mm: 0.0,
                pitch_mm: f.pixel_mm,
                rows: (p.board_length_mm / f.pixel_mm).ceil() as usize,
                width: (p.board_width_mm / f.pixel_mm).ceil() as usize,
            };
            if grid.rows.saturating_mul(grid.width) > 1 << 28 {
                return Err(bad(
                    path,
                    &key("board_length_mm"),
                    format!(
                        "a {} x {} px board map is more than the line holds (2^28 px)",
                        grid.rows, grid.width
                    ),
                ));
            }
            let program_path = at(&p.program);
            let d = Design::load(&program_path).map_err(|e| bad(path, &key("program"), e))?;
            products.push(Product {
                id: p.id.clone(),
                program: d.program,
                program_path,
                pads: d.pads,
                families: d.families,
                grid,
                program_hash: d.program_hash,
            });
        }
        let default_product = products
            .iter()
            .position(|p| p.id == f.default_product)
            .ok_or_else(|| {
                bad(
                    path,
                    "default_product",
                    format!("{:?} is not one of the products listed", f.default_product),
                )
            })?;
        let config_hashes = (0..n)
            .map(|i| {
                dpsa_board::streams::expected_config_hash(&cal, i)
                    .map_err(|e| bad(path, "calibration", e))
            })
            .collect::<Result<Vec<u64>, LineError>>()?;
        let printer = f.printer.clone().unwrap_or_default().check(path)?;
        let data = at(&f.data);
        let spool = f.cfx.spool.as_deref().map_or_else(|| data.join("cfx"), at);
        let keep_boards = f.maps.keep_boards.unwrap_or(DEFAULT_KEEP_MAPS);
        if keep_boards > MAX_KEEP_MAPS {
            return Err(bad(
                path,
                "maps.keep_boards",
                format!("{keep_boards} is more than {MAX_KEEP_MAPS}"),
            ));
        }
        let maps = Maps {
            dir: f.maps.dir.as_deref().map_or_else(|| data.join("maps"), at),
            keep_boards,
        };
        if let Some(d) = f.retention.pad_days {
            if !(d.is_finite() && d > 0.0 && d <= MAX_PAD_DAYS) {
                return Err(bad(
                    path,
                    "retention.pad_days",
                    format!(
                        "{d} days is not in (0, {MAX_PAD_DAYS}]; leave the key out to keep \
                         every pad row for ever"
                    ),
                ));
            }
        }
        for (key, d) in [
            ("data", &data),
            ("cfx.spool", &spool),
            ("maps.dir", &maps.dir),
        ] {
            std::fs::create_dir_all(d)
                .map_err(|e| bad(path, key, format!("cannot create {}: {e}", d.display())))?;
        }
        Ok(LineConfig {
            path: path.to_path_buf(),
            cal,
            calibration_hash,
            data,
            line,
            store,
            spool,
            listen,
            products,
            default_product,
            timeouts: t,
            config_hashes,
            printer,
            maps,
            pad_days: f.retention.pad_days,
        })
    }
}

impl LineConfig {
    /// The line's product file ([`PRODUCT_FILE`] in the data directory).
    pub fn product_file(&self) -> PathBuf {
        self.data.join(PRODUCT_FILE)
    }

    /// Each product's id and board map grid, in order.
    pub fn product_grids(&self) -> Vec<(String, BoardGrid)> {
        self.products
            .iter()
            .map(|p| (p.id.clone(), p.grid))
            .collect()
    }

    /// The product of the boards that begin now (index into `products`): what the product
    /// file names, or the default without one; `Err` says why the file names none
    /// ([`crate::boards::product_named`]).
    pub fn product_now(&self) -> Result<usize, String> {
        crate::boards::product_named(
            &self.product_file(),
            &self.product_grids(),
            self.default_product,
        )
    }
}

/// What `dpsa line init` needs besides the calibration and the program.
pub struct InitBoard {
    /// Board length along the conveyor and width across it, mm.
    pub length_mm: f64,
    /// See `length_mm`.
    pub width_mm: f64,
    /// The board map's pixel, mm.
    pub pixel_mm: f64,
}

/// `dpsa line init`: a configuration for one product on loopback, with a free port per camera
/// (each port taken and released at once, so another program may take it before the line
/// starts: `dpsa line run` then says which address is in use). Paths are written absolute.
/// The result is loaded back before it is written, so a configuration that would not start is
/// never written.
pub fn init(
    cal: &Path,
    program: &Path,
    data: &Path,
    board: &InitBoard,
    out: &Path,
) -> Result<LineFile, LineError> {
    let abs = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    let calf = CalFile::load(cal).map_err(|e| bad(cal, "calibration", e))?;
    let mut camera = Vec::new();
    for c in &calf.camera {
        let l = std::net::TcpListener::bind(("127.0.0.1", 0))
            .map_err(|e| LineError::Io(format!("no free loopback port: {e}")))?;
        let listen = l.local_addr().map_err(|e| LineError::Io(e.to_string()))?;
        camera.push(CameraEntry { id: c.id, listen });
    }
    let id = Program::load(program)
        .ok()
        .and_then(|p| p.name)
        .filter(|n| !n.is_empty())
        .unwrap_or_else(|| "default".into());
    let f = LineFile {
        calibration: abs(cal),
        data: abs(data),
        pixel_mm: board.pixel_mm,
        default_product: id.clone(),
        line: None,
        store: None,
        camera,
        product: vec![ProductEntry {
            id,
            program: abs(program),
            board_length_mm: board.length_mm,
            board_width_mm: board.width_mm,
        }],
        timeouts: Timeouts::default(),
        cfx: CfxEntry::default(),
        maps: MapsEntry::default(),
        printer: None,
        retention: RetentionEntry {
            pad_days: Some(INIT_PAD_DAYS),
        },
    };
    let text = format!(
        "# dpsa line: one line's configuration (docs/line.md lists every key).\n\
         # Written by `dpsa line init`; edit it, then `dpsa line run --config {}`.\n\
         # [retention] pad_days: every pad's row is deleted that many days after its board\n\
         # (the boards and the per-pad aggregates stay); remove the table to keep them all.\n\n{}",
        out.display(),
        toml::to_string_pretty(&f).map_err(|e| LineError::Io(e.to_string()))?
    );
    if out.exists() {
        return Err(LineError::Io(format!(
            "{} exists (an edited configuration is never replaced): remove it or give another --out",
            out.display()
        )));
    }
    use dpsa_formats::files::Input;
    dpsa_formats::files::refuse_overwrite("--out", out, &[Input::File(cal), Input::File(program)])
        .map_err(LineError::File)?;
    // Loaded back from a scratch copy beside it before it is written.
    let dir = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let probe = tempfile::Builder::new()
        .prefix(".line-init")
        .suffix(".toml")
        .tempfile_in(dir)
        .map_err(|e| LineError::Io(format!("cannot write in {}: {e}", dir.display())))?;
    std::fs::write(probe.path(), &text).map_err(|e| LineError::Io(e.to_string()))?;
    LineConfig::load(probe.path())?;
    dpsa_formats::files::write_bytes(out, text.as_bytes()).map_err(LineError::File)?;
    Ok(f)
}
