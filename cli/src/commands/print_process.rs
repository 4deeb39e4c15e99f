//! `dpsa print-process`: a simulated print process over a run of boards, either into a new
//! store (`--program --store`: every pad's values drawn, no images) or through a running line
//! as images (`--line --scene`: each board printed by the simulator as the process says, its
//! cameras' streams made by the core and sent to the line like `dpsa line send`, the line
//! inspecting and storing it); with `--printer-applies` the simulated printer applies the
//! line's own printer corrections, closing the loop.

use super::out;
use anyhow::{bail, Context, Result};
use dpsa_line::config::LineConfig;
use dpsa_line::send::{Rate, SendOptions};
use dpsa_line::store::{Store, StoredPrint};
use dpsa_sim::array::scene::ArrayScene;
use dpsa_sim::process::{BoardPrint, ProcessSpec};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("into").required(true).args(["store", "line"])))]
pub struct Args {
    /// The process (`docs/spc.md`, "A known process": boards, seed, in-control scatter,
    /// `[[change]]`s).
    #[arg(long)]
    process: PathBuf,
    /// Into a new store: the inspection program whose pads are printed (its paste layer,
    /// components, windows).
    #[arg(long, requires = "store")]
    program: Option<PathBuf>,
    /// The store to write: a new SQLite file (an existing one is refused).
    #[arg(long, requires = "program")]
    store: Option<PathBuf>,
    /// The line the boards are stored under (`--store`).
    #[arg(long, default_value = "line-1")]
    line_name: String,
    /// Through a running line: its configuration (`dpsa line run --config` of the same file
    /// must be serving; its product's program must be the scene's).
    #[arg(long, requires = "scene")]
    line: Option<PathBuf>,
    /// The array scene the boards are printed and imaged from (`--line`).
    #[arg(long, requires = "line")]
    scene: Option<PathBuf>,
    /// The simulated printer applies the line's printer corrections (the one proposed after
    /// the board `1 + printer.delay_boards` boards before, as a conveyor of that many boards
    /// would give it); without it the printer ignores them.
    #[arg(long, requires = "line")]
    printer_applies: bool,
    /// A scratch directory for each board's recording (removed after each board); default a
    /// temporary directory.
    #[arg(long, requires = "line")]
    work: Option<PathBuf>,
    /// How long to wait for the line to store a board, s.
    #[arg(long, default_value_t = 120.0, requires = "line")]
    wait_s: f64,
    /// Print what was written as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let spec = ProcessSpec::load(&a.process)?;
    if let (Some(line), Some(scene)) = (&a.line, &a.scene) {
        let s = through_line(&spec, line, scene, &a)?;
        if a.json {
            out!("{}", serde_json::to_string_pretty(&s)?);
        } else {
            out!(
                "{} boards through line {} ({}): {} stored, {} incomplete; the printer {} the \
                 line's corrections",
                s.boards.len(),
                s.line,
                s.product,
                s.boards.iter().filter(|b| b.placement.is_some()).count(),
                s.boards.iter().filter(|b| b.placement.is_none()).count(),
                if s.printer_applies {
                    "applied"
                } else {
                    "ignored"
                }
            );
        }
        return Ok(());
    }
    let (Some(program), Some(store)) = (&a.program, &a.store) else {
        bail!("give --program and --store, or --line and --scene");
    };
    let s = dpsa_sim::process::print_process(&spec, program, store, &a.line_name)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        out!(
            "{} boards of {} pads ({} fine apertures) into {}: {} failed, {} warned, {} passed",
            s.boards,
            s.pads,
            s.fine_pads,
            s.store,
            s.fail,
            s.warn,
            s.pass
        );
    }
    Ok(())
}

/// One board of a process run through the line.
#[derive(Clone, Debug, serde::Serialize)]
struct LineBoard {
    /// Board index in the process.
    board: usize,
    /// The line's run id.
    run_id: String,
    /// What the process does to it.
    process: BoardPrint,
    /// The correction the printer applied to it (x, y um; rotation mdeg).
    applied: [f64; 3],
    /// The print it made: the process's shift less the correction, um, and turn, mdeg.
    printed: [f64; 3],
    /// The placement the line measured on it (`None`: incomplete or not fitted).
    placement: Option<[f64; 3]>,
    /// The correction the line proposed after it.
    proposal: [f64; 3],
    /// The line's reason.
    reason: String,
}

/// A process run through the line.
#[derive(Clone, Debug, serde::Serialize)]
struct LineRun {
    line: String,
    product: String,
    printer_applies: bool,
    delay_boards: usize,
    boards: Vec<LineBoard>,
    seconds: f64,
}

/// mrad to millidegrees.
const MDEG_PER_MRAD: f64 = 180.0 / std::f64::consts::PI;

fn through_line(spec: &ProcessSpec, line: &Path, scene: &Path, a: &Args) -> Result<LineRun> {
    spec.validate()
        .map_err(|e| anyhow::anyhow!("{}: {e}", a.process.display()))?;
    if !(a.wait_s.is_finite() && a.wait_s > 0.0 && a.wait_s <= 3600.0) {
        bail!("--wait-s {} is not in (0, 3600] s", a.wait_s);
    }
    let t0 = Instant::now();
    let cfg = LineConfig::load(line)?;
    let base = line.parent().unwrap_or(Path::new("."));
    let file: dpsa_line::config::LineFile =
        toml::from_str(&std::fs::read_to_string(line)?).context("the line's configuration")?;
    let cal = base.join(&file.calibration);
    let product = cfg.products[cfg.default_product].id.clone();
    let mut sc = ArrayScene::load(scene)?;
    super::warn(&sc.warnings());
    let scratch;
    let work = match &a.work {
        Some(w) => {
            std::fs::create_dir_all(w).with_context(|| format!("creating {}", w.display()))?;
            w.clone()
        }
        None => {
            scratch = tempfile::tempdir()?;
            scratch.path().to_path_buf()
        }
    };
    let delay = cfg.printer.delay;
    let mut boards: Vec<LineBoard> = Vec::with_capacity(spec.boards);
    for (b, p) in spec.board_prints().into_iter().enumerate() {
        // The printer's correction in force: the one proposed after the board `delay + 1`
        // before (the boards between were printed before it came).
        let applied = match b.checked_sub(delay + 1) {
            Some(k) if a.printer_applies => boards[k].proposal,
            _ => [0.0; 3],
        };
        let printed = [
            p.shift_um[0] - applied[0],
            p.shift_um[1] - applied[1],
            p.turn_mrad * MDEG_PER_MRAD - applied[2],
        ];
        sc.print.offset_mm = Some([printed[0] / 1000.0, printed[1] / 1000.0]);
        sc.print.rotation_mrad = printed[2] / MDEG_PER_MRAD;
        sc.print.volume_pct = p.volume_pct;
        // The simulator clogs one class of apertures: the losses summed, under the widest
        // area ratio.
        sc.print.clogging_pct = p.clog.iter().map(|c| c.0).sum::<f64>().min(80.0);
        if let Some(r) = p.clog.iter().map(|c| c.1).reduce(f64::max) {
            sc.print.clogging_area_ratio = r;
        }
        // The simulated printer reports its stencil's cleans to the line, as a printer
        // integration would (`dpsa line clean`).
        if spec
            .changes
            .iter()
            .any(|c| matches!(c, dpsa_sim::process::Change::Clean { at } if *at == b))
        {
            Store::open(&cfg.store, &cfg.line)?.record_clean(
                &product,
                dpsa_line::boards::unix_now(),
                "printer (simulated)",
                Some(&format!("the print process's clean before board {b}")),
            )?;
        }
        let seed = spec.seed.wrapping_mul(1_000_003).wrapping_add(b as u64);
        let dir = work.join(format!("board-{b:04}"));
        if dir.exists() {
            std::fs::remove_dir_all(&dir)?;
        }
        dpsa_sim::array::record::simulate_board(&sc, seed, &dir)
            .with_context(|| format!("printing board {b}"))?;
        let streams = super::line::core_streams(&dir, &cal, cfg.listen.len())?;
        std::fs::remove_dir_all(&dir)?;
        let sent = dpsa_line::send::send(
            &streams,
            &SendOptions {
                to: cfg.listen.clone(),
                rate: Rate::Max,
                boards: 1,
                loss: 0.0,
                silent: None,
                silent_for_s: 0.0,
                seed,
            },
        )?;
        let run_id = sent.run_ids[0].clone();
        let row = wait_stored(&cfg, &product, &run_id, a.wait_s)?;
        let pr = &row.print.proposal;
        boards.push(LineBoard {
            board: b,
            run_id,
            process: p,
            applied,
            printed,
            placement: row
                .print
                .placement
                .map(|m| [m.x_um, m.y_um, m.rotation_mdeg]),
            proposal: pr.correction.as_array(),
            reason: pr.reason.clone(),
        });
    }
    Ok(LineRun {
        line: cfg.line.clone(),
        product,
        printer_applies: a.printer_applies,
        delay_boards: delay,
        boards,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Waits until the line has stored board `run_id` with its print row; the row.
fn wait_stored(cfg: &LineConfig, product: &str, run_id: &str, wait_s: f64) -> Result<StoredPrint> {
    let t0 = Instant::now();
    let mut store = Store::open(&cfg.store, &cfg.line)?;
    loop {
        if let Some(r) = store
            .prints(product, 4)?
            .into_iter()
            .find(|r| format!("{:016x}", r.run_id) == run_id)
        {
            return Ok(r);
        }
        if t0.elapsed().as_secs_f64() > wait_s {
            bail!(
                "board {run_id}: not stored by line {} within {wait_s} s (is `dpsa line run \
                 --config` serving, for product {product}?)",
                cfg.line
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}
