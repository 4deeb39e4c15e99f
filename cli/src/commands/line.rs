//! `dpsa line`: the line service (`run`), its configuration (`init`), the simulated frame
//! grabbers that feed it (`send`), what it stored (`boards`) and the store's benchmark
//! (`store-bench`). The work is in `dpsa-line`; see `docs/line.md`.

use super::out;
use anyhow::{bail, Context, Result};
use dpsa_line::config::{InitBoard, LineConfig};
use dpsa_line::send::{Rate, SendOptions};
use dpsa_line::store::Location;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    cmd: LineCmd,
}

#[derive(clap::Subcommand)]
enum LineCmd {
    /// Run the line: take boards from the frame grabbers, stitch, inspect, store, spool CFX.
    /// Logs on stderr; on exit (SIGTERM, SIGINT, --boards) prints its summary as JSON.
    Run(RunArgs),
    /// Write a working configuration for one product on loopback (free ports chosen).
    Init(InitArgs),
    /// Simulated frame grabbers: replay a board's camera streams to the line.
    Send(SendArgs),
    /// The boards the line stored, newest first, as JSON.
    Boards(BoardsArgs),
    /// Tell the line the product of the boards that begin from now on (--set ID), or that
    /// they are the configuration's default product again (--default); without either, say
    /// which it is. Prints it as JSON.
    Product(ProductArgs),
    /// Check the store (SQLite's page and foreign-key checks, and the schema's rules on every
    /// row), or with --newest N the rules on its newest boards' rows, as `line run` does at
    /// start on a store too large to read whole. Prints the result as JSON; a store found
    /// damaged is an error, naming what was found.
    Check(CheckArgs),
    /// Record that the stencil was cleaned (now, or --at): `dpsa spc` counts the fine
    /// apertures' clogging from the last clean. Prints the event as JSON.
    Clean(CleanArgs),
    /// Benchmark the store: inserts per second, a pad's history, bytes per board; as JSON.
    StoreBench(StoreBenchArgs),
    /// Benchmark the link on loopback: TCP against UDP for one camera's stream, with and
    /// without a receiver that stalls halfway; as JSON.
    LinkBench(LinkBenchArgs),
}

#[derive(clap::Args)]
struct RunArgs {
    /// The line's configuration (`dpsa line init` writes one).
    #[arg(long)]
    config: PathBuf,
    /// Stop (as on SIGTERM) once this many boards ended.
    #[arg(long)]
    boards: Option<usize>,
    /// The store, over the configuration's `store`: a PostgreSQL URL
    /// (postgres://USER:PASSWORD@HOST:PORT/DATABASE) or the path of an SQLite file.
    #[arg(long, value_name = "URL_OR_PATH")]
    store: Option<String>,
    /// Serve the line's pages (`dpsa serve`'s, read-only) on this address while it runs, e.g.
    /// 127.0.0.1:8080 (port 0: one chosen, logged).
    #[arg(long, value_name = "ADDR")]
    web: Option<SocketAddr>,
    /// A file whose first line is the token every review on the pages must carry (as `dpsa
    /// serve --token-file`).
    #[arg(long, value_name = "FILE", requires = "web")]
    web_token_file: Option<PathBuf>,
}

#[derive(clap::Args)]
struct InitArgs {
    /// The array's calibration file (`dpsa calibrate`).
    #[arg(long)]
    cal: PathBuf,
    /// The product's inspection program (`program.toml`).
    #[arg(long)]
    program: PathBuf,
    /// The line's data directory (store, CFX spool).
    #[arg(long)]
    data: PathBuf,
    /// The configuration to write (never over an existing file).
    #[arg(long)]
    out: PathBuf,
    /// Take the board's size and the map's pixel from this board recording's `array.json`.
    #[arg(long, conflicts_with_all = ["board_mm", "pixel_mm"])]
    board: Option<PathBuf>,
    /// The board's length and width, mm (without --board).
    #[arg(long, num_args = 2, value_names = ["LENGTH", "WIDTH"], value_parser = super::positive)]
    board_mm: Option<Vec<f64>>,
    /// The board map's pixel, mm (without --board).
    #[arg(long, value_parser = super::positive)]
    pixel_mm: Option<f64>,
}

#[derive(clap::Args)]
struct SendArgs {
    /// A board: a directory of its cameras' packet streams (`*.dpsa`, matched by the camera
    /// id of their headers) or, with the simulator, an array board recording (each camera
    /// run through the core with the line's calibration).
    rec: PathBuf,
    /// Send to the cameras' addresses of this configuration.
    #[arg(long, conflicts_with = "to")]
    config: Option<PathBuf>,
    /// Send to these addresses (camera order).
    #[arg(long, num_args = 1..)]
    to: Vec<SocketAddr>,
    /// The calibration the core runs with for a board recording (default: the config's).
    #[arg(long)]
    cal: Option<PathBuf>,
    /// `paper`: the rows at the paper's conveyor speed (220 mm/s); `max`: as fast as it goes;
    /// or a conveyor speed in mm/s.
    #[arg(long, default_value = "paper", value_parser = rate)]
    rate: String,
    /// Consecutive boards, each with a fresh run id.
    #[arg(long, default_value_t = 1)]
    boards: usize,
    /// Probability that a packet is lost (not the stream header or end).
    #[arg(long, default_value_t = 0.0, value_parser = super::finite)]
    loss: f64,
    /// This camera falls silent in the first board ...
    #[arg(long, requires = "at")]
    drop_camera: Option<usize>,
    /// ... at this board row.
    #[arg(long, requires = "drop_camera")]
    at: Option<i64>,
    /// How long the silent camera's connection stays open (and silent), s.
    #[arg(long, default_value_t = 10.0, value_parser = super::positive)]
    silent_for: f64,
    /// Seeds the run ids and the losses (default: the clock).
    #[arg(long)]
    seed: Option<u64>,
}

#[derive(clap::Args)]
struct BoardsArgs {
    /// The line's configuration.
    #[arg(long)]
    config: PathBuf,
    /// At most this many boards.
    #[arg(long, default_value_t = 50)]
    last: usize,
    /// With every pad of each board.
    #[arg(long)]
    pads: bool,
    /// With each board's print: the placement measured on it and the printer correction the
    /// loop proposed after it (`print`, null for a board the line stored without one).
    #[arg(long)]
    prints: bool,
    /// The store, over the configuration's `store`: a PostgreSQL URL or the path of an
    /// SQLite file. The boards listed are the configuration's line's.
    #[arg(long, value_name = "URL_OR_PATH")]
    store: Option<String>,
}

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("change").args(["set", "default"])))]
struct ProductArgs {
    /// The line's configuration.
    #[arg(long)]
    config: PathBuf,
    /// The product (one of the configuration's `[[product]]` ids).
    #[arg(long, value_name = "ID")]
    set: Option<String>,
    /// Back to the configuration's `default_product`.
    #[arg(long)]
    default: bool,
}

#[derive(clap::Args)]
struct CheckArgs {
    /// The line's configuration.
    #[arg(long)]
    config: PathBuf,
    /// Only the rows of the store's newest N boards (every line's) and the aggregates.
    #[arg(long, value_name = "N")]
    newest: Option<usize>,
    /// The store, over the configuration's `store`.
    #[arg(long, value_name = "URL_OR_PATH")]
    store: Option<String>,
}

#[derive(clap::Args)]
struct CleanArgs {
    /// The line's configuration.
    #[arg(long)]
    config: PathBuf,
    /// The product whose stencil was cleaned (default: the product the line is told now,
    /// `dpsa line product`).
    #[arg(long)]
    product: Option<String>,
    /// When, Unix seconds (default: now).
    #[arg(long)]
    at: Option<f64>,
    /// Who says so: `operator`, the printer's name.
    #[arg(long, default_value = "operator")]
    source: String,
    /// A note, for a person.
    #[arg(long)]
    note: Option<String>,
    /// The store, over the configuration's `store`.
    #[arg(long, value_name = "URL_OR_PATH")]
    store: Option<String>,
}

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("where").required(true).args(["dir", "store"])))]
struct StoreBenchArgs {
    /// A directory for the scratch SQLite store (`store-bench.sqlite`, replaced if there,
    /// removed after).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Where to measure: a PostgreSQL URL (the benchmark works in a scratch schema
    /// `dpsa_store_bench` of that database, dropped after), or the path of an SQLite file that
    /// must not exist (removed after).
    #[arg(long, value_name = "URL_OR_PATH")]
    store: Option<String>,
    /// Boards inserted.
    #[arg(long, default_value_t = 2000)]
    boards: usize,
    /// Pads per board.
    #[arg(long, default_value_t = 6000)]
    pads: usize,
}

#[derive(clap::Args)]
struct LinkBenchArgs {
    /// MB (10^6 bytes) carried per run; the default is one camera's stream of the paper board.
    #[arg(long, default_value_t = 12.7)]
    mb: f64,
    /// The sender's rate, MB/s; the default is one camera of the paper board at the conveyor's
    /// rate (38 MB a board for three cameras, a board a second).
    #[arg(long, default_value_t = 12.7)]
    rate_mb_s: f64,
    /// How long the receiver stops reading halfway, ms (the host busy).
    #[arg(long, default_value_t = 250)]
    stall_ms: u64,
}

/// Runs `dpsa line ...`.
pub fn run(a: Args) -> Result<()> {
    match a.cmd {
        LineCmd::Run(a) => run_line(a),
        LineCmd::Init(a) => init(a),
        LineCmd::Send(a) => send(a),
        LineCmd::Boards(a) => boards(a),
        LineCmd::Clean(a) => clean(a),
        LineCmd::Check(a) => check(a),
        LineCmd::Product(a) => product(a),
        LineCmd::StoreBench(a) => store_bench(a),
        LineCmd::LinkBench(a) => {
            if !(a.mb.is_finite() && a.mb > 0.0 && a.mb <= 10_000.0) {
                bail!("--mb must be above 0 and at most 10000, not {}", a.mb);
            }
            if !(a.rate_mb_s.is_finite() && a.rate_mb_s > 0.0) {
                bail!("--rate-mb-s must be above 0, not {}", a.rate_mb_s);
            }
            let r = dpsa_line::link_bench::run(&dpsa_line::link_bench::Options {
                bytes: (a.mb * 1e6) as u64,
                rate: a.rate_mb_s * 1e6,
                stall_ms: a.stall_ms,
            })?;
            out!("{}", serde_json::to_string_pretty(&r)?);
            Ok(())
        }
    }
}

/// The store a `--store` names.
fn store_arg(text: &str) -> Result<Location> {
    Location::from_arg(text).map_err(|why| anyhow::anyhow!("--store: {why}"))
}

/// The store a `--store` names, else the configuration's.
fn store_or(arg: Option<&str>, cfg: &LineConfig) -> Result<Location> {
    arg.map_or_else(|| Ok(cfg.store.clone()), store_arg)
}

fn store_bench(a: StoreBenchArgs) -> Result<()> {
    use dpsa_line::store::bench;
    let (r, target) = match (&a.dir, &a.store) {
        (Some(dir), _) => (
            bench::run(dir, a.boards, a.pads),
            Location::Sqlite(dir.join(bench::FILE_NAME)),
        ),
        (None, Some(text)) => {
            let target = store_arg(text)?;
            (bench::run_at(&target, a.boards, a.pads), target)
        }
        (None, None) => bail!("give --dir DIR or --store URL_OR_PATH"),
    };
    // The scratch store (1.4 GB at the defaults in SQLite) goes, whatever the outcome; but
    // an SQLite file the benchmark refused to replace is not its to remove. After a failed
    // run the failure is what is said (the scratch store may never have been made).
    let refused = matches!(&r, Err(dpsa_line::store::StoreError::Invalid { .. }));
    if !(refused && a.dir.is_none()) {
        let removed = bench::remove_scratch(&target);
        if let (Ok(_), Err(e)) = (&r, removed) {
            eprintln!("warning: the benchmark's scratch store is left: {e:#}");
        }
    }
    out!("{}", serde_json::to_string_pretty(&r?)?);
    Ok(())
}

fn run_line(a: RunArgs) -> Result<()> {
    super::log_to_stderr();
    let mut cfg = LineConfig::load(&a.config)?;
    if let Some(text) = &a.store {
        cfg.store = store_arg(text)?;
    }
    if let Some(bind) = a.web {
        // The store made (or migrated) first: the pages open it read-only.
        drop(dpsa_line::store::Store::open(&cfg.store, &cfg.line)?);
        let reviews = super::serve::review_policy(a.web_token_file.as_deref(), bind)?;
        let at = dpsa_web::spawn(
            dpsa_web::Site {
                store: cfg.store.clone(),
                line: cfg.line.clone(),
                reviews,
                spc: Default::default(),
                maps: (cfg.maps.keep_boards > 0).then(|| cfg.maps.dir.clone()),
                map_cache: Default::default(),
                designs: std::sync::Arc::new(dpsa_web::board_view::Designs::load(
                    &cfg.products
                        .iter()
                        .map(|p| p.program_path.as_path())
                        .collect::<Vec<_>>(),
                )?),
            },
            bind,
        )?;
        tracing::info!(address = %at, "the line's pages: http://{at}/");
    }
    let opts = dpsa_line::service::RunOptions { boards: a.boards };
    let summary = dpsa_line::service::run(cfg, opts)?;
    out!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

fn init(a: InitArgs) -> Result<()> {
    let board = match (&a.board, &a.board_mm, a.pixel_mm) {
        (Some(rec), _, _) => {
            let m = dpsa_formats::array::ArrayManifest::load(rec)
                .with_context(|| format!("--board {}", rec.display()))?;
            InitBoard {
                length_mm: m.board_length_mm,
                width_mm: m.board_width_mm,
                pixel_mm: m.pixel_mm,
            }
        }
        (None, Some(lw), Some(p)) => InitBoard {
            length_mm: lw[0],
            width_mm: lw[1],
            pixel_mm: p,
        },
        _ => bail!("give the board: --board REC (its array.json), or --board-mm LENGTH WIDTH and --pixel-mm P"),
    };
    let f = dpsa_line::config::init(&a.cal, &a.program, &a.data, &board, &a.out)?;
    let addrs: Vec<String> = f.camera.iter().map(|c| c.listen.to_string()).collect();
    out!(
        "{} written: product {:?}, cameras at {}",
        a.out.display(),
        f.default_product,
        addrs.join(" ")
    );
    Ok(())
}

/// The cameras' streams of `dir`: `*.dpsa` files matched by the camera id of their headers.
fn stream_files(dir: &Path, cameras: usize) -> Result<Option<Vec<Vec<u8>>>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("{}", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "dpsa"))
        .collect();
    if files.is_empty() {
        return Ok(None);
    }
    files.sort();
    let mut slots: Vec<Option<Vec<u8>>> = vec![None; cameras];
    for f in files {
        let bytes = dpsa_formats::files::read_capped(&f, 1 << 32, "packet stream")?;
        let cam = dpsa_core::packets::Stream::new(&bytes)
            .find_map(|i| match i {
                dpsa_core::packets::Item::Packet { packet, .. } => packet.stream_info(),
                _ => None,
            })
            .map(|i| usize::from(i.camera));
        match cam {
            Some(c) if c < cameras && slots[c].is_none() => slots[c] = Some(bytes),
            Some(c) if c < cameras => bail!("{}: a second stream of camera {c}", f.display()),
            Some(c) => bail!(
                "{}: camera {c}, but there are {cameras} cameras",
                f.display()
            ),
            None => bail!("{}: no stream header", f.display()),
        }
    }
    slots
        .into_iter()
        .enumerate()
        .map(|(i, s)| s.with_context(|| format!("{}: no stream of camera {i}", dir.display())))
        .collect::<Result<Vec<_>>>()
        .map(Some)
}

/// Each camera of the board recording `dir` through the core with calibration `cal`.
#[cfg(feature = "sim")]
pub(crate) fn core_streams(dir: &Path, cal: &Path, cameras: usize) -> Result<Vec<Vec<u8>>> {
    (0..cameras)
        .map(|i| {
            let mut rec = super::open(&dir.join(format!("cam{i}")))?;
            super::apply_cal(&mut rec, cal, Some(i as u8))?;
            let (_, bytes) = dpsa_sim::reconstruct::reconstruct_bytes(&rec, false)?;
            Ok(bytes)
        })
        .collect()
}

fn send(a: SendArgs) -> Result<()> {
    let (to, cal) = match &a.config {
        Some(c) => {
            let cfg = LineConfig::load(c)?;
            let base = c.parent().unwrap_or(Path::new("."));
            let f: dpsa_line::config::LineFile =
                toml::from_str(&std::fs::read_to_string(c)?).context("the configuration")?;
            (cfg.listen, Some(base.join(f.calibration)))
        }
        None if !a.to.is_empty() => (a.to.clone(), None),
        None => bail!("give --config LINE.toml or --to ADDR..."),
    };
    let cameras = to.len();
    let streams = match stream_files(&a.rec, cameras)? {
        Some(s) => s,
        None => {
            #[cfg(feature = "sim")]
            {
                let Some(cal) = a.cal.clone().or(cal) else {
                    bail!(
                        "{} is a board recording: give --cal (or --config) for the core",
                        a.rec.display()
                    );
                };
                core_streams(&a.rec, &cal, cameras)?
            }
            #[cfg(not(feature = "sim"))]
            {
                let _ = cal;
                bail!("{} holds no *.dpsa streams (a board recording needs the build with the simulator)", a.rec.display());
            }
        }
    };
    let rate = if a.rate == "max" {
        Rate::Max
    } else {
        let mm_s = if a.rate == "paper" {
            dpsa_line::send::CONVEYOR_MM_S
        } else {
            a.rate.parse::<f64>()?
        };
        // The paper's conveyor: 220 mm/s; a board row is one pixel of the array's pitch.
        let pixel_mm = match &a.config {
            Some(c) => {
                let f: dpsa_line::config::LineFile = toml::from_str(&std::fs::read_to_string(c)?)?;
                f.pixel_mm
            }
            None => 0.02,
        };
        Rate::Paced {
            row_s: pixel_mm / mm_s,
        }
    };
    let seed = a.seed.unwrap_or_else(|| {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(1, |d| d.as_nanos() as u64)
    });
    let opts = SendOptions {
        to,
        rate,
        boards: a.boards,
        loss: a.loss,
        silent: a.drop_camera.zip(a.at),
        silent_for_s: a.silent_for,
        seed,
    };
    let r = dpsa_line::send::send(&streams, &opts)?;
    out!("{}", serde_json::to_string_pretty(&r)?);
    Ok(())
}

/// clap value parser of `--rate`.
fn rate(s: &str) -> std::result::Result<String, String> {
    match s {
        "paper" | "max" => Ok(s.into()),
        _ => match s.parse::<f64>() {
            Ok(v) if v.is_finite() && v > 0.0 => Ok(s.into()),
            _ => Err(format!(
                "{s:?}: expected paper, max or a conveyor speed in mm/s > 0"
            )),
        },
    }
}

fn clean(a: CleanArgs) -> Result<()> {
    let cfg = LineConfig::load(&a.config)?;
    let location = store_or(a.store.as_deref(), &cfg)?;
    let product = match a.product {
        Some(p) if cfg.products.iter().any(|q| q.id == p) => p,
        Some(p) => bail!(
            "--product {p:?}: not a product of {} ({})",
            a.config.display(),
            cfg.products
                .iter()
                .map(|q| q.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ),
        // The product the line is told now (`dpsa line product`), whose stencil is on the
        // printer.
        None => match cfg.product_now() {
            Ok(k) => cfg.products[k].id.clone(),
            Err(why) => bail!("{why}: give --product"),
        },
    };
    let at = match a.at {
        Some(t) => t,
        None => dpsa_line::boards::unix_now(),
    };
    let mut store = dpsa_line::store::Store::open(&location, &cfg.line)?;
    let id = store.record_clean(&product, at, &a.source, a.note.as_deref())?;
    let c = dpsa_line::store::StencilClean {
        id,
        product,
        cleaned_unix_s: at,
        source: a.source,
        note: a.note,
    };
    out!("{}", serde_json::to_string_pretty(&c)?);
    Ok(())
}

fn product(a: ProductArgs) -> Result<()> {
    let cfg = LineConfig::load(&a.config)?;
    let file = cfg.product_file();
    let ids: Vec<&str> = cfg.products.iter().map(|p| p.id.as_str()).collect();
    if let Some(id) = &a.set {
        if !ids.contains(&id.as_str()) {
            bail!(
                "--set {id:?}: not a product of {} ({ids:?})",
                a.config.display()
            );
        }
        dpsa_formats::files::write_bytes(&file, format!("{id}\n").as_bytes())?;
    } else if a.default {
        match std::fs::remove_file(&file) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => bail!("cannot remove {}: {e}", file.display()),
        }
    }
    // A file that names no product is said, not failed: this is how one finds out why the
    // boards that begin now are stored incomplete.
    let (product, from, refused) = match cfg.product_now() {
        Ok(k) if file.exists() => (Some(ids[k]), "the product file", None),
        Ok(k) => (Some(ids[k]), "default_product", None),
        Err(why) => (None, "the product file", Some(why)),
    };
    let v = serde_json::json!({
        "product": product,
        "from": from,
        "file": file.display().to_string(),
        "products": ids,
        "refused": refused,
    });
    out!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

fn check(a: CheckArgs) -> Result<()> {
    let cfg = LineConfig::load(&a.config)?;
    let location = store_or(a.store.as_deref(), &cfg)?;
    if let Location::Sqlite(path) = &location {
        if !path.is_file() {
            bail!(
                "no store at {}: the line has stored nothing yet",
                path.display()
            );
        }
    }
    if a.newest == Some(0) {
        bail!("--newest 0 checks no board: give at least 1, or leave it out for the whole store");
    }
    let mut store = dpsa_line::store::Store::open_read_only(&location, &cfg.line)?;
    let (bytes, counted) = store.bytes()?;
    let t = std::time::Instant::now();
    match a.newest {
        None => store.check()?,
        Some(n) => store.check_newest(n)?,
    }
    let v = serde_json::json!({
        "store": location.to_string(),
        "checked": a.newest.map_or_else(|| "whole".to_owned(), |n| format!("newest {n} boards")),
        "ok": true,
        "bytes": bytes,
        "bytes_counted": counted,
        "seconds": t.elapsed().as_secs_f64(),
    });
    out!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

fn boards(a: BoardsArgs) -> Result<()> {
    let cfg = LineConfig::load(&a.config)?;
    let location = store_or(a.store.as_deref(), &cfg)?;
    let mut store = dpsa_line::store::Store::open(&location, &cfg.line)?;
    let boards = store.boards(a.last)?;
    // The print rows of the products listed, by board id (each product's newest, as many as
    // boards are listed).
    let mut prints = std::collections::HashMap::new();
    if a.prints {
        let products: std::collections::BTreeSet<&str> =
            boards.iter().map(|b| b.product.as_str()).collect();
        for p in products {
            for r in store.prints(p, a.last)? {
                prints.insert(r.board_id, r.print);
            }
        }
    }
    let mut list = Vec::new();
    for b in boards {
        let mut v = serde_json::to_value(&b)?;
        if a.pads {
            v["pad_rows"] = serde_json::to_value(store.pads(b.id)?)?;
        }
        if a.prints {
            v["print"] = serde_json::to_value(prints.get(&b.id))?;
        }
        list.push(v);
    }
    out!("{}", serde_json::to_string_pretty(&list)?);
    Ok(())
}
