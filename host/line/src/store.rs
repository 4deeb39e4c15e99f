//! The line's store: every board the line began, how each ended, and every pad it measured,
//! in one SQLite file.
//!
//! The line service calls [`Store::begin_board`] when a board starts and
//! [`Store::finish_board`] when it has been inspected (or could not be); a board's end, its
//! cameras' losses, its pads, its defects and the per-pad running aggregates are written in one
//! transaction, so a reader (the CLI, an engineer's `sqlite3`) sees a board whole or not at all.
//! After a restart, [`Store::recover`] turns the boards the service died in into `incomplete`
//! ones. [`Store::prune_pads`] is the retention: it deletes the bulky pad rows of old boards
//! and keeps the boards and the aggregates.
//!
//! The file is in WAL mode: readers never block the writer, nor the writer the readers.
//!
//! # Schema, version 1
//!
//! The version is SQLite's `PRAGMA user_version`. [`Store::open`] brings an older file up to
//! [`SCHEMA_VERSION`] by migrations, one transaction each, and refuses a file whose version is
//! newer than this program knows ([`StoreError::NewerSchema`]). Times are Unix seconds (REAL);
//! a measurement that could not be made (NaN) is stored as NULL, never as NaN.
//!
//! ## `boards`: one row per board the line began
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `id` | INTEGER PRIMARY KEY | the store's id of the board; grows with every board begun |
//! | `run_id` | TEXT NOT NULL UNIQUE | the line's run id, 16 lowercase hex digits; a board is never stored twice |
//! | `product` | TEXT NOT NULL | the product (board type) name |
//! | `program_hash` | TEXT NOT NULL | hash of the inspection program, as the caller gave it |
//! | `calibration_hash` | TEXT NOT NULL | hash of the calibration in use |
//! | `started_unix_s` | REAL NOT NULL | when the board began |
//! | `ended_unix_s` | REAL NULL | when it ended; NULL while `open` |
//! | `state` | TEXT NOT NULL | `open` (in progress), `inspected` or `incomplete` |
//! | `verdict` | TEXT NULL | `pass`, `warn` or `fail`: set for `inspected` boards only |
//! | `incomplete_reason` | TEXT NULL | why the board was never inspected: set for `incomplete` boards only |
//! | `pads` | INTEGER NOT NULL | pad rows written when it was inspected (0 otherwise); kept when [`Store::prune_pads`] deletes the rows |
//!
//! A CHECK ties `state` to the others: an `open` board has no end, verdict nor reason; an
//! `inspected` board an end and a verdict and no reason; an `incomplete` board an end and a
//! reason, no verdict and no pads. Indexes: `boards_by_product (product, state, id)` (a pad's
//! history), `boards_by_end (ended_unix_s)` (retention) and `boards_open (id) WHERE state =
//! 'open'` (recovery).
//!
//! ## `board_cameras`: one row per camera of a finished board
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `board_id` | INTEGER NOT NULL | `boards.id` (ON DELETE CASCADE) |
//! | `camera` | INTEGER NOT NULL | camera index, 0..=255 |
//! | `rows` | INTEGER NOT NULL | row packets received |
//! | `missing_rows` | INTEGER NOT NULL | board rows lost (never arrived) |
//! | `missing_packets` | INTEGER NOT NULL | packets missing |
//! | `damaged_packets` | INTEGER NOT NULL | packets that arrived damaged |
//!
//! Primary key `(board_id, camera)`, WITHOUT ROWID.
//!
//! ## `pads`: one row per pad of an inspected board
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `board_id` | INTEGER NOT NULL | `boards.id` (ON DELETE CASCADE) |
//! | `pad` | INTEGER NOT NULL | index of the pad in the paste layer |
//! | `name` | TEXT NOT NULL | e.g. `R12-1` (component-pin) or `pad 17` |
//! | `level` | TEXT NOT NULL | `pass`, `warn` or `fail` |
//! | `class` | TEXT NULL | the deciding class, e.g. `insufficient`, `not measurable`; NULL for a pass |
//! | `volume_um3` | REAL NULL | paste volume, um³ |
//! | `volume_pct` | REAL NULL | volume, % of nominal |
//! | `area_mm2` | REAL NULL | paste area, mm² |
//! | `area_pct` | REAL NULL | area, % of the opening |
//! | `height_um` | REAL NULL | mean height, um |
//! | `height_pct` | REAL NULL | height, % of nominal |
//! | `offset_x_um`, `offset_y_um` | REAL NULL | offset of the deposit from the opening, um |
//! | `coverage` | REAL NOT NULL | share of the opening's pixels that were valid, 0..=1 |
//! | `uncertainty_um3` | REAL NULL | volume uncertainty, um³ (not computed yet: NULL) |
//!
//! Primary key `(board_id, pad)`, WITHOUT ROWID: the rows sit in the primary key's B-tree
//! itself, in the order they are written, which keeps inserts append-only and makes a pad of a
//! given board one B-tree lookup (a pad's history over 1,000 boards is 1,000 lookups, served
//! by `boards_by_product`: no second index on `pads` is needed, which would cost every insert).
//!
//! ## `defects`: one row per pad of an inspected board whose level is `warn` or `fail`
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `board_id` | INTEGER NOT NULL | `boards.id` (ON DELETE CASCADE) |
//! | `pad` | INTEGER NOT NULL | pad index |
//! | `level` | TEXT NOT NULL | `warn` or `fail` |
//! | `class` | TEXT NULL | the deciding class |
//!
//! Primary key `(board_id, pad)`, WITHOUT ROWID.
//!
//! ## `alarms`: statistical process control alarms (empty for now)
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `id` | INTEGER PRIMARY KEY | |
//! | `raised_unix_s` | REAL NOT NULL | when it was raised |
//! | `product` | TEXT NOT NULL | the product |
//! | `pad` | INTEGER NULL | the pad, NULL for an alarm on the whole board |
//! | `rule` | TEXT NOT NULL | the rule that fired |
//! | `message` | TEXT NOT NULL | what it says, for a person |
//!
//! ## `pad_stats`: running aggregates per pad of a product, kept for ever
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `product` | TEXT NOT NULL | the product |
//! | `pad` | INTEGER NOT NULL | pad index |
//! | `boards` | INTEGER NOT NULL | inspected boards on which the pad had a `volume_pct` |
//! | `sum_volume_pct` | REAL NOT NULL | Σ volume_pct over those boards |
//! | `sum_sq_volume_pct` | REAL NOT NULL | Σ volume_pct² over those boards |
//! | `fails` | INTEGER NOT NULL | of those boards, how many the pad failed |
//! | `warns` | INTEGER NOT NULL | of those boards, how many it warned |
//! | `last_board_id` | INTEGER NOT NULL | the last board counted |
//!
//! Primary key `(product, pad)`, WITHOUT ROWID. Updated in [`Store::finish_board`]'s
//! transaction for inspected boards, and only for the pads with a `volume_pct` (a pad whose
//! volume could not be measured is not counted, not even in `fails`: its fail is in `defects`).
//! Mean = `sum_volume_pct / boards`; variance = `sum_sq_volume_pct / boards - mean²`.
//!
//! # Queries an engineer would run
//!
//! The last 20 boards, with their result:
//!
//! ```sql
//! SELECT id, run_id, product, datetime(started_unix_s, 'unixepoch') AS started, state,
//!        coalesce(verdict, incomplete_reason, '(in progress)') AS result, pads
//! FROM boards ORDER BY id DESC LIMIT 20;
//! ```
//!
//! Pad 17's volume over the last 100 inspected boards of a product, newest first:
//!
//! ```sql
//! SELECT b.id, b.run_id, datetime(b.started_unix_s, 'unixepoch') AS started,
//!        p.name, p.level, p.volume_pct
//! FROM (SELECT id, run_id, started_unix_s FROM boards
//!       WHERE product = 'ctrl-b' AND state = 'inspected' ORDER BY id DESC LIMIT 100) AS b
//! JOIN pads AS p ON p.board_id = b.id AND p.pad = 17
//! ORDER BY b.id DESC;
//! ```
//!
//! Defects per class and hour over the last day:
//!
//! ```sql
//! SELECT strftime('%Y-%m-%d %H:00', b.ended_unix_s, 'unixepoch') AS hour,
//!        d.level, coalesce(d.class, '?') AS class, count(*) AS pads
//! FROM defects AS d JOIN boards AS b ON b.id = d.board_id
//! WHERE b.ended_unix_s >= CAST(strftime('%s', 'now', '-1 day') AS REAL)
//! GROUP BY hour, d.level, class ORDER BY hour, pads DESC;
//! ```
//!
//! Boards never inspected, and why:
//!
//! ```sql
//! SELECT incomplete_reason, count(*) AS boards,
//!        datetime(max(ended_unix_s), 'unixepoch') AS last
//! FROM boards WHERE state = 'incomplete'
//! GROUP BY incomplete_reason ORDER BY boards DESC;
//! ```
//!
//! The pads of a product whose volume drifts most, from the aggregates:
//!
//! ```sql
//! SELECT pad, boards, sum_volume_pct / boards AS mean_pct,
//!        sqrt(max(sum_sq_volume_pct / boards - (sum_volume_pct / boards) * (sum_volume_pct / boards), 0)) AS sd_pct,
//!        fails, warns
//! FROM pad_stats WHERE product = 'ctrl-b' ORDER BY abs(mean_pct - 100) DESC LIMIT 20;
//! ```
//!
//! (`sqrt` needs an `sqlite3` built with the math functions, as the bundled one is.)

use std::path::{Path, PathBuf};
use std::time::Duration;

/// A run id as JSON: 16 lowercase hex digits, as the logs, the CFX spool and the `boards`
/// table write it (a JSON number would lose bits in readers that hold numbers as f64).
fn hex_id<S: serde::Serializer>(id: &u64, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(&format_args!("{id:016x}"))
}

use rusqlite::{params, Connection, OptionalExtension, TransactionBehavior};

#[path = "store_bench.rs"]
pub mod bench;

/// The newest schema version this program knows (`PRAGMA user_version` of a store it made).
pub const SCHEMA_VERSION: u32 = MIGRATIONS.len() as u32;

/// The migrations, in order: applying `MIGRATIONS[i]` takes a store from version `i` to
/// version `i + 1`. Never edit one that has shipped: add the next.
const MIGRATIONS: &[&str] = &[SCHEMA_V1];

/// Version 1: the tables of the module documentation.
///
/// The CHECKs of the per-pad tables compare with `=` joined by OR, never `IN (...)`: SQLite
/// evaluates a CHECK's `IN` list by building a small temporary table every row, which more
/// than doubled the time of a pad insert (measured: 53 against 23 ms per board of 6,000 pads).
const SCHEMA_V1: &str = "
CREATE TABLE boards (
    id                INTEGER PRIMARY KEY,
    run_id            TEXT NOT NULL UNIQUE
                      CHECK (length(run_id) = 16 AND run_id NOT GLOB '*[^0-9a-f]*'),
    product           TEXT NOT NULL,
    program_hash      TEXT NOT NULL,
    calibration_hash  TEXT NOT NULL,
    started_unix_s    REAL NOT NULL,
    ended_unix_s      REAL,
    state             TEXT NOT NULL CHECK (state IN ('open', 'inspected', 'incomplete')),
    verdict           TEXT CHECK (verdict IN ('pass', 'warn', 'fail')),
    incomplete_reason TEXT,
    pads              INTEGER NOT NULL DEFAULT 0 CHECK (pads >= 0),
    CHECK ((state = 'open' AND ended_unix_s IS NULL AND verdict IS NULL
                AND incomplete_reason IS NULL AND pads = 0)
        OR (state = 'inspected' AND ended_unix_s IS NOT NULL AND verdict IS NOT NULL
                AND incomplete_reason IS NULL)
        OR (state = 'incomplete' AND ended_unix_s IS NOT NULL AND verdict IS NULL
                AND incomplete_reason IS NOT NULL AND pads = 0))
);
CREATE INDEX boards_by_product ON boards (product, state, id);
CREATE INDEX boards_by_end ON boards (ended_unix_s);
CREATE INDEX boards_open ON boards (id) WHERE state = 'open';

CREATE TABLE board_cameras (
    board_id        INTEGER NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    camera          INTEGER NOT NULL CHECK (camera BETWEEN 0 AND 255),
    rows            INTEGER NOT NULL CHECK (rows >= 0),
    missing_rows    INTEGER NOT NULL CHECK (missing_rows >= 0),
    missing_packets INTEGER NOT NULL CHECK (missing_packets >= 0),
    damaged_packets INTEGER NOT NULL CHECK (damaged_packets >= 0),
    PRIMARY KEY (board_id, camera)
) WITHOUT ROWID;

CREATE TABLE pads (
    board_id        INTEGER NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    pad             INTEGER NOT NULL CHECK (pad >= 0),
    name            TEXT NOT NULL,
    level           TEXT NOT NULL CHECK (level = 'pass' OR level = 'warn' OR level = 'fail'),
    class           TEXT,
    volume_um3      REAL,
    volume_pct      REAL,
    area_mm2        REAL,
    area_pct        REAL,
    height_um       REAL,
    height_pct      REAL,
    offset_x_um     REAL,
    offset_y_um     REAL,
    coverage        REAL NOT NULL CHECK (coverage BETWEEN 0 AND 1),
    uncertainty_um3 REAL,
    PRIMARY KEY (board_id, pad)
) WITHOUT ROWID;

CREATE TABLE defects (
    board_id INTEGER NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    pad      INTEGER NOT NULL,
    level    TEXT NOT NULL CHECK (level = 'warn' OR level = 'fail'),
    class    TEXT,
    PRIMARY KEY (board_id, pad)
) WITHOUT ROWID;

CREATE TABLE alarms (
    id            INTEGER PRIMARY KEY,
    raised_unix_s REAL NOT NULL,
    product       TEXT NOT NULL,
    pad           INTEGER,
    rule          TEXT NOT NULL,
    message       TEXT NOT NULL
);

CREATE TABLE pad_stats (
    product           TEXT NOT NULL,
    pad               INTEGER NOT NULL,
    boards            INTEGER NOT NULL,
    sum_volume_pct    REAL NOT NULL,
    sum_sq_volume_pct REAL NOT NULL,
    fails             INTEGER NOT NULL,
    warns             INTEGER NOT NULL,
    last_board_id     INTEGER NOT NULL,
    PRIMARY KEY (product, pad)
) WITHOUT ROWID;
";

/// How long a statement waits for another connection's lock before it gives up (busy).
const BUSY_TIMEOUT: Duration = Duration::from_secs(10);

/// Boards whose pads [`Store::prune_pads`] deletes in one transaction: short enough that the
/// line's own writes wait little, long enough that the commits cost nothing.
const PRUNE_BOARDS_PER_TRANSACTION: usize = 50;

/// Why the store could not do what was asked. Every sentence names the store's file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// The store's directory could not be created.
    #[error("cannot create the directory of the store {}", .path.display())]
    Io {
        /// The store file.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// SQLite failed (disk full, locked beyond the busy timeout, a constraint refused a row...).
    #[error("SQLite failed on the store {}", .path.display())]
    Sqlite {
        /// The store file.
        path: PathBuf,
        /// What SQLite said.
        source: rusqlite::Error,
    },
    /// The file was written by a newer program: its schema is unknown here, so it is left alone.
    #[error(
        "the store {} has schema version {found}, newer than the {known} this program knows: \
         use the newer program (or another store file)",
        .path.display()
    )]
    NewerSchema {
        /// The store file.
        path: PathBuf,
        /// Its `user_version`.
        found: u32,
        /// [`SCHEMA_VERSION`].
        known: u32,
    },
    /// The file is damaged (or is not an SQLite database at all).
    #[error("the store {} is damaged: {why}", .path.display())]
    Corrupt {
        /// The store file.
        path: PathBuf,
        /// What SQLite's checks (or SQLite itself) said.
        why: String,
    },
    /// A board with this run id is already stored: a board is never stored twice.
    #[error("the store {} already holds a board of run id {run_id:016x}", .path.display())]
    Duplicate {
        /// The store file.
        path: PathBuf,
        /// The run id.
        run_id: u64,
    },
    /// No board has this id.
    #[error("the store {} has no board {id}", .path.display())]
    UnknownBoard {
        /// The store file.
        path: PathBuf,
        /// The board id asked for.
        id: i64,
    },
    /// The board was already finished: a finished board is never rewritten.
    #[error("board {id} of the store {} is already {state}, not open: a finished board is never rewritten", .path.display())]
    NotOpen {
        /// The store file.
        path: PathBuf,
        /// The board id.
        id: i64,
        /// Its state (`inspected` or `incomplete`).
        state: String,
    },
    /// A value the caller gave was refused before anything was written.
    #[error("the store {} refused a value: {why}", .path.display())]
    Invalid {
        /// The store file.
        path: PathBuf,
        /// Which value, and why.
        why: String,
    },
}

/// A board the line began.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BoardStart {
    /// The line's run id; stored as 16 lowercase hex digits, unique.
    pub run_id: u64,
    /// The product (board type) name.
    pub product: String,
    /// Hash of the inspection program, hex text as the caller gives it.
    pub program_hash: String,
    /// Hash of the calibration in use, hex text.
    pub calibration_hash: String,
    /// When the board began, Unix seconds.
    pub started_unix_s: f64,
}

/// What one camera lost of a board.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct CameraLoss {
    /// Camera index.
    pub camera: u8,
    /// Row packets received.
    pub rows: u64,
    /// Board rows lost (never arrived).
    pub missing_rows: u64,
    /// Packets missing.
    pub missing_packets: u64,
    /// Packets that arrived damaged.
    pub damaged_packets: u64,
}

/// One pad's measurement and level. A measurement that could not be made is `None` (a `NaN`
/// given in `Some` is stored as NULL too, and so read back as `None`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PadRow {
    /// Index of the pad in the paste layer.
    pub pad: u32,
    /// The pad's name, e.g. `R12-1` (component-pin) or `pad 17`.
    pub name: String,
    /// `pass`, `warn` or `fail`.
    pub level: String,
    /// The deciding class, e.g. `insufficient`, `not measurable`; `None` for a pass.
    pub class: Option<String>,
    /// Paste volume, um³.
    pub volume_um3: Option<f64>,
    /// Volume, % of nominal.
    pub volume_pct: Option<f64>,
    /// Paste area, mm².
    pub area_mm2: Option<f64>,
    /// Area, % of the opening.
    pub area_pct: Option<f64>,
    /// Mean height, um.
    pub height_um: Option<f64>,
    /// Height, % of nominal.
    pub height_pct: Option<f64>,
    /// Offset of the deposit from the opening along x, um.
    pub offset_x_um: Option<f64>,
    /// Offset along y, um.
    pub offset_y_um: Option<f64>,
    /// Share of the opening's pixels that were valid, 0..=1.
    pub coverage: f64,
    /// Volume uncertainty, um³: not computed yet, always `None` for now.
    pub uncertainty_um3: Option<f64>,
}

/// How a board ended.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub enum Outcome {
    /// Inspected: the board's verdict (`pass` | `warn` | `fail`) and every pad.
    Inspected {
        /// `pass`, `warn` or `fail`.
        verdict: String,
        /// Every pad of the board.
        pads: Vec<PadRow>,
    },
    /// Never inspected: why (a camera silent, a stream cut, the service stopped ...). Never
    /// passes.
    Incomplete {
        /// Why, for a person.
        reason: String,
    },
}

/// A board as the store holds it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StoredBoard {
    /// The store's id of the board.
    pub id: i64,
    /// The line's run id.
    #[serde(serialize_with = "hex_id")]
    pub run_id: u64,
    /// The product name.
    pub product: String,
    /// Hash of the inspection program.
    pub program_hash: String,
    /// Hash of the calibration.
    pub calibration_hash: String,
    /// When it began, Unix seconds.
    pub started_unix_s: f64,
    /// When it ended; `None` while open.
    pub ended_unix_s: Option<f64>,
    /// `open` (in progress), `inspected` or `incomplete`.
    pub state: String,
    /// The verdict of an inspected board.
    pub verdict: Option<String>,
    /// Why an incomplete board was never inspected.
    pub incomplete_reason: Option<String>,
    /// Pad rows written for it when it was inspected (kept after [`Store::prune_pads`] deleted
    /// the rows themselves).
    pub pads: u64,
    /// Its cameras' losses, in camera order (none while open or after [`Store::recover`]).
    pub cameras: Vec<CameraLoss>,
}

/// One board of a pad's history ([`Store::pad_history`]): `(board id, run id, level,
/// volume_pct)`.
pub type HistoryEntry = (i64, u64, String, Option<f64>);

/// The line's store: one SQLite connection to one file.
#[derive(Debug)]
pub struct Store {
    conn: Connection,
    path: PathBuf,
}

/// Maps an SQLite error to a [`StoreError`] of the file `path`: a damaged file (or one that is
/// no database) becomes [`StoreError::Corrupt`].
fn sql_err(path: &Path, source: rusqlite::Error) -> StoreError {
    use rusqlite::ErrorCode::{DatabaseCorrupt, NotADatabase};
    match source.sqlite_error_code() {
        Some(DatabaseCorrupt | NotADatabase) => StoreError::Corrupt {
            path: path.to_owned(),
            why: source.to_string(),
        },
        _ => StoreError::Sqlite {
            path: path.to_owned(),
            source,
        },
    }
}

/// `PRAGMA user_version`, which must be a version (not negative).
fn user_version(conn: &Connection, path: &Path) -> Result<u32, StoreError> {
    let v: i64 = conn
        .pragma_query_value(None, "user_version", |r| r.get(0))
        .map_err(|e| sql_err(path, e))?;
    u32::try_from(v).map_err(|_| StoreError::Corrupt {
        path: path.to_owned(),
        why: format!("its schema version (user_version) is {v}"),
    })
}

/// A run id as stored: 16 lowercase hex digits.
fn run_id_text(run_id: u64) -> String {
    format!("{run_id:016x}")
}

/// A stored run id back to its number.
fn parse_run_id(path: &Path, text: &str) -> Result<u64, StoreError> {
    match u64::from_str_radix(text, 16) {
        Ok(v) if text.len() == 16 => Ok(v),
        _ => Err(StoreError::Corrupt {
            path: path.to_owned(),
            why: format!("a board's run id is {text:?}, not 16 hex digits"),
        }),
    }
}

/// NaN (a measurement that could not be made) becomes `None`, so NULL: never a NaN in the file.
fn real(v: Option<f64>) -> Option<f64> {
    v.filter(|x| !x.is_nan())
}

/// Is `e` a UNIQUE (or primary key) constraint refusing a row?
fn is_unique_violation(e: &rusqlite::Error) -> bool {
    e.sqlite_error().is_some_and(|f| {
        f.extended_code == rusqlite::ffi::SQLITE_CONSTRAINT_UNIQUE
            || f.extended_code == rusqlite::ffi::SQLITE_CONSTRAINT_PRIMARYKEY
    })
}

const LEVELS: [&str; 3] = ["pass", "warn", "fail"];

const INSERT_PAD: &str = "INSERT INTO pads (board_id, pad, name, level, class, volume_um3, volume_pct, \
     area_mm2, area_pct, height_um, height_pct, offset_x_um, offset_y_um, coverage, uncertainty_um3) \
     VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15)";

/// Adds board `?2`'s pads (of product `?1`) that have a volume to the running aggregates.
const UPSERT_PAD_STATS: &str = "INSERT INTO pad_stats (product, pad, boards, sum_volume_pct, \
     sum_sq_volume_pct, fails, warns, last_board_id) \
     SELECT ?1, pad, 1, volume_pct, volume_pct * volume_pct, level = 'fail', level = 'warn', board_id \
     FROM pads WHERE board_id = ?2 AND volume_pct IS NOT NULL \
     ON CONFLICT (product, pad) DO UPDATE SET \
     boards = boards + 1, \
     sum_volume_pct = sum_volume_pct + excluded.sum_volume_pct, \
     sum_sq_volume_pct = sum_sq_volume_pct + excluded.sum_sq_volume_pct, \
     fails = fails + excluded.fails, \
     warns = warns + excluded.warns, \
     last_board_id = excluded.last_board_id";

impl Store {
    /// Opens the store at `path`, creating it (and its parent directory) if it does not exist,
    /// and brings its schema up to [`SCHEMA_VERSION`] by migrations (`PRAGMA user_version`;
    /// each migration in its own transaction, so a store is always at one version or the
    /// next). A store of a newer schema is refused ([`StoreError::NewerSchema`]) and left
    /// untouched; a file that is no SQLite database is [`StoreError::Corrupt`].
    ///
    /// The connection is in WAL mode with `synchronous = NORMAL`, foreign keys on and a busy
    /// timeout of 10 s. `NORMAL` does not sync the disk at every commit, only when the WAL is
    /// checkpointed into the database; with WAL that is safe: a commit appends its pages to
    /// the WAL and a crash or power cut can lose at most the last transactions not yet synced
    /// (each one whole, never half), never corrupt the file. For the line that means the last
    /// boards of a power cut may be missing, and [`Store::recover`] finds the ones left open.
    pub fn open(path: &Path) -> Result<Store, StoreError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|source| StoreError::Io {
                path: path.to_owned(),
                source,
            })?;
        }
        Self::open_with(path, MIGRATIONS)
    }

    /// [`Store::open`] with another list of migrations (the benchmark compares schemas).
    fn open_with(path: &Path, migrations: &[&str]) -> Result<Store, StoreError> {
        let err = |e| sql_err(path, e);
        let mut conn = Connection::open(path).map_err(err)?;
        conn.busy_timeout(BUSY_TIMEOUT).map_err(err)?;
        let known = migrations.len() as u32;
        let found = user_version(&conn, path)?;
        if found > known {
            return Err(StoreError::NewerSchema {
                path: path.to_owned(),
                found,
                known,
            });
        }
        let mode: String = conn
            .pragma_update_and_check(None, "journal_mode", "WAL", |r| r.get(0))
            .map_err(err)?;
        if !mode.eq_ignore_ascii_case("wal") {
            return Err(StoreError::Invalid {
                path: path.to_owned(),
                why: format!("SQLite could not put it in WAL mode (journal mode is {mode})"),
            });
        }
        conn.pragma_update(None, "synchronous", "NORMAL")
            .map_err(err)?;
        conn.pragma_update(None, "foreign_keys", "ON")
            .map_err(err)?;
        conn.set_prepared_statement_cache_capacity(32);
        if found < known {
            Self::migrate(&mut conn, path, migrations)?;
        }
        Ok(Store {
            conn,
            path: path.to_owned(),
        })
    }

    /// Applies the migrations the store lacks, one transaction each. The version is read
    /// again inside each (write-locked) transaction, so two programs opening a new store at
    /// once do not both migrate it.
    fn migrate(conn: &mut Connection, path: &Path, migrations: &[&str]) -> Result<(), StoreError> {
        let err = |e| sql_err(path, e);
        let known = migrations.len() as u32;
        loop {
            let tx = conn
                .transaction_with_behavior(TransactionBehavior::Immediate)
                .map_err(err)?;
            let v = user_version(&tx, path)?;
            if v > known {
                return Err(StoreError::NewerSchema {
                    path: path.to_owned(),
                    found: v,
                    known,
                });
            }
            if v == known {
                return tx.commit().map_err(err);
            }
            tx.execute_batch(migrations[v as usize]).map_err(err)?;
            tx.pragma_update(None, "user_version", v + 1).map_err(err)?;
            tx.commit().map_err(err)?;
        }
    }

    /// The store's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The store's schema version (`PRAGMA user_version`): [`SCHEMA_VERSION`] once open.
    pub fn schema_version(&self) -> Result<u32, StoreError> {
        user_version(&self.conn, &self.path)
    }

    fn err(&self) -> impl Fn(rusqlite::Error) -> StoreError + '_ {
        |e| sql_err(&self.path, e)
    }

    fn invalid(&self, why: String) -> StoreError {
        StoreError::Invalid {
            path: self.path.clone(),
            why,
        }
    }

    /// A board the line began: a row in state `open`. Returns its id. A run id already stored
    /// is refused ([`StoreError::Duplicate`]): a board is never stored twice.
    pub fn begin_board(&mut self, b: &BoardStart) -> Result<i64, StoreError> {
        if !b.started_unix_s.is_finite() {
            return Err(self.invalid(format!(
                "board {:016x} started at {} s",
                b.run_id, b.started_unix_s
            )));
        }
        let result = self
            .conn
            .prepare_cached(
                "INSERT INTO boards (run_id, product, program_hash, calibration_hash, \
                 started_unix_s, state) VALUES (?1, ?2, ?3, ?4, ?5, 'open')",
            )
            .and_then(|mut s| {
                s.execute(params![
                    run_id_text(b.run_id),
                    b.product,
                    b.program_hash,
                    b.calibration_hash,
                    b.started_unix_s
                ])
            });
        match result {
            Ok(_) => Ok(self.conn.last_insert_rowid()),
            Err(e) if is_unique_violation(&e) => Err(StoreError::Duplicate {
                path: self.path.clone(),
                run_id: b.run_id,
            }),
            Err(e) => Err(sql_err(&self.path, e)),
        }
    }

    /// Refuses, before anything is written, what a CHECK would refuse less clearly.
    fn validate_finish(
        &self,
        id: i64,
        ended_unix_s: f64,
        outcome: &Outcome,
    ) -> Result<(), StoreError> {
        if !ended_unix_s.is_finite() {
            return Err(self.invalid(format!("board {id} ended at {ended_unix_s} s")));
        }
        if let Outcome::Inspected { verdict, pads } = outcome {
            if !LEVELS.contains(&verdict.as_str()) {
                return Err(self.invalid(format!(
                    "board {id}: verdict {verdict:?} is none of pass, warn, fail"
                )));
            }
            for p in pads {
                if !LEVELS.contains(&p.level.as_str()) {
                    return Err(self.invalid(format!(
                        "board {id}, pad {} ({}): level {:?} is none of pass, warn, fail",
                        p.pad, p.name, p.level
                    )));
                }
                if !(0.0..=1.0).contains(&p.coverage) {
                    return Err(self.invalid(format!(
                        "board {id}, pad {} ({}): coverage {} is not within 0..=1",
                        p.pad, p.name, p.coverage
                    )));
                }
            }
        }
        Ok(())
    }

    /// Ends board `id` in one transaction: its state, verdict or reason, end time, the
    /// cameras' loss rows and, for an inspected board, every pad row, a `defects` row per pad
    /// whose level is `fail` or `warn`, and the pads' running aggregates (`pad_stats`). If
    /// anything fails, nothing is written and the board stays open.
    ///
    /// Ending a board that is not open is refused ([`StoreError::NotOpen`]): a finished board
    /// is never rewritten. So are an unknown id, a verdict or level other than `pass`, `warn`,
    /// `fail`, a coverage outside 0..=1, two pads of one index or two losses of one camera.
    pub fn finish_board(
        &mut self,
        id: i64,
        ended_unix_s: f64,
        cameras: &[CameraLoss],
        outcome: &Outcome,
    ) -> Result<(), StoreError> {
        self.validate_finish(id, ended_unix_s, outcome)?;
        let path = self.path.as_path();
        let err = |e| sql_err(path, e);
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(err)?;
        let row: Option<(String, String)> = tx
            .prepare_cached("SELECT state, product FROM boards WHERE id = ?1")
            .and_then(|mut s| s.query_row([id], |r| Ok((r.get(0)?, r.get(1)?))).optional())
            .map_err(err)?;
        let product = match row {
            None => {
                return Err(StoreError::UnknownBoard {
                    path: path.to_owned(),
                    id,
                })
            }
            Some((state, _)) if state != "open" => {
                return Err(StoreError::NotOpen {
                    path: path.to_owned(),
                    id,
                    state,
                })
            }
            Some((_, product)) => product,
        };
        {
            let mut s = tx
                .prepare_cached(
                    "INSERT INTO board_cameras (board_id, camera, rows, missing_rows, \
                     missing_packets, damaged_packets) VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                )
                .map_err(err)?;
            for c in cameras {
                s.execute(params![
                    id,
                    c.camera,
                    c.rows,
                    c.missing_rows,
                    c.missing_packets,
                    c.damaged_packets
                ])
                .map_err(err)?;
            }
        }
        match outcome {
            Outcome::Inspected { verdict, pads } => {
                {
                    let mut s = tx.prepare_cached(INSERT_PAD).map_err(err)?;
                    for p in pads {
                        s.execute(params![
                            id,
                            p.pad,
                            p.name,
                            p.level,
                            p.class,
                            real(p.volume_um3),
                            real(p.volume_pct),
                            real(p.area_mm2),
                            real(p.area_pct),
                            real(p.height_um),
                            real(p.height_pct),
                            real(p.offset_x_um),
                            real(p.offset_y_um),
                            p.coverage,
                            real(p.uncertainty_um3),
                        ])
                        .map_err(err)?;
                    }
                    let mut s = tx
                        .prepare_cached(
                            "INSERT INTO defects (board_id, pad, level, class) \
                             VALUES (?1, ?2, ?3, ?4)",
                        )
                        .map_err(err)?;
                    for p in pads.iter().filter(|p| p.level != "pass") {
                        s.execute(params![id, p.pad, p.level, p.class])
                            .map_err(err)?;
                    }
                    tx.prepare_cached(UPSERT_PAD_STATS)
                        .and_then(|mut s| s.execute(params![product, id]))
                        .map_err(err)?;
                }
                tx.prepare_cached(
                    "UPDATE boards SET state = 'inspected', verdict = ?2, ended_unix_s = ?3, \
                     pads = ?4 WHERE id = ?1",
                )
                .and_then(|mut s| s.execute(params![id, verdict, ended_unix_s, pads.len()]))
                .map_err(err)?;
            }
            Outcome::Incomplete { reason } => {
                tx.prepare_cached(
                    "UPDATE boards SET state = 'incomplete', incomplete_reason = ?2, \
                     ended_unix_s = ?3 WHERE id = ?1",
                )
                .and_then(|mut s| s.execute(params![id, reason, ended_unix_s]))
                .map_err(err)?;
            }
        }
        tx.commit().map_err(err)
    }

    /// After a restart: every board still open (the service died in it) becomes `incomplete`
    /// with `reason`, ended at `now_unix_s`. Returns their run ids, oldest first. Finished
    /// boards are left alone.
    pub fn recover(&mut self, reason: &str, now_unix_s: f64) -> Result<Vec<u64>, StoreError> {
        if !now_unix_s.is_finite() {
            return Err(self.invalid(format!("recovery at {now_unix_s} s")));
        }
        let path = self.path.as_path();
        let err = |e| sql_err(path, e);
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(err)?;
        let texts: Vec<String> = {
            let mut s = tx
                .prepare("SELECT run_id FROM boards WHERE state = 'open' ORDER BY id")
                .map_err(err)?;
            let rows = s.query_map([], |r| r.get(0)).map_err(err)?;
            rows.collect::<Result<_, _>>().map_err(err)?
        };
        tx.execute(
            "UPDATE boards SET state = 'incomplete', incomplete_reason = ?1, ended_unix_s = ?2 \
             WHERE state = 'open'",
            params![reason, now_unix_s],
        )
        .map_err(err)?;
        tx.commit().map_err(err)?;
        texts.iter().map(|t| parse_run_id(path, t)).collect()
    }

    /// Checks the file: `PRAGMA integrity_check` (every page, every index) and `PRAGMA
    /// foreign_key_check`. `Ok(())`, or [`StoreError::Corrupt`] with what they said. Reads the
    /// whole file: seconds for a store of gigabytes.
    pub fn check(&self) -> Result<(), StoreError> {
        let corrupt = |why: String| StoreError::Corrupt {
            path: self.path.clone(),
            why,
        };
        let said: Vec<String> = {
            let mut s = self
                .conn
                .prepare("PRAGMA integrity_check(20)")
                .map_err(self.err())?;
            let rows = s.query_map([], |r| r.get(0)).map_err(self.err())?;
            rows.collect::<Result<_, _>>().map_err(self.err())?
        };
        if said != ["ok"] {
            return Err(corrupt(format!("integrity check: {}", said.join("; "))));
        }
        let orphans: Vec<(String, String)> = {
            let mut s = self
                .conn
                .prepare("PRAGMA foreign_key_check")
                .map_err(self.err())?;
            let rows = s
                .query_map([], |r| Ok((r.get(0)?, r.get(2)?)))
                .map_err(self.err())?;
            rows.collect::<Result<_, _>>().map_err(self.err())?
        };
        if let Some((table, parent)) = orphans.first() {
            return Err(corrupt(format!(
                "foreign key check: {} row(s) refer to missing rows, the first of table {table} \
                 to a missing row of {parent}",
                orphans.len()
            )));
        }
        Ok(())
    }

    /// The boards, newest (last begun) first, at most `limit`.
    pub fn boards(&self, limit: usize) -> Result<Vec<StoredBoard>, StoreError> {
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let mut s = self
            .conn
            .prepare_cached(
                "SELECT id, run_id, product, program_hash, calibration_hash, started_unix_s, \
                 ended_unix_s, state, verdict, incomplete_reason, pads \
                 FROM boards ORDER BY id DESC LIMIT ?1",
            )
            .map_err(self.err())?;
        let rows = s
            .query_map([limit], |r| {
                Ok((
                    r.get::<_, String>(1)?,
                    StoredBoard {
                        id: r.get(0)?,
                        run_id: 0,
                        product: r.get(2)?,
                        program_hash: r.get(3)?,
                        calibration_hash: r.get(4)?,
                        started_unix_s: r.get(5)?,
                        ended_unix_s: r.get(6)?,
                        state: r.get(7)?,
                        verdict: r.get(8)?,
                        incomplete_reason: r.get(9)?,
                        pads: r.get(10)?,
                        cameras: Vec::new(),
                    },
                ))
            })
            .map_err(self.err())?;
        let mut boards = Vec::new();
        for row in rows {
            let (run_id, mut board) = row.map_err(self.err())?;
            board.run_id = parse_run_id(&self.path, &run_id)?;
            board.cameras = self.cameras(board.id)?;
            boards.push(board);
        }
        Ok(boards)
    }

    /// Board `board_id`'s camera losses, in camera order.
    fn cameras(&self, board_id: i64) -> Result<Vec<CameraLoss>, StoreError> {
        let mut s = self
            .conn
            .prepare_cached(
                "SELECT camera, rows, missing_rows, missing_packets, damaged_packets \
                 FROM board_cameras WHERE board_id = ?1 ORDER BY camera",
            )
            .map_err(self.err())?;
        let rows = s
            .query_map([board_id], |r| {
                Ok(CameraLoss {
                    camera: r.get(0)?,
                    rows: r.get(1)?,
                    missing_rows: r.get(2)?,
                    missing_packets: r.get(3)?,
                    damaged_packets: r.get(4)?,
                })
            })
            .map_err(self.err())?;
        rows.collect::<Result<_, _>>().map_err(self.err())
    }

    /// One board's pads in pad order (none for a board not inspected, or pruned). An unknown
    /// board is [`StoreError::UnknownBoard`].
    pub fn pads(&self, board_id: i64) -> Result<Vec<PadRow>, StoreError> {
        let known = self
            .conn
            .prepare_cached("SELECT 1 FROM boards WHERE id = ?1")
            .and_then(|mut s| s.exists([board_id]))
            .map_err(self.err())?;
        if !known {
            return Err(StoreError::UnknownBoard {
                path: self.path.clone(),
                id: board_id,
            });
        }
        let mut s = self
            .conn
            .prepare_cached(
                "SELECT pad, name, level, class, volume_um3, volume_pct, area_mm2, area_pct, \
                 height_um, height_pct, offset_x_um, offset_y_um, coverage, uncertainty_um3 \
                 FROM pads WHERE board_id = ?1 ORDER BY pad",
            )
            .map_err(self.err())?;
        let rows = s
            .query_map([board_id], |r| {
                Ok(PadRow {
                    pad: r.get(0)?,
                    name: r.get(1)?,
                    level: r.get(2)?,
                    class: r.get(3)?,
                    volume_um3: r.get(4)?,
                    volume_pct: r.get(5)?,
                    area_mm2: r.get(6)?,
                    area_pct: r.get(7)?,
                    height_um: r.get(8)?,
                    height_pct: r.get(9)?,
                    offset_x_um: r.get(10)?,
                    offset_y_um: r.get(11)?,
                    coverage: r.get(12)?,
                    uncertainty_um3: r.get(13)?,
                })
            })
            .map_err(self.err())?;
        rows.collect::<Result<_, _>>().map_err(self.err())
    }

    /// A pad's history: `(board id, run id, level, volume_pct)` of pad index `pad` of
    /// `product` over the last `boards` inspected boards, newest first. Boards whose pad rows
    /// were pruned, or that had no pad of that index, give no entry.
    pub fn pad_history(
        &self,
        product: &str,
        pad: u32,
        boards: usize,
    ) -> Result<Vec<HistoryEntry>, StoreError> {
        let limit = i64::try_from(boards).unwrap_or(i64::MAX);
        let mut s = self
            .conn
            .prepare_cached(
                "SELECT b.id, b.run_id, p.level, p.volume_pct \
                 FROM (SELECT id, run_id FROM boards \
                       WHERE product = ?1 AND state = 'inspected' ORDER BY id DESC LIMIT ?3) AS b \
                 JOIN pads AS p ON p.board_id = b.id AND p.pad = ?2 \
                 ORDER BY b.id DESC",
            )
            .map_err(self.err())?;
        let rows = s
            .query_map(params![product, pad, limit], |r| {
                Ok((
                    r.get::<_, i64>(0)?,
                    r.get::<_, String>(1)?,
                    r.get::<_, String>(2)?,
                    r.get::<_, Option<f64>>(3)?,
                ))
            })
            .map_err(self.err())?;
        let mut out = Vec::new();
        for row in rows {
            let (id, run_id, level, volume_pct) = row.map_err(self.err())?;
            out.push((id, parse_run_id(&self.path, &run_id)?, level, volume_pct));
        }
        Ok(out)
    }

    /// Retention: deletes the pad and defect rows of the boards that ended before
    /// `before_unix_s`; the boards' rows, their cameras and the per-pad running aggregates stay.
    /// Returns the pad rows deleted. Works in transactions of 50 boards, so that the line's
    /// own writes never wait long; the freed pages are reused by later boards (the file does
    /// not shrink). Only the boards from the oldest one that still has pads on are looked at,
    /// so a daily prune costs the boards of the retention window, not of the store's life.
    pub fn prune_pads(&mut self, before_unix_s: f64) -> Result<u64, StoreError> {
        if before_unix_s.is_nan() {
            return Err(self.invalid("pruning before NaN s".to_owned()));
        }
        let path = self.path.as_path();
        let err = |e| sql_err(path, e);
        let ids: Vec<i64> = {
            let mut s = self
                .conn
                .prepare(
                    "SELECT id FROM boards \
                     WHERE id >= (SELECT min(board_id) FROM pads) AND ended_unix_s < ?1 \
                     AND EXISTS (SELECT 1 FROM pads WHERE board_id = boards.id) ORDER BY id",
                )
                .map_err(err)?;
            let rows = s.query_map([before_unix_s], |r| r.get(0)).map_err(err)?;
            rows.collect::<Result<_, _>>().map_err(err)?
        };
        let mut deleted = 0u64;
        for chunk in ids.chunks(PRUNE_BOARDS_PER_TRANSACTION) {
            let tx = self
                .conn
                .transaction_with_behavior(TransactionBehavior::Immediate)
                .map_err(err)?;
            {
                let mut defects = tx
                    .prepare_cached("DELETE FROM defects WHERE board_id = ?1")
                    .map_err(err)?;
                let mut pads = tx
                    .prepare_cached("DELETE FROM pads WHERE board_id = ?1")
                    .map_err(err)?;
                for id in chunk {
                    defects.execute([id]).map_err(err)?;
                    deleted += pads.execute([id]).map_err(err)? as u64;
                }
            }
            tx.commit().map_err(err)?;
        }
        Ok(deleted)
    }

    /// Copies the WAL into the database and empties it (`PRAGMA wal_checkpoint(TRUNCATE)`).
    fn checkpoint(&self) -> Result<(), StoreError> {
        self.conn
            .query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |_| Ok(()))
            .map_err(self.err())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn start(run_id: u64, product: &str, t: f64) -> BoardStart {
        BoardStart {
            run_id,
            product: product.to_owned(),
            program_hash: "a1b2c3".to_owned(),
            calibration_hash: "d4e5f6".to_owned(),
            started_unix_s: t,
        }
    }

    fn pad(i: u32, level: &str, volume_pct: Option<f64>) -> PadRow {
        PadRow {
            pad: i,
            name: format!("R{}-{}", i / 2, i % 2 + 1),
            level: level.to_owned(),
            class: match level {
                "pass" => None,
                _ if volume_pct.is_none() => Some("not measurable".to_owned()),
                _ => Some("insufficient".to_owned()),
            },
            volume_um3: volume_pct.map(|v| v * 1.0e5),
            volume_pct,
            area_mm2: Some(0.5 + f64::from(i) * 0.01),
            area_pct: Some(98.0),
            height_um: Some(120.0),
            height_pct: Some(101.0),
            offset_x_um: Some(-3.5),
            offset_y_um: Some(4.25),
            coverage: 0.97,
            uncertainty_um3: None,
        }
    }

    fn cams() -> Vec<CameraLoss> {
        vec![
            CameraLoss {
                camera: 0,
                rows: 2048,
                missing_rows: 0,
                missing_packets: 1,
                damaged_packets: 0,
            },
            CameraLoss {
                camera: 1,
                rows: 2040,
                missing_rows: 8,
                missing_packets: 8,
                damaged_packets: 2,
            },
        ]
    }

    /// A fresh store in a temporary directory (kept alive by the returned guard).
    fn fresh() -> (tempfile::TempDir, Store) {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&dir.path().join("sub").join("line.sqlite")).unwrap();
        (dir, store)
    }

    /// Begins and inspects a board of `n` pads; pad `i`'s volume is `base + i`.
    fn inspect(store: &mut Store, run_id: u64, product: &str, n: u32, base: f64) -> i64 {
        let id = store
            .begin_board(&start(run_id, product, run_id as f64))
            .unwrap();
        let pads = (0..n)
            .map(|i| pad(i, "pass", Some(base + f64::from(i))))
            .collect();
        store
            .finish_board(
                id,
                run_id as f64 + 0.5,
                &cams(),
                &Outcome::Inspected {
                    verdict: "pass".to_owned(),
                    pads,
                },
            )
            .unwrap();
        id
    }

    #[test]
    fn round_trip_of_a_board_with_pads_nan_becomes_none() {
        let (_dir, mut store) = fresh();
        assert_eq!(store.schema_version().unwrap(), SCHEMA_VERSION);
        let id = store
            .begin_board(&start(0xdead_beef_0000_0001, "ctrl-b", 1000.25))
            .unwrap();
        let open = &store.boards(10).unwrap()[0];
        assert_eq!(open.state, "open");
        assert_eq!((open.ended_unix_s, open.verdict.as_ref()), (None, None));
        let mut pads = vec![
            pad(0, "pass", Some(101.5)),
            pad(1, "warn", Some(70.0)),
            pad(2, "fail", Some(f64::NAN)),
            pad(3, "fail", None),
        ];
        pads[2].class = Some("not measurable".to_owned());
        pads[2].volume_um3 = Some(f64::NAN);
        pads[2].height_um = Some(f64::NAN);
        pads[3].name = "pad 3".to_owned();
        store
            .finish_board(
                id,
                1001.0,
                &cams(),
                &Outcome::Inspected {
                    verdict: "fail".to_owned(),
                    pads: pads.clone(),
                },
            )
            .unwrap();
        let back = store.pads(id).unwrap();
        let mut want = pads;
        want[2].volume_um3 = None;
        want[2].volume_pct = None;
        want[2].height_um = None;
        assert_eq!(back, want);
        let nan_stored: i64 = store
            .conn
            .query_row(
                "SELECT count(*) FROM pads WHERE volume_pct != volume_pct",
                [],
                |r| r.get(0),
            )
            .unwrap();
        assert_eq!(nan_stored, 0);
        let board = &store.boards(10).unwrap()[0];
        assert_eq!(
            board,
            &StoredBoard {
                id,
                run_id: 0xdead_beef_0000_0001,
                product: "ctrl-b".to_owned(),
                program_hash: "a1b2c3".to_owned(),
                calibration_hash: "d4e5f6".to_owned(),
                started_unix_s: 1000.25,
                ended_unix_s: Some(1001.0),
                state: "inspected".to_owned(),
                verdict: Some("fail".to_owned()),
                incomplete_reason: None,
                pads: 4,
                cameras: cams(),
            }
        );
        let run_id: String = store
            .conn
            .query_row("SELECT run_id FROM boards", [], |r| r.get(0))
            .unwrap();
        assert_eq!(run_id, "deadbeef00000001");
        let defects: Vec<(u32, String, Option<String>)> = store
            .conn
            .prepare("SELECT pad, level, class FROM defects ORDER BY pad")
            .unwrap()
            .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(
            defects,
            [
                (1, "warn".to_owned(), Some("insufficient".to_owned())),
                (2, "fail".to_owned(), Some("not measurable".to_owned())),
                (3, "fail".to_owned(), Some("not measurable".to_owned())),
            ]
        );
        store.check().unwrap();
    }

    #[test]
    fn state_machine_refuses_what_would_rewrite_a_board() {
        let (_dir, mut store) = fresh();
        let id = store.begin_board(&start(7, "p", 1.0)).unwrap();
        // A run id is stored once.
        let dup = store.begin_board(&start(7, "p", 2.0)).unwrap_err();
        assert!(
            matches!(dup, StoreError::Duplicate { run_id: 7, .. }),
            "{dup}"
        );
        assert!(dup.to_string().contains("line.sqlite"), "{dup}");
        // Invalid values are refused before anything is written, the board stays open.
        let bad_verdict = Outcome::Inspected {
            verdict: "ok".to_owned(),
            pads: vec![],
        };
        let e = store.finish_board(id, 3.0, &[], &bad_verdict).unwrap_err();
        assert!(matches!(e, StoreError::Invalid { .. }), "{e}");
        let bad_level = Outcome::Inspected {
            verdict: "pass".to_owned(),
            pads: vec![pad(0, "good", Some(1.0))],
        };
        let e = store.finish_board(id, 3.0, &[], &bad_level).unwrap_err();
        assert!(matches!(e, StoreError::Invalid { .. }), "{e}");
        // A failure half way (two pads of one index) rolls the whole board back.
        let twice = Outcome::Inspected {
            verdict: "pass".to_owned(),
            pads: vec![pad(0, "pass", Some(1.0)), pad(0, "pass", Some(2.0))],
        };
        let e = store.finish_board(id, 3.0, &cams(), &twice).unwrap_err();
        assert!(matches!(e, StoreError::Sqlite { .. }), "{e}");
        assert_eq!(store.boards(1).unwrap()[0].state, "open");
        assert_eq!(store.boards(1).unwrap()[0].cameras, []);
        assert_eq!(store.pads(id).unwrap(), []);
        // Incomplete: a reason, never a verdict nor pads.
        let why = Outcome::Incomplete {
            reason: "camera 1 silent".to_owned(),
        };
        store.finish_board(id, 3.0, &cams(), &why).unwrap();
        let b = &store.boards(1).unwrap()[0];
        assert_eq!(b.state, "incomplete");
        assert_eq!(b.verdict, None);
        assert_eq!(b.incomplete_reason.as_deref(), Some("camera 1 silent"));
        assert_eq!(b.pads, 0);
        assert_eq!(b.cameras, cams());
        // Finishing again, either way, is refused and changes nothing.
        let pass = Outcome::Inspected {
            verdict: "pass".to_owned(),
            pads: vec![pad(0, "pass", Some(100.0))],
        };
        for outcome in [&pass, &why] {
            let e = store.finish_board(id, 4.0, &[], outcome).unwrap_err();
            assert!(
                matches!(&e, StoreError::NotOpen { state, .. } if state == "incomplete"),
                "{e}"
            );
        }
        assert_eq!(&store.boards(1).unwrap()[0], b);
        let e = store.finish_board(id + 100, 4.0, &[], &why).unwrap_err();
        assert!(matches!(e, StoreError::UnknownBoard { .. }), "{e}");
        // The schema's CHECK holds even against SQL written by hand.
        for sql in [
            "UPDATE boards SET verdict = 'fail'",
            "UPDATE boards SET incomplete_reason = NULL",
            "UPDATE boards SET state = 'open'",
            "UPDATE boards SET state = 'inspected'",
        ] {
            assert!(store.conn.execute(sql, []).is_err(), "{sql} was accepted");
        }
    }

    #[test]
    fn recover_turns_open_boards_incomplete_and_leaves_finished_ones() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("line.sqlite");
        let (done, incomplete);
        {
            let mut store = Store::open(&path).unwrap();
            done = inspect(&mut store, 1, "p", 3, 100.0);
            store.begin_board(&start(2, "p", 2.0)).unwrap();
            incomplete = store.begin_board(&start(3, "p", 3.0)).unwrap();
            store
                .finish_board(
                    incomplete,
                    3.5,
                    &[],
                    &Outcome::Incomplete {
                        reason: "stream cut".to_owned(),
                    },
                )
                .unwrap();
            store.begin_board(&start(4, "p", 4.0)).unwrap();
            // The service dies here: the store is dropped with boards 2 and 4 open.
        }
        let before = Store::open(&path).unwrap().boards(10).unwrap();
        let mut store = Store::open(&path).unwrap();
        assert_eq!(store.recover("service restarted", 99.0).unwrap(), [2, 4]);
        let after = store.boards(10).unwrap();
        for (b, a) in before.iter().zip(&after) {
            if b.state == "open" {
                assert_eq!(a.state, "incomplete");
                assert_eq!(a.incomplete_reason.as_deref(), Some("service restarted"));
                assert_eq!(a.ended_unix_s, Some(99.0));
                assert_eq!(a.verdict, None);
            } else {
                assert_eq!(a, b);
            }
        }
        assert!(after.iter().any(|b| b.id == done && b.state == "inspected"));
        assert_eq!(store.recover("again", 100.0).unwrap(), Vec::<u64>::new());
        assert_eq!(store.boards(10).unwrap(), after);
    }

    #[test]
    fn check_passes_on_a_fresh_store_and_fails_on_garbage() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("line.sqlite");
        {
            let mut store = Store::open(&path).unwrap();
            store.check().unwrap();
            for run in 0..12 {
                inspect(&mut store, run, "p", 400, 90.0);
            }
            store.check().unwrap();
            store.checkpoint().unwrap();
        }
        // Garbage over four pages in the middle of the file.
        let mut bytes = std::fs::read(&path).unwrap();
        assert!(bytes.len() > 64 * 1024, "{} bytes", bytes.len());
        let middle = bytes.len() / 2 / 4096 * 4096;
        for (i, b) in bytes[middle..middle + 4 * 4096].iter_mut().enumerate() {
            *b = (i as u8).wrapping_mul(37) ^ 0x5a;
        }
        std::fs::write(&path, &bytes).unwrap();
        match Store::open(&path) {
            Err(e) => assert!(e.to_string().contains("line.sqlite"), "{e}"),
            Ok(store) => {
                let e = store.check().unwrap_err();
                assert!(matches!(e, StoreError::Corrupt { .. }), "{e}");
                assert!(e.to_string().contains("line.sqlite"), "{e}");
            }
        }
        // A file that is not a database at all.
        let junk = dir.path().join("junk.sqlite");
        std::fs::write(&junk, vec![0x42u8; 10_000]).unwrap();
        let e = Store::open(&junk).unwrap_err();
        assert!(matches!(e, StoreError::Corrupt { .. }), "{e}");
    }

    #[test]
    fn pad_history_is_newest_first_and_only_inspected_boards() {
        let (_dir, mut store) = fresh();
        let a1 = inspect(&mut store, 1, "a", 5, 100.0);
        let b1 = inspect(&mut store, 2, "b", 5, 50.0);
        let open = store.begin_board(&start(3, "a", 3.0)).unwrap();
        let a2 = inspect(&mut store, 4, "a", 5, 110.0);
        let gone = store.begin_board(&start(5, "a", 5.0)).unwrap();
        store
            .finish_board(
                gone,
                5.5,
                &[],
                &Outcome::Incomplete {
                    reason: "camera 0 silent".to_owned(),
                },
            )
            .unwrap();
        let a3 = inspect(&mut store, 6, "a", 5, 120.0);
        let h = store.pad_history("a", 2, 10).unwrap();
        assert_eq!(
            h,
            [
                (a3, 6, "pass".to_owned(), Some(122.0)),
                (a2, 4, "pass".to_owned(), Some(112.0)),
                (a1, 1, "pass".to_owned(), Some(102.0)),
            ]
        );
        assert!(h.iter().all(|e| e.0 != b1 && e.0 != open && e.0 != gone));
        assert_eq!(store.pad_history("a", 2, 2).unwrap(), h[..2]);
        assert_eq!(store.pad_history("a", 99, 10).unwrap(), []);
        assert_eq!(store.pad_history("b", 0, 10).unwrap()[0].0, b1);
    }

    #[test]
    fn prune_deletes_pads_and_keeps_boards_and_pad_stats() {
        let (_dir, mut store) = fresh();
        let old = inspect(&mut store, 1, "p", 20, 100.0);
        let id = store.begin_board(&start(2, "p", 2.0)).unwrap();
        let mut pads: Vec<_> = (0..20).map(|i| pad(i, "pass", Some(100.0))).collect();
        pads[3] = pad(3, "fail", Some(20.0));
        store
            .finish_board(
                id,
                2.5,
                &cams(),
                &Outcome::Inspected {
                    verdict: "fail".to_owned(),
                    pads,
                },
            )
            .unwrap();
        let new = inspect(&mut store, 10, "p", 20, 100.0);
        let boards = store.boards(10).unwrap();
        let stats = |s: &Store| -> Vec<(u32, i64, f64, i64)> {
            s.conn
                .prepare("SELECT pad, boards, sum_volume_pct, fails FROM pad_stats ORDER BY pad")
                .unwrap()
                .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
                .unwrap()
                .collect::<Result<_, _>>()
                .unwrap()
        };
        let before = stats(&store);
        // Boards 1 and 2 ended at 1.5 and 2.5; board 10 at 10.5.
        assert_eq!(store.prune_pads(5.0).unwrap(), 40);
        assert_eq!(store.pads(old).unwrap(), []);
        assert_eq!(store.pads(id).unwrap(), []);
        assert_eq!(store.pads(new).unwrap().len(), 20);
        let defects: i64 = store
            .conn
            .query_row("SELECT count(*) FROM defects", [], |r| r.get(0))
            .unwrap();
        assert_eq!(defects, 0);
        assert_eq!(store.boards(10).unwrap(), boards);
        assert_eq!(stats(&store), before);
        assert_eq!(before[3], (3, 3, 103.0 + 20.0 + 103.0, 1));
        assert_eq!(store.pad_history("p", 0, 10).unwrap().len(), 1);
        assert_eq!(store.prune_pads(5.0).unwrap(), 0);
        store.check().unwrap();
    }

    #[test]
    fn a_newer_schema_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("line.sqlite");
        drop(Store::open(&path).unwrap());
        Connection::open(&path)
            .unwrap()
            .pragma_update(None, "user_version", 99)
            .unwrap();
        let e = Store::open(&path).unwrap_err();
        assert!(
            matches!(e, StoreError::NewerSchema { found: 99, known, .. } if known == SCHEMA_VERSION),
            "{e}"
        );
        let text = e.to_string();
        assert!(
            text.contains("line.sqlite") && text.contains("99"),
            "{text}"
        );
        // Left untouched.
        let v: i64 = Connection::open(&path)
            .unwrap()
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .unwrap();
        assert_eq!(v, 99);
    }

    #[test]
    fn opening_a_v1_store_again_changes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("line.sqlite");
        let (boards, pads, schema) = {
            let mut store = Store::open(&path).unwrap();
            let id = inspect(&mut store, 1, "p", 7, 100.0);
            store.begin_board(&start(2, "p", 2.0)).unwrap();
            let schema: Vec<String> = store
                .conn
                .prepare("SELECT sql FROM sqlite_schema WHERE sql IS NOT NULL ORDER BY name")
                .unwrap()
                .query_map([], |r| r.get(0))
                .unwrap()
                .collect::<Result<_, _>>()
                .unwrap();
            (store.boards(10).unwrap(), store.pads(id).unwrap(), schema)
        };
        for _ in 0..2 {
            let store = Store::open(&path).unwrap();
            assert_eq!(store.schema_version().unwrap(), 1);
            assert_eq!(store.boards(10).unwrap(), boards);
            assert_eq!(store.pads(boards[1].id).unwrap(), pads);
            let again: Vec<String> = store
                .conn
                .prepare("SELECT sql FROM sqlite_schema WHERE sql IS NOT NULL ORDER BY name")
                .unwrap()
                .query_map([], |r| r.get(0))
                .unwrap()
                .collect::<Result<_, _>>()
                .unwrap();
            assert_eq!(again, schema);
        }
    }

    #[test]
    fn pad_stats_equal_sums_recomputed_from_the_pad_rows() {
        let (_dir, mut store) = fresh();
        let mut seed = 0x1234_5678_u64;
        let mut next = move || {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (seed >> 33) as u32
        };
        for run in 0..8u64 {
            let product = if run % 3 == 0 { "b" } else { "a" };
            let id = store.begin_board(&start(run, product, run as f64)).unwrap();
            let pads = (0..30)
                .map(|i| {
                    let r = next() % 100;
                    let volume = if r < 10 {
                        None
                    } else {
                        Some(60.0 + f64::from(next() % 800) / 10.0)
                    };
                    let level = match r {
                        0..=14 => "fail",
                        15..=29 => "warn",
                        _ => "pass",
                    };
                    pad(i, level, volume)
                })
                .collect();
            store
                .finish_board(
                    id,
                    run as f64 + 0.5,
                    &cams(),
                    &Outcome::Inspected {
                        verdict: "fail".to_owned(),
                        pads,
                    },
                )
                .unwrap();
        }
        // Recompute from what `pads()` gives back.
        type Sums = (i64, f64, f64, i64, i64, i64);
        let mut want = std::collections::BTreeMap::<(String, u32), Sums>::new();
        for board in store.boards(100).unwrap() {
            for p in store.pads(board.id).unwrap() {
                let Some(v) = p.volume_pct else { continue };
                let e = want
                    .entry((board.product.clone(), p.pad))
                    .or_insert((0, 0.0, 0.0, 0, 0, 0));
                e.0 += 1;
                e.1 += v;
                e.2 += v * v;
                e.3 += i64::from(p.level == "fail");
                e.4 += i64::from(p.level == "warn");
                e.5 = e.5.max(board.id);
            }
        }
        let got: Vec<((String, u32), Sums)> = store
            .conn
            .prepare(
                "SELECT product, pad, boards, sum_volume_pct, sum_sq_volume_pct, fails, warns, \
                 last_board_id FROM pad_stats ORDER BY product, pad",
            )
            .unwrap()
            .query_map([], |r| {
                Ok((
                    (r.get(0)?, r.get(1)?),
                    (
                        r.get(2)?,
                        r.get(3)?,
                        r.get(4)?,
                        r.get(5)?,
                        r.get(6)?,
                        r.get(7)?,
                    ),
                ))
            })
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(got.len(), want.len());
        for ((key, g), (wkey, w)) in got.iter().zip(&want) {
            assert_eq!(key, wkey);
            assert_eq!((g.0, g.3, g.4, g.5), (w.0, w.3, w.4, w.5), "{key:?}");
            assert!((g.1 - w.1).abs() < 1e-9 * w.1.abs().max(1.0), "{key:?}");
            assert!((g.2 - w.2).abs() < 1e-9 * w.2.abs().max(1.0), "{key:?}");
        }
        assert!(got.iter().any(|(_, g)| g.3 > 0) && got.iter().any(|(_, g)| g.4 > 0));
    }

    #[test]
    fn the_benchmark_runs_small() {
        let dir = tempfile::tempdir().unwrap();
        let b = bench::run(dir.path(), 30, 200).unwrap();
        assert_eq!(b.boards, 30);
        assert!(b.pad_rows > 0 && b.pad_rows <= 30 * 200);
        assert!(b.insert.pads_per_s > 0.0 && b.history.median_ms >= 0.0);
        assert!(b.prune.pad_rows_deleted > 0);
        let json = serde_json::to_string(&b).unwrap();
        assert!(json.contains("\"goals\""), "{json}");
    }
}
