//! A benchmark of the line's store on synthetic boards: how fast boards go in, how fast a pad's
//! history comes out, how large the store grows and how fast retention deletes; on SQLite or
//! on PostgreSQL.
//!
//! [`run`] makes a fresh store `store-bench.sqlite` in the directory it is given (replacing
//! one left by an earlier run); [`run_at`] a fresh store at a [`Location`]: an SQLite file
//! that must not exist yet, or, in a PostgreSQL database, a scratch schema
//! `dpsa_store_bench` (made anew: one of that name left by an earlier run is dropped; the
//! database's other schemas are not touched). Either fills it with `boards` boards of `pads`
//! pads each, as the line would (line `store-bench`), and measures. The values are
//! pseudo-random but the same on every run: about 1 % of the pads warn, 0.2 % fail, 0.1 % could
//! not be measured (NaN), and one board in 97 is incomplete. The store is left for a look
//! (2,000 x 6,000 pads is about 1.4 GB in SQLite); [`remove_scratch`] removes it.

use std::path::Path;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::{
    BoardStart, CameraLoss, Location, Outcome, PadRow, Step, Store, StoreError, MIGRATIONS,
};

/// The store's file name in the benchmark's directory.
pub const FILE_NAME: &str = "store-bench.sqlite";

/// The benchmark's schema in a PostgreSQL database.
pub const SCRATCH_SCHEMA: &str = "dpsa_store_bench";

/// The line the benchmark's boards are of.
const LINE: &str = "store-bench";

/// The goal for inserts, pad rows per second (sustained).
pub const GOAL_PADS_PER_S: f64 = 50_000.0;

/// The goal for a pad's history over the last 1,000 boards, ms.
pub const GOAL_HISTORY_MS: f64 = 50.0;

/// Boards a history query asks for.
const HISTORY_BOARDS: usize = 1000;

/// History queries timed (their median is the figure).
const HISTORY_QUERIES: usize = 20;

/// What [`run`] measured.
#[derive(Debug, Clone, Serialize)]
pub struct StoreBench {
    /// The store measured (a PostgreSQL URL with its password hidden).
    pub store: String,
    /// `sqlite` or `postgres`.
    pub backend: &'static str,
    /// Its schema version.
    pub schema_version: u32,
    /// Which schema (the store's own, or a variant compared with it).
    pub schema: String,
    /// Boards written.
    pub boards: usize,
    /// Of those, inspected (the others incomplete).
    pub inspected_boards: usize,
    /// Pads per inspected board.
    pub pads_per_board: usize,
    /// Pad rows written in all.
    pub pad_rows: u64,
    /// Writing the boards.
    pub insert: InsertBench,
    /// A pad's history.
    pub history: HistoryBench,
    /// [`Store::check`] of the full store (what the service does at start when the store is
    /// at most [`crate::service::WHOLE_CHECK_BYTES`]), seconds.
    pub check_s: f64,
    /// Boards [`Store::check_newest`] was timed on ([`crate::service::CHECK_NEWEST_BOARDS`]).
    pub check_newest_boards: usize,
    /// [`Store::check_newest`] of them (what the service does at start on a larger store),
    /// seconds: the same on a store of any age.
    pub check_newest_s: f64,
    /// The store's size.
    pub size: SizeBench,
    /// Retention ([`Store::prune_pads`]).
    pub prune: PruneBench,
    /// The goals, met or not.
    pub goals: Goals,
}

/// Writing the boards: `begin_board` and `finish_board` of each, timed together (the making
/// of the synthetic pads is not timed).
#[derive(Debug, Clone, Serialize)]
pub struct InsertBench {
    /// Pad rows per second over all boards.
    pub pads_per_s: f64,
    /// Pad rows per second over the last 10 % of the boards (the store at its largest).
    pub pads_per_s_last_10pct: f64,
    /// Mean seconds per board.
    pub s_per_board_mean: f64,
    /// Median seconds per board.
    pub s_per_board_median: f64,
    /// 99th percentile of the seconds per board.
    pub s_per_board_p99: f64,
    /// The slowest board, s (a WAL checkpoint lands in some board's commit).
    pub s_per_board_max: f64,
    /// All boards, s.
    pub total_s: f64,
}

/// A pad's history ([`Store::pad_history`]) over the last boards.
#[derive(Debug, Clone, Serialize)]
pub struct HistoryBench {
    /// The pad index asked for.
    pub pad: u32,
    /// Boards asked for.
    pub boards_asked: usize,
    /// Entries returned.
    pub entries: usize,
    /// Queries timed.
    pub queries: usize,
    /// Their median, ms.
    pub median_ms: f64,
    /// The slowest, ms.
    pub max_ms: f64,
}

/// The store's size once every board is in: SQLite's file and WAL after a checkpoint (`PRAGMA
/// wal_checkpoint(TRUNCATE)`); PostgreSQL's tables with their indexes and TOAST
/// (`pg_total_relation_size`: the server's WAL and catalogs not counted).
#[derive(Debug, Clone, Serialize)]
pub struct SizeBench {
    /// Bytes.
    pub bytes: u64,
    /// What was counted.
    pub counted: &'static str,
    /// Per board written.
    pub bytes_per_board: f64,
    /// Per pad row written.
    pub bytes_per_pad_row: f64,
}

/// Retention: the pads of the older half of the boards deleted.
#[derive(Debug, Clone, Serialize)]
pub struct PruneBench {
    /// Pad rows deleted.
    pub pad_rows_deleted: u64,
    /// Seconds it took.
    pub seconds: f64,
    /// Pad rows deleted per second.
    pub pad_rows_per_s: f64,
    /// The line's keeper's share after each board (`[retention]`): calls of
    /// [`Store::prune_pads_oldest`] for [`crate::keeper::PRUNE_BOARDS_PER_BOARD`] boards
    /// each, on the boards left, timed one by one.
    pub keeper_calls: usize,
    /// Pad rows those calls deleted.
    pub keeper_pad_rows_deleted: u64,
    /// Their median, ms.
    pub keeper_call_median_ms: f64,
    /// The slowest, ms.
    pub keeper_call_max_ms: f64,
}

/// Calls of the keeper's retention timed by the benchmark (fewer when fewer boards are left).
const KEEPER_PRUNE_CALLS: usize = 20;

/// The goals of the store.
#[derive(Debug, Clone, Serialize)]
pub struct Goals {
    /// Inserts: at least 50,000 pad rows/s, the lower of the figures over all boards and over
    /// the last 10 %.
    pub inserts: Goal,
    /// A pad's history over the last 1,000 boards within 50 ms (median).
    pub history: Goal,
}

/// One goal.
#[derive(Debug, Clone, Serialize)]
pub struct Goal {
    /// The goal, for a person, e.g. `>= 50000 pad rows/s`.
    pub goal: String,
    /// What was measured, in the goal's unit.
    pub measured: f64,
    /// Whether it was met.
    pub met: bool,
}

/// Creates a fresh SQLite store `DIR/store-bench.sqlite` (replacing one left there, with its
/// WAL), writes `boards` synthetic boards of `pads` pads each, and measures (see
/// [`StoreBench`]). `boards` must be at least 1. Takes one to two minutes for 2,000 x 6,000
/// pads on a two-core machine, and leaves a file of about 1.4 GB.
pub fn run(dir: &Path, boards: usize, pads: usize) -> Result<StoreBench, StoreError> {
    let path = dir.join(FILE_NAME);
    remove_sqlite(&path)?;
    run_at(&Location::Sqlite(path), boards, pads)
}

/// [`run`] at `target`: an SQLite file that must not exist (a benchmark never replaces a file
/// it did not make), or a PostgreSQL database, in its scratch schema [`SCRATCH_SCHEMA`].
pub fn run_at(target: &Location, boards: usize, pads: usize) -> Result<StoreBench, StoreError> {
    run_with(target, boards, pads, MIGRATIONS, "store")
}

/// Removes what [`run_at`] made at `target`: the SQLite file and its WAL, or the scratch
/// schema with everything in it.
pub fn remove_scratch(target: &Location) -> Result<(), StoreError> {
    match target {
        Location::Sqlite(path) => remove_sqlite(path),
        Location::Postgres(url) => super::pg::Pg::scratch_schema(url, SCRATCH_SCHEMA, false),
    }
}

/// Removes an SQLite file and its WAL and shared-memory files, those that exist.
fn remove_sqlite(path: &Path) -> Result<(), StoreError> {
    for suffix in ["", "-wal", "-shm"] {
        let mut name = path.to_owned().into_os_string();
        name.push(suffix);
        match std::fs::remove_file(&name) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(StoreError::Io {
                    store: path.display().to_string(),
                    source: e,
                });
            }
            _ => {}
        }
    }
    Ok(())
}

/// [`run_at`] with another schema.
fn run_with(
    target: &Location,
    boards: usize,
    pads: usize,
    migrations: &[Step],
    schema: &str,
) -> Result<StoreBench, StoreError> {
    if boards == 0 {
        return Err(StoreError::Invalid {
            store: target.to_string(),
            why: "a benchmark of 0 boards".to_owned(),
        });
    }
    let location = match target {
        Location::Sqlite(path) => {
            if std::fs::symlink_metadata(path).is_ok() {
                return Err(StoreError::Invalid {
                    store: target.to_string(),
                    why: "it exists: the benchmark makes a fresh store and never replaces a \
                          file (remove it, or give another path)"
                        .to_owned(),
                });
            }
            target.clone()
        }
        Location::Postgres(url) => {
            super::pg::Pg::scratch_schema(url, SCRATCH_SCHEMA, true)?;
            Location::Postgres(url.with_schema(SCRATCH_SCHEMA))
        }
    };
    let mut store = Store::open_with(&location, LINE, migrations)?;
    let product = "bench-board";
    let t0 = 1.7e9;
    let mut times = Vec::with_capacity(boards);
    let mut pad_rows = 0u64;
    let mut inspected = 0usize;
    for board in 0..boards {
        let started = t0 + board as f64;
        let start = BoardStart {
            run_id: 0x00be_0000_0000_0000 | board as u64,
            product: product.to_owned(),
            program_hash: "0123456789abcdef".to_owned(),
            calibration_hash: "fedcba9876543210".to_owned(),
            started_unix_s: started,
        };
        let (outcome, cameras) = synthetic_board(board, pads);
        if let Outcome::Inspected { pads, .. } = &outcome {
            pad_rows += pads.len() as u64;
            inspected += 1;
        }
        let t = Instant::now();
        let id = store.begin_board(&start)?;
        store.finish_board(id, started + 0.9, &cameras, &outcome)?;
        times.push(t.elapsed());
    }
    let total: Duration = times.iter().sum();
    let last = boards.div_ceil(10);
    let last_time: Duration = times[boards - last..].iter().sum();
    let last_pads = (boards - last..boards)
        .filter(|&b| !is_incomplete(b))
        .count() as f64
        * pads as f64;
    let mut secs: Vec<f64> = times.iter().map(Duration::as_secs_f64).collect();
    secs.sort_by(f64::total_cmp);
    let insert = InsertBench {
        pads_per_s: pad_rows as f64 / total.as_secs_f64(),
        pads_per_s_last_10pct: last_pads / last_time.as_secs_f64(),
        s_per_board_mean: total.as_secs_f64() / boards as f64,
        s_per_board_median: quantile(&secs, 0.5),
        s_per_board_p99: quantile(&secs, 0.99),
        s_per_board_max: secs.last().copied().unwrap_or(0.0),
        total_s: total.as_secs_f64(),
    };

    let pad = (pads / 2) as u32;
    let mut ms = Vec::with_capacity(HISTORY_QUERIES);
    let mut entries = 0;
    for _ in 0..HISTORY_QUERIES {
        let t = Instant::now();
        entries = store.pad_history(product, pad, HISTORY_BOARDS)?.len();
        ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    ms.sort_by(f64::total_cmp);
    let history = HistoryBench {
        pad,
        boards_asked: HISTORY_BOARDS,
        entries,
        queries: HISTORY_QUERIES,
        median_ms: quantile(&ms, 0.5),
        max_ms: ms.last().copied().unwrap_or(0.0),
    };

    let t = Instant::now();
    store.check()?;
    let check_s = t.elapsed().as_secs_f64();
    let check_newest_boards = crate::service::CHECK_NEWEST_BOARDS;
    let t = Instant::now();
    store.check_newest(check_newest_boards)?;
    let check_newest_s = t.elapsed().as_secs_f64();

    store.checkpoint()?;
    let (bytes, counted) = store.bytes()?;
    let size = SizeBench {
        bytes,
        counted,
        bytes_per_board: bytes as f64 / boards as f64,
        bytes_per_pad_row: bytes as f64 / pad_rows.max(1) as f64,
    };

    let t = Instant::now();
    let deleted = store.prune_pads(t0 + (boards / 2) as f64)?;
    let seconds = t.elapsed().as_secs_f64();
    let mut call_ms = Vec::with_capacity(KEEPER_PRUNE_CALLS);
    let mut keeper_deleted = 0;
    for _ in 0..KEEPER_PRUNE_CALLS {
        let t = Instant::now();
        let n = store.prune_pads_oldest(
            t0 + boards as f64 + 1.0,
            crate::keeper::PRUNE_BOARDS_PER_BOARD,
        )?;
        if n == 0 {
            break;
        }
        call_ms.push(t.elapsed().as_secs_f64() * 1e3);
        keeper_deleted += n;
    }
    call_ms.sort_by(f64::total_cmp);
    let prune = PruneBench {
        pad_rows_deleted: deleted,
        seconds,
        pad_rows_per_s: deleted as f64 / seconds,
        keeper_calls: call_ms.len(),
        keeper_pad_rows_deleted: keeper_deleted,
        keeper_call_median_ms: quantile(&call_ms, 0.5),
        keeper_call_max_ms: call_ms.last().copied().unwrap_or(0.0),
    };

    let inserts = insert.pads_per_s.min(insert.pads_per_s_last_10pct);
    let goals = Goals {
        inserts: Goal {
            goal: format!(">= {GOAL_PADS_PER_S} pad rows/s"),
            measured: inserts,
            met: inserts >= GOAL_PADS_PER_S,
        },
        history: Goal {
            goal: format!("<= {GOAL_HISTORY_MS} ms for {HISTORY_BOARDS} boards"),
            measured: history.median_ms,
            met: history.median_ms <= GOAL_HISTORY_MS,
        },
    };
    Ok(StoreBench {
        schema_version: store.schema_version()?,
        store: location.to_string(),
        backend: location.backend(),
        schema: schema.to_owned(),
        boards,
        inspected_boards: inspected,
        pads_per_board: pads,
        pad_rows,
        insert,
        history,
        check_s,
        check_newest_boards,
        check_newest_s,
        size,
        prune,
        goals,
    })
}

/// The `q` quantile of sorted values (nearest rank), 0 for none.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// One board in 97 is never inspected.
fn is_incomplete(board: usize) -> bool {
    board % 97 == 96
}

/// SplitMix64: small, fast, and the same numbers everywhere.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Roughly normal, mean 0, standard deviation 1 (Irwin-Hall of 12 uniforms).
    fn normal(&mut self) -> f64 {
        (0..12).map(|_| self.unit()).sum::<f64>() - 6.0
    }
}

/// Board `board`'s outcome and camera losses.
fn synthetic_board(board: usize, pads: usize) -> (Outcome, Vec<CameraLoss>) {
    let mut rng = Rng(0x5eed_0000 ^ (board as u64).wrapping_mul(0x2545_f491_4f6c_dd1d));
    let cameras = (0..2)
        .map(|camera| {
            let missing = if rng.unit() < 0.05 {
                rng.next_u64() % 20
            } else {
                0
            };
            CameraLoss {
                camera,
                rows: 2048 - missing,
                missing_rows: missing,
                missing_packets: missing,
                damaged_packets: u64::from(rng.unit() < 0.02),
            }
        })
        .collect();
    if is_incomplete(board) {
        let reason = format!("camera {} silent", board % 2);
        return (Outcome::Incomplete { reason }, cameras);
    }
    let mut worst = 0;
    let rows = (0..pads)
        .map(|i| {
            let mut r = Rng(0xa5a5 ^ i as u64);
            let nominal_area_mm2 = 0.2 + 1.3 * r.unit();
            let nominal_height_um = 120.0;
            let u = rng.unit();
            let shift = if u < 0.002 {
                -55.0
            } else if u < 0.012 {
                -32.0
            } else {
                0.0
            };
            let unmeasurable = rng.unit() < 0.001;
            let volume_pct = 100.0 + 6.0 * rng.normal() + shift;
            let height_pct = 100.0 + 4.0 * rng.normal() + shift / 2.0;
            let area_pct = 100.0 * volume_pct / height_pct;
            let deviation = (volume_pct - 100.0).abs();
            let (level, class) = if unmeasurable {
                (2, Some("not measurable"))
            } else if deviation > 50.0 {
                (
                    2,
                    Some(if volume_pct < 100.0 {
                        "insufficient"
                    } else {
                        "excess"
                    }),
                )
            } else if deviation > 25.0 {
                (
                    1,
                    Some(if volume_pct < 100.0 {
                        "insufficient"
                    } else {
                        "excess"
                    }),
                )
            } else {
                (0, None)
            };
            worst = worst.max(level);
            let measured = |v: f64| Some(if unmeasurable { f64::NAN } else { v });
            PadRow {
                pad: i as u32,
                name: if i % 5 == 4 {
                    format!("pad {i}")
                } else {
                    format!("U{}-{}", i / 5, i % 5 + 1)
                },
                level: ["pass", "warn", "fail"][level].to_owned(),
                class: class.map(str::to_owned),
                volume_um3: measured(
                    nominal_area_mm2 * 1e6 * nominal_height_um * volume_pct / 100.0,
                ),
                volume_pct: measured(volume_pct),
                area_mm2: measured(nominal_area_mm2 * area_pct / 100.0),
                area_pct: measured(area_pct),
                height_um: measured(nominal_height_um * height_pct / 100.0),
                height_pct: measured(height_pct),
                offset_x_um: measured(8.0 * rng.normal()),
                offset_y_um: measured(8.0 * rng.normal()),
                coverage: if unmeasurable {
                    0.1
                } else {
                    0.9 + 0.1 * rng.unit()
                },
                uncertainty_um3: None,
            }
        })
        .collect();
    let verdict = ["pass", "warn", "fail"][worst].to_owned();
    (
        Outcome::Inspected {
            verdict,
            pads: rows,
        },
        cameras,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The schema variants compared; `cargo test --release -p dpsa-line -- --ignored
    /// --nocapture store::bench` prints their figures. `STORE_BENCH_BOARDS` and
    /// `STORE_BENCH_PADS` set the size (200 x 6,000 by default).
    #[test]
    #[ignore = "a benchmark: a minute or more"]
    fn compare_schemas() {
        let boards = std::env::var("STORE_BENCH_BOARDS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(200);
        let pads = std::env::var("STORE_BENCH_PADS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(6000);
        // Variants of version 1's `pads` (SQLite), version 2 on top as shipped.
        let v1 = super::super::schema::V1;
        let rowid = v1.replacen(
            "    PRIMARY KEY (board_id, pad)\n){without_rowid};\n\nCREATE TABLE defects",
            "    PRIMARY KEY (board_id, pad)\n);\n\nCREATE TABLE defects",
            1,
        );
        assert_ne!(rowid, v1);
        let index = format!("{v1}\nCREATE INDEX pads_by_pad ON pads (pad, board_id);\n");
        let variants = [
            ("store (pads WITHOUT ROWID)", v1.to_owned()),
            ("pads with rowid", rowid),
            ("pads WITHOUT ROWID + index pads (pad, board_id)", index),
        ];
        let only = std::env::var("STORE_BENCH_ONLY").ok();
        for (i, (name, sql)) in variants.iter().enumerate() {
            if only.as_ref().is_some_and(|o| o.parse() != Ok(i)) {
                continue;
            }
            let dir = tempfile::tempdir().unwrap();
            let steps = [Step::Both(sql.clone().into()), MIGRATIONS[1].clone()];
            let target = Location::Sqlite(dir.path().join(FILE_NAME));
            let b = run_with(&target, boards, pads, &steps, name).unwrap();
            println!("{}", serde_json::to_string_pretty(&b).unwrap());
        }
    }

    #[test]
    fn synthetic_boards_are_the_same_every_time_and_have_defects() {
        let (a, _) = synthetic_board(3, 2000);
        let (b, _) = synthetic_board(3, 2000);
        let fmt = |o: &Outcome| format!("{o:?}");
        assert_eq!(fmt(&a), fmt(&b));
        let Outcome::Inspected { pads, .. } = a else {
            panic!("board 3 is inspected")
        };
        let count = |l: &str| pads.iter().filter(|p| p.level == l).count();
        assert!(count("warn") > 0 && count("fail") > 0 && count("pass") > 1900);
        assert!(pads.iter().all(|p| (0.0..=1.0).contains(&p.coverage)));
        assert!(matches!(
            synthetic_board(96, 10).0,
            Outcome::Incomplete { .. }
        ));
    }
}
