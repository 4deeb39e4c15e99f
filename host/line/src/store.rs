//! The line's store: every board the line began, how each ended, and every pad it measured;
//! in one SQLite file (the default: one line, one file) or in one PostgreSQL database that
//! all the lines of a factory share.
//!
//! The line service calls [`Store::begin_board`] when a board starts and
//! [`Store::finish_board`] when it has been inspected (or could not be); a board's end, its
//! cameras' losses, its pads, its defects and the per-pad running aggregates are written in one
//! transaction, so a reader (the CLI, an engineer's `sqlite3` or `psql`) sees a board whole or
//! not at all. After a restart, [`Store::recover`] turns the boards the service died in into
//! `incomplete` ones. [`Store::prune_pads`] is the retention: it deletes the bulky pad rows of
//! old boards and keeps the boards and the aggregates.
//!
//! A [`Store`] is opened for one line ([`Store::open`]`(location, line)`): it stamps the
//! boards it begins with that line's name, and what it reads or changes by line (recovery, the
//! board list, a pad's history, the aggregates, retention) is that line's only. A board read by
//! its id ([`Store::pads`]) may be any line's.
//!
//! # Where: [`Location`]
//!
//! - SQLite: a file (the service's default `DATA/line.sqlite`), in WAL mode: readers never
//!   block the writer, nor the writer the readers.
//! - PostgreSQL: a `postgres://` or `postgresql://` URL (`postgres://USER:PASSWORD@HOST:PORT/
//!   DATABASE`; rust-postgres's `postgres` crate, plain TCP without TLS). The tables go into
//!   the first schema of the connection's search path (`public` unless the role or the URL's
//!   `options=-csearch_path%3D...` says otherwise). A password in the URL is never shown: the
//!   store is named everywhere by [`Location`]'s `Display`, which writes `***` for it.
//!
//! # Two backends, one store
//!
//! [`Store`] holds an enum of the two connections and each method matches on it; each backend
//! (`store/sqlite.rs`, `store/pg.rs`) has the same methods. An enum rather than a trait object:
//! the set is closed (two databases), neither needs boxing nor object-safe signatures (a
//! transaction borrows its connection), a third backend would fail to compile at every method
//! until written, and what is common (checking values, run ids as text, NaN as NULL, the
//! line's name) stays here, once. The schema and its migrations are in one place for both,
//! `store/schema.rs`: one text per step with the words the dialects spell differently filled
//! in, or, where SQLite cannot alter in place, two texts side by side that end in the same
//! tables (a test compares the two backends' tables, columns and indexes).
//!
//! # Schema, version 4
//!
//! Versioned: SQLite's `PRAGMA user_version`; on PostgreSQL the one row of a table
//! `schema_version`. [`Store::open`] brings an older store up to [`SCHEMA_VERSION`] by
//! migrations and refuses one whose version is newer than this program knows
//! ([`StoreError::NewerSchema`]), leaving it untouched. On SQLite each migration is one
//! transaction (the version read again under the write lock); on PostgreSQL all of them are
//! one transaction under an advisory lock, so two lines starting at once on a new database do
//! not both migrate it. Version 1 was one line's store; version 2 added `line` to `boards`
//! and `pad_stats`, made a run id unique per line and the aggregates per line; version 3 added
//! `prints` and `stencil_cleans` (a store of version 2 gains them empty: the loop back to the
//! printer starts afresh); version 4 added `pad_images` and `reviews` for the operator's pages
//! (a store of version 3 gains them empty).
//! A version-1
//! SQLite file migrates in place (its `boards` and `pad_stats` copied into the new tables,
//! `pads` untouched); its boards become line `line-1`'s ([`DEFAULT_LINE`]), so a line of
//! another name that takes the file over renames them first (`UPDATE boards SET line = 'smt-3'
//! WHERE line = 'line-1'`, the same in `pad_stats`).
//!
//! Times are Unix seconds (REAL: an 8-byte float; DOUBLE PRECISION on PostgreSQL, whose REAL
//! is 4 bytes); a measurement that could not be made (NaN) is stored as NULL, never as NaN.
//! INTEGER is 64-bit on SQLite; on PostgreSQL, ids, counts of rows and aggregates are BIGINT
//! and the columns marked INTEGER below (a pad or camera index, a board's pad count) are its
//! 32-bit INTEGER. `id INTEGER PRIMARY KEY` is SQLite's rowid, `BIGINT GENERATED ALWAYS AS
//! IDENTITY PRIMARY KEY` on PostgreSQL.
//!
//! ## `boards`: one row per board a line began
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `id` | INTEGER PRIMARY KEY | the store's id of the board; grows with every board begun, across lines (on PostgreSQL it may skip values: a refused insert spends one) |
//! | `run_id` | TEXT NOT NULL | the line's run id, 16 lowercase hex digits; unique per line (`boards_by_run`): a board is never stored twice |
//! | `product` | TEXT NOT NULL | the product (board type) name |
//! | `program_hash` | TEXT NOT NULL | hash of the inspection program, as the caller gave it |
//! | `calibration_hash` | TEXT NOT NULL | hash of the calibration in use |
//! | `started_unix_s` | REAL NOT NULL | when the board began |
//! | `ended_unix_s` | REAL NULL | when it ended; NULL while `open` |
//! | `state` | TEXT NOT NULL | `open` (in progress), `inspected` or `incomplete` |
//! | `verdict` | TEXT NULL | `pass`, `warn` or `fail`: set for `inspected` boards only |
//! | `incomplete_reason` | TEXT NULL | why the board was never inspected: set for `incomplete` boards only |
//! | `pads` | INTEGER NOT NULL | pad rows written when it was inspected (0 otherwise); kept when [`Store::prune_pads`] deletes the rows |
//! | `line` | TEXT NOT NULL | the line's name (LINE.toml's `line`, default `line-1`), not empty (version 2) |
//!
//! A CHECK ties `state` to the others: an `open` board has no end, verdict nor reason; an
//! `inspected` board an end and a verdict and no reason; an `incomplete` board an end and a
//! reason, no verdict and no pads. Indexes: `boards_by_run (line, run_id)` UNIQUE,
//! `boards_by_line (line, product, state, id)` (a line's pad history), `boards_by_product
//! (product, state, id)` (a product across lines), `boards_by_end (ended_unix_s)` (retention)
//! and `boards_open (id) WHERE state = 'open'` (recovery).
//!
//! A run id is unique per line, not in the whole store: it is the line's (the frame grabbers
//! of one line share it, `docs/line.md`), and nothing makes two lines' run ids differ; a board
//! is named by its line and run id (the CFX spool is per line too).
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
//! Primary key `(board_id, camera)`, WITHOUT ROWID (SQLite).
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
//! | `uncertainty_um3` | REAL NULL | the volume's standard uncertainty, um³ (`docs/spc.md`, "Uncertainty"); NULL where not measured |
//!
//! Primary key `(board_id, pad)`. On SQLite the table is WITHOUT ROWID: the rows sit in the
//! primary key's B-tree itself, in the order they are written, which keeps inserts append-only
//! and makes a pad of a given board one B-tree lookup (a pad's history over 1,000 boards is
//! 1,000 lookups, served by `boards_by_line`: no second index on `pads` is needed, which would
//! cost every insert). On PostgreSQL the rows are a heap with the primary key an index beside
//! it (the same lookups, one more page each); they go in by binary `COPY` (measured, 6,000
//! pads: 28 ms a board, against 46 ms by INSERTs of 500 rows and 2.1 s by one INSERT a row,
//! `store::pg::tests::pad_rows_by_copy_and_by_insert`), and the foreign key to `boards` is
//! kept by statement-level triggers rather than the constraint, which checks every row by a
//! query of its own (70 of the 90 ms of a board's insert): a pad row of a board not in
//! `boards` is refused, deleting a board deletes its pads, a board's id cannot change
//! (`store/schema.rs`, version 2).
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
//! Primary key `(board_id, pad)`, WITHOUT ROWID (SQLite).
//!
//! ## `prints`: one row per board the line finished, the print and the loop back to the printer (version 3)
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `board_id` | INTEGER PRIMARY KEY | `boards.id` (ON DELETE CASCADE) |
//! | `x_um`, `y_um`, `rotation_mdeg`, `stretch_ppm` | REAL NULL | the print's placement on the board (`dpsa_inspect::print`): translation at the pattern's centre, rotation counter-clockwise, stretch; NULL, with every placement column, when it could not be fitted or the board was never inspected |
//! | `u_x_um`, `u_y_um`, `u_rotation_mdeg`, `u_stretch_ppm` | REAL NULL | their standard uncertainties |
//! | `scale_um` | REAL NULL | the robust scale of the pads' residuals |
//! | `centre_x_mm`, `centre_y_mm` | REAL NULL | the pattern's centre the translation is at, design mm |
//! | `pads_used`, `outliers` | INTEGER NULL | pads the fit used and set aside |
//! | `correction_x_um`, `correction_y_um`, `correction_rotation_mdeg` | REAL NOT NULL | the correction proposed to the printer after the board (absolute: its offset setting) |
//! | `change_x_um`, `change_y_um`, `change_rotation_mdeg` | REAL NOT NULL | its change from the one before |
//! | `estimate_x_um`, `estimate_y_um`, `estimate_rotation_mdeg` | REAL NULL | the loop's estimate of the printer's own error; NULL before its first placement |
//! | `u_estimate_x_um`, `u_estimate_y_um`, `u_estimate_rotation_mdeg` | REAL NULL | its standard uncertainty |
//! | `held`, `limited` | INTEGER NOT NULL | axes held in the dead band and axes at a limit, bit 0 x, bit 1 y, bit 2 rotation |
//! | `reason` | TEXT NOT NULL | what the loop did and why, for a person |
//!
//! Written in [`Store::finish_board_with_print`]'s transaction with the board (an incomplete
//! board gets a row too, without a placement: it was printed, and the loop counts it in its
//! delay). The line's loop resumes from a product's newest rows ([`Store::prints`]); an
//! engineer's chart of the printer is one join:
//!
//! ```sql
//! SELECT b.run_id, p.x_um, p.y_um, p.rotation_mdeg, p.correction_x_um, p.correction_y_um,
//!        p.correction_rotation_mdeg, p.reason
//! FROM prints AS p JOIN boards AS b ON b.id = p.board_id
//! WHERE b.line = 'line-1' AND b.product = 'ctrl-b' ORDER BY p.board_id DESC LIMIT 50;
//! ```
//!
//! ## `stencil_cleans`: the stencil's cleans, as reported (version 3)
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `id` | INTEGER PRIMARY KEY | |
//! | `line` | TEXT NOT NULL | the line, not empty |
//! | `product` | TEXT NOT NULL | the product printed with the stencil, not empty |
//! | `cleaned_unix_s` | REAL NOT NULL | when it was cleaned |
//! | `source` | TEXT NOT NULL | who says so (`operator`, the printer's name), not empty |
//! | `note` | TEXT NULL | for a person |
//!
//! Index `stencil_cleans_by_line (line, product, cleaned_unix_s)`. Written by
//! [`Store::record_clean`] (`dpsa line clean`, a printer integration); `dpsa spc` counts the
//! fine apertures' clogging from the last clean before its newest board.
//!
//! ## `pad_images`: the heights around each pad that warned or failed (version 4)
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `board_id` | INTEGER NOT NULL | `boards.id` (ON DELETE CASCADE) |
//! | `pad` | INTEGER NOT NULL | the pad's index; a pad row of the board has it |
//! | `family` | TEXT NULL | the pad's package family (its component's package, else its aperture class) |
//! | `x0_mm`, `y0_mm` | REAL NOT NULL | board `x`, `y` of the first sample's centre |
//! | `pitch_mm` | REAL NOT NULL | sample pitch (the map's), > 0 |
//! | `nx`, `ny` | INTEGER NOT NULL | samples along `x` and `y`, 1..=256 each |
//! | `lsb_um` | REAL NOT NULL | the height step, [`IMAGE_LSB_UM`] |
//! | `heights` | BLOB NOT NULL (BYTEA) | `nx x ny` little-endian `i16` heights above the pad's local surface in `lsb_um` steps, `[ix * ny + iy]`; [`INVALID_SAMPLE`] where the map had none; a CHECK holds its length to `2 nx ny` |
//! | `outline` | TEXT NOT NULL | the opening on the board, JSON (`dpsa_gerber::pads::Outline`) |
//!
//! Primary key `(board_id, pad)`, WITHOUT ROWID (SQLite). Written in
//! [`Store::finish_board_with_images`]'s transaction (the line keeps at most 200 a board,
//! failures first; about 12 kB for a 1 mm pad at a 28 um pitch); deleted with the board's pad
//! rows by [`Store::prune_pads`].
//!
//! ## `reviews`: an operator's decision on a call (version 4)
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `id` | INTEGER PRIMARY KEY | grows with every review |
//! | `board_id` | INTEGER NOT NULL | `boards.id` (ON DELETE CASCADE), an inspected board |
//! | `pad` | INTEGER NOT NULL | the pad; it warned or failed (its `defects` row, while kept) |
//! | `family` | TEXT NULL | the pad's package family, copied from its image when reviewed (the rates outlive the pruned rows) |
//! | `decision` | TEXT NOT NULL | `confirmed` or `false_call` |
//! | `reviewer` | TEXT NOT NULL | who, not empty |
//! | `reviewed_unix_s` | REAL NOT NULL | when |
//! | `note` | TEXT NULL | what the reviewer wrote |
//!
//! Index `reviews_by_board (board_id, pad, id)`. A pad may be reviewed again: the newest
//! decision counts ([`Store::family_reviews`]). Written by [`Store::add_review`] (`dpsa
//! serve`'s review form); kept by retention.
//!
//! The false-call rate per family over a line, each pad's newest decision once:
//!
//! ```sql
//! SELECT r.family, sum(r.decision = 'false_call') AS false_calls, count(*) AS reviewed
//! FROM reviews AS r JOIN boards AS b ON b.id = r.board_id
//! WHERE b.line = 'line-1' AND r.id = (SELECT max(q.id) FROM reviews AS q
//!     WHERE q.board_id = r.board_id AND q.pad = r.pad)
//! GROUP BY r.family ORDER BY false_calls * 1.0 / count(*) DESC;
//! ```
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
//! ## `pad_stats`: running aggregates per pad of a product on a line, kept for ever
//!
//! | column | type | meaning |
//! | --- | --- | --- |
//! | `line` | TEXT NOT NULL | the line whose boards these are, not empty (version 2) |
//! | `product` | TEXT NOT NULL | the product |
//! | `pad` | INTEGER NOT NULL | pad index |
//! | `boards` | INTEGER NOT NULL | inspected boards on which the pad had a `volume_pct` |
//! | `sum_volume_pct` | REAL NOT NULL | Σ volume_pct over those boards |
//! | `sum_sq_volume_pct` | REAL NOT NULL | Σ volume_pct² over those boards |
//! | `fails` | INTEGER NOT NULL | of those boards, how many the pad failed |
//! | `warns` | INTEGER NOT NULL | of those boards, how many it warned |
//! | `last_board_id` | INTEGER NOT NULL | the last board counted |
//!
//! Primary key `(line, product, pad)`, WITHOUT ROWID (SQLite); on PostgreSQL half of each
//! page is left free (`fillfactor = 50`), so that the update of a row stays on its page and
//! leaves the key's index alone ("HOT": half the time of an update). Updated in
//! [`Store::finish_board`]'s transaction for inspected boards, and only for the pads with a
//! `volume_pct` (a pad whose volume could not be measured is not counted, not even in `fails`:
//! its fail is in `defects`). Mean = `sum_volume_pct / boards`; variance = `sum_sq_volume_pct
//! / boards - mean²`.
//!
//! Per line, not per product across lines: each line's printer and stencil are their own
//! process, and a statistical control loop watches one of them (a drifting printer shows in
//! its line's row, where a row shared with a good line would dilute it). The sums add up, so
//! the product's figures across lines are one `GROUP BY` away (below), while per-product rows
//! could never be split by line again. And two lines running the same product never update
//! the same rows, so they never wait for each other's locks on PostgreSQL.
//!
//! # Checks ([`Store::check`])
//!
//! SQLite: `PRAGMA integrity_check` (every page and index) and `PRAGMA foreign_key_check`.
//! PostgreSQL has neither (its `amcheck` is an extension only a superuser installs). On both,
//! in one read snapshot, the rows are checked against what the schema states and what the
//! store keeps true: each CHECK restated as a query (boards' state against end, verdict, reason and pad
//! count; run ids 16 hex digits; camera, pad, level and coverage ranges; aggregates with
//! `fails + warns <= boards`), the foreign keys (no camera, pad or defect row of a board not
//! in the store), a board's pad rows as many as its `pads` and only for inspected boards,
//! one `defects` row for each pad that warned or failed and a pad row for each defect. On
//! PostgreSQL also: no NaN anywhere, no trigger switched off, the triggers that keep `pads`'
//! foreign key all there, no constraint added `NOT VALID`, and `schema_version` at this
//! program's version. The checks read every pad row: seconds for a store of gigabytes.
//! [`Store::check_newest`] applies the same rules to the rows of the newest boards only (and
//! to the aggregates, whole), without SQLite's page checks: what `dpsa line run` does at
//! start on a store larger than [`crate::service::WHOLE_CHECK_BYTES`].
//!
//! # Queries an engineer would run
//!
//! (SQLite spelling; on PostgreSQL `to_timestamp(started_unix_s)` for `datetime(started_unix_s,
//! 'unixepoch')`.) The last 20 boards of line `line-1`, with their result:
//!
//! ```sql
//! SELECT id, run_id, product, datetime(started_unix_s, 'unixepoch') AS started, state,
//!        coalesce(verdict, incomplete_reason, '(in progress)') AS result, pads
//! FROM boards WHERE line = 'line-1' ORDER BY id DESC LIMIT 20;
//! ```
//!
//! Pad 17's volume over the last 100 inspected boards of a product on a line, newest first:
//!
//! ```sql
//! SELECT b.id, b.run_id, datetime(b.started_unix_s, 'unixepoch') AS started,
//!        p.name, p.level, p.volume_pct
//! FROM (SELECT id, run_id, started_unix_s FROM boards
//!       WHERE line = 'line-1' AND product = 'ctrl-b' AND state = 'inspected'
//!       ORDER BY id DESC LIMIT 100) AS b
//! JOIN pads AS p ON p.board_id = b.id AND p.pad = 17
//! ORDER BY b.id DESC;
//! ```
//!
//! Defects per line, class and hour over the last day:
//!
//! ```sql
//! SELECT strftime('%Y-%m-%d %H:00', b.ended_unix_s, 'unixepoch') AS hour, b.line,
//!        d.level, coalesce(d.class, '?') AS class, count(*) AS pads
//! FROM defects AS d JOIN boards AS b ON b.id = d.board_id
//! WHERE b.ended_unix_s >= CAST(strftime('%s', 'now', '-1 day') AS REAL)
//! GROUP BY hour, b.line, d.level, class ORDER BY hour, pads DESC;
//! ```
//!
//! Boards never inspected, and why:
//!
//! ```sql
//! SELECT line, incomplete_reason, count(*) AS boards,
//!        datetime(max(ended_unix_s), 'unixepoch') AS last
//! FROM boards WHERE state = 'incomplete'
//! GROUP BY line, incomplete_reason ORDER BY boards DESC;
//! ```
//!
//! The pads of a product whose volume drifts most on a line, from the aggregates:
//!
//! ```sql
//! SELECT pad, boards, sum_volume_pct / boards AS mean_pct,
//!        sqrt(max(sum_sq_volume_pct / boards - (sum_volume_pct / boards) * (sum_volume_pct / boards), 0)) AS sd_pct,
//!        fails, warns
//! FROM pad_stats WHERE line = 'line-1' AND product = 'ctrl-b'
//! ORDER BY abs(mean_pct - 100) DESC LIMIT 20;
//! ```
//!
//! (`sqrt` needs an `sqlite3` built with the math functions, as the bundled one is;
//! PostgreSQL spells `max(a, b)` `greatest(a, b)`.) The same product across all lines:
//!
//! ```sql
//! SELECT pad, sum(boards) AS boards, sum(sum_volume_pct) / sum(boards) AS mean_pct,
//!        sum(fails) AS fails, sum(warns) AS warns
//! FROM pad_stats WHERE product = 'ctrl-b' GROUP BY pad ORDER BY pad;
//! ```

use crate::printer::{Correction, Proposal};
use dpsa_inspect::print::PrintOffset;
use std::path::PathBuf;

/// A run id as JSON: 16 lowercase hex digits, as the logs, the CFX spool and the `boards`
/// table write it (a JSON number would lose bits in readers that hold numbers as f64).
fn hex_id<S: serde::Serializer>(id: &u64, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(&format_args!("{id:016x}"))
}

#[path = "store_bench.rs"]
pub mod bench;
mod pg;
#[cfg(test)]
mod pg_test_server;
mod review;
mod schema;
mod sqlite;

use review::ImageValues;
pub use review::{Decision, FamilyReviews, PadImage, Review, IMAGE_LSB_UM, INVALID_SAMPLE};
use schema::{Step, MIGRATIONS};

/// The newest schema version this program knows (`PRAGMA user_version` of a store it made).
pub const SCHEMA_VERSION: u32 = MIGRATIONS.len() as u32;

/// The end of a check: `Ok` when no rule was `broken`, else [`StoreError::Corrupt`] saying
/// each.
fn broken_rules(store: &str, broken: &[String]) -> Result<(), StoreError> {
    if broken.is_empty() {
        Ok(())
    } else {
        Err(StoreError::Corrupt {
            store: store.to_owned(),
            why: broken.join("; "),
        })
    }
}

/// The line's name when LINE.toml gives none, and the line of every board stored before
/// schema version 2.
pub const DEFAULT_LINE: &str = "line-1";

/// Boards whose pads [`Store::prune_pads`] deletes in one transaction: short enough that the
/// line's own writes wait little, long enough that the commits cost nothing.
const PRUNE_BOARDS_PER_TRANSACTION: usize = 50;

/// Whether `name` may name a line: 1 to 64 ASCII letters, digits, `-`, `_` or `.` (it is
/// written in logs, JSON and SQL by hand, and compared byte for byte). `Err` says why not.
pub fn check_line_name(name: &str) -> Result<(), String> {
    let ok = (1..=64).contains(&name.len())
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'));
    if ok {
        Ok(())
    } else {
        Err(format!(
            "{name:?} is not a line name (1 to 64 ASCII letters, digits, '-', '_' or '.')"
        ))
    }
}

/// Where a store is: an SQLite file or a PostgreSQL database.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Location {
    /// An SQLite file (made, with its directory, if missing).
    Sqlite(PathBuf),
    /// A PostgreSQL database.
    Postgres(PgUrl),
}

impl std::fmt::Display for Location {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Location::Sqlite(p) => write!(f, "{}", p.display()),
            Location::Postgres(u) => u.fmt(f),
        }
    }
}

/// The URL schemes of PostgreSQL.
const PG_SCHEMES: [&str; 2] = ["postgres://", "postgresql://"];

impl Location {
    /// A PostgreSQL URL, as LINE.toml's `store` key takes: `postgres://` or `postgresql://`,
    /// parsed here (host, port, options), so a wrong one is refused before anything starts.
    /// `Err` is a sentence that shows the text with its password hidden.
    pub fn postgres(text: &str) -> Result<Location, String> {
        if !PG_SCHEMES.iter().any(|s| text.starts_with(s)) {
            return Err(format!(
                "{:?} is not a PostgreSQL URL (postgres://USER:PASSWORD@HOST:PORT/DATABASE)",
                redact(text)
            ));
        }
        let url = PgUrl {
            url: text.to_owned(),
            shown: redact(text),
            schema: None,
        };
        url.config()?;
        Ok(Location::Postgres(url))
    }

    /// A command line's store: a PostgreSQL URL, else a path of an SQLite file. Another
    /// `scheme://` is refused (it is no path anyone means).
    pub fn from_arg(text: &str) -> Result<Location, String> {
        if PG_SCHEMES.iter().any(|s| text.starts_with(s)) {
            Location::postgres(text)
        } else if text.contains("://") {
            Err(format!(
                "{:?} is neither a PostgreSQL URL (postgres://USER:PASSWORD@HOST:PORT/DATABASE) \
                 nor the path of an SQLite file",
                redact(text)
            ))
        } else if text.is_empty() {
            Err("an empty store: give a PostgreSQL URL or the path of an SQLite file".to_owned())
        } else {
            Ok(Location::Sqlite(PathBuf::from(text)))
        }
    }

    /// `sqlite` or `postgres`.
    pub fn backend(&self) -> &'static str {
        match self {
            Location::Sqlite(_) => "sqlite",
            Location::Postgres(_) => "postgres",
        }
    }
}

/// `text` with the password of a URL's user (`scheme://user:PASSWORD@host`, up to the first
/// `@`, as the PostgreSQL client reads it) and the value of any `password=` parameter replaced
/// by `***`.
fn redact(text: &str) -> String {
    let mut out = text.to_owned();
    if let Some(start) = out.find("://").map(|i| i + 3) {
        if let Some(at) = out[start..].find('@').map(|i| start + i) {
            if let Some(colon) = out[start..at].find(':').map(|i| start + i) {
                out.replace_range(colon + 1..at, "***");
            }
        }
    }
    let mut from = 0;
    while let Some(i) = out[from..].to_ascii_lowercase().find("password=") {
        let value = from + i + "password=".len();
        let end = out[value..]
            .find(|c: char| c == '&' || c.is_whitespace())
            .map_or(out.len(), |e| value + e);
        out.replace_range(value..end, "***");
        from = value + 3;
    }
    out
}

/// A PostgreSQL URL whose `Display` and `Debug` hide its password.
#[derive(Clone, PartialEq, Eq)]
pub struct PgUrl {
    /// As given (with the password): only ever handed to the client.
    url: String,
    /// With the password hidden: what logs and errors show.
    shown: String,
    /// A schema to put first on the search path (the benchmark's scratch space).
    schema: Option<String>,
}

impl PgUrl {
    /// The client's configuration, or why the URL is none (never quoting the URL).
    fn config(&self) -> Result<postgres::Config, String> {
        self.url.parse::<postgres::Config>().map_err(|e| {
            // The client's sentence is in its source ("invalid value for option `port`"); it
            // names options, never their values.
            let why =
                std::error::Error::source(&e).map_or_else(|| e.to_string(), |s| s.to_string());
            format!(
                "{:?} is not a PostgreSQL URL the client reads: {why}",
                self.shown
            )
        })
    }

    /// The schema put first on the search path, if any.
    fn schema(&self) -> Option<&str> {
        self.schema.as_deref()
    }

    /// The same database with `schema` first on the search path.
    fn with_schema(&self, schema: &str) -> PgUrl {
        PgUrl {
            schema: Some(schema.to_owned()),
            ..self.clone()
        }
    }

    /// The same database with the search path the URL gives.
    fn without_schema(&self) -> PgUrl {
        PgUrl {
            schema: None,
            ..self.clone()
        }
    }
}

impl std::fmt::Display for PgUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.shown)?;
        match &self.schema {
            Some(s) => write!(f, " (schema {s})"),
            None => Ok(()),
        }
    }
}

impl std::fmt::Debug for PgUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PgUrl({self})")
    }
}

/// Why the store could not do what was asked. Every sentence names the store: its file, or
/// its URL with the password hidden.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// The store's directory (or the file, for its size) could not be reached.
    #[error("cannot create or read the store {store}")]
    Io {
        /// The store.
        store: String,
        /// What the system said.
        source: std::io::Error,
    },
    /// SQLite failed (disk full, locked beyond the busy timeout, a constraint refused a row...).
    #[error("SQLite failed on the store {store}")]
    Sqlite {
        /// The store.
        store: String,
        /// What SQLite said.
        source: rusqlite::Error,
    },
    /// PostgreSQL failed (no server there, refused login, a constraint refused a row, the
    /// connection cut...).
    #[error("PostgreSQL failed on the store {store}")]
    Postgres {
        /// The store.
        store: String,
        /// What the client or the server said.
        source: postgres::Error,
    },
    /// The store was written by a newer program: its schema is unknown here, so it is left
    /// alone.
    #[error(
        "the store {store} has schema version {found}, newer than the {known} this program \
         knows: use the newer program (or another store)"
    )]
    NewerSchema {
        /// The store.
        store: String,
        /// Its version.
        found: u32,
        /// [`SCHEMA_VERSION`].
        known: u32,
    },
    /// The store is damaged (or is not an SQLite database at all), or breaks its own rules.
    #[error("the store {store} is damaged: {why}")]
    Corrupt {
        /// The store.
        store: String,
        /// What the checks (or the database itself) said.
        why: String,
    },
    /// A board with this run id is already stored for this line: a board is never stored
    /// twice.
    #[error("the store {store} already holds a board of run id {run_id:016x} of line {line}")]
    Duplicate {
        /// The store.
        store: String,
        /// The line.
        line: String,
        /// The run id.
        run_id: u64,
    },
    /// No board has this id.
    #[error("the store {store} has no board {id}")]
    UnknownBoard {
        /// The store.
        store: String,
        /// The board id asked for.
        id: i64,
    },
    /// The board was already finished: a finished board is never rewritten.
    #[error(
        "board {id} of the store {store} is already {state}, not open: a finished board is \
         never rewritten"
    )]
    NotOpen {
        /// The store.
        store: String,
        /// The board id.
        id: i64,
        /// Its state (`inspected` or `incomplete`).
        state: String,
    },
    /// Another service holds this line on the store (PostgreSQL).
    #[error(
        "line {line} is in use on the store {store}: another `dpsa line run` serves a line of \
         that name there; give each line its own `line` name in its LINE.toml"
    )]
    LineInUse {
        /// The store.
        store: String,
        /// The line.
        line: String,
    },
    /// A value the caller gave was refused before anything was written.
    #[error("the store {store} refused a value: {why}")]
    Invalid {
        /// The store.
        store: String,
        /// Which value, and why.
        why: String,
    },
}
/// A board the line began.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BoardStart {
    /// The line's run id; stored as 16 lowercase hex digits, unique per line.
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
    /// The volume's standard uncertainty, um³ (`None` where not measured).
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

/// The print of one finished board and what the loop back to the printer proposed after it
/// (table `prints`, version 3).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PrintRow {
    /// The print's placement measured on the board (`None`: it could not be fitted, or the
    /// board was never inspected).
    pub placement: Option<PrintOffset>,
    /// The correction the loop proposed after the board (its estimate NaN before the loop's
    /// first placement).
    pub proposal: Proposal,
}

/// What a board's end writes beside its outcome, encoded: its print row and its pads' images.
pub(crate) struct Beside {
    pub(crate) print: Option<PrintValues>,
    pub(crate) images: Vec<ImageValues>,
}

/// A stored [`PrintRow`] with its board ([`Store::prints`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StoredPrint {
    /// The store's id of the board.
    pub board_id: i64,
    /// Its run id.
    #[serde(serialize_with = "hex_id")]
    pub run_id: u64,
    /// The placement and the proposal.
    #[serde(flatten)]
    pub print: PrintRow,
}

/// `prints`' columns after `board_id`, in the order of [`PrintValues`]: the reals, the two
/// counts, the two flag sets, the reason.
pub(crate) const PRINT_COLUMNS: &str = "x_um, y_um, rotation_mdeg, stretch_ppm, u_x_um, u_y_um, \
     u_rotation_mdeg, u_stretch_ppm, scale_um, centre_x_mm, centre_y_mm, correction_x_um, \
     correction_y_um, correction_rotation_mdeg, change_x_um, change_y_um, \
     change_rotation_mdeg, estimate_x_um, estimate_y_um, estimate_rotation_mdeg, \
     u_estimate_x_um, u_estimate_y_um, u_estimate_rotation_mdeg, pads_used, outliers, held, \
     limited, reason";

/// Reals of a print row.
pub(crate) const PRINT_REALS: usize = 23;

/// Parameters of a print row's insert: the board's id and [`PRINT_COLUMNS`].
const PRINT_PARAMS: usize = 1 + PRINT_REALS + 5;

/// The insert of a print row, parameters `1..=PRINT_PARAMS` written `{mark}N` (`?` or `$`).
fn insert_print_sql(mark: char) -> String {
    let marks: Vec<String> = (1..=PRINT_PARAMS).map(|k| format!("{mark}{k}")).collect();
    format!(
        "INSERT INTO prints (board_id, {PRINT_COLUMNS}) VALUES ({})",
        marks.join(", ")
    )
}

/// A line's print rows of a product, newest first: walks `prints` backwards by its key and
/// joins each row's board by its key (a restart reads a few rows, however old the line).
fn select_prints_sql(mark: char) -> String {
    format!(
        "SELECT b.id, b.run_id, {} FROM prints AS p JOIN boards AS b ON b.id = p.board_id \
         WHERE b.line = {mark}1 AND b.product = {mark}2 ORDER BY p.board_id DESC LIMIT {mark}3",
        PRINT_COLUMNS
            .split(',')
            .map(|c| format!("p.{}", c.trim()))
            .collect::<Vec<_>>()
            .join(", ")
    )
}

/// A [`PrintRow`] as `prints`' columns hold it (NaN as NULL), for both backends.
#[derive(Debug, Clone)]
pub(crate) struct PrintValues {
    /// Placement (4), its uncertainties (4), scale, centre (2); correction (3), change (3),
    /// estimate (3) and its uncertainty (3).
    pub(crate) reals: [Option<f64>; PRINT_REALS],
    /// Pads used and outliers of the placement.
    pub(crate) counts: [Option<i32>; 2],
    /// Held and limited axes, bit 0 x, bit 1 y, bit 2 rotation.
    pub(crate) flags: [i32; 2],
    /// The proposal's reason.
    pub(crate) reason: String,
}

fn axis_bits(v: [bool; 3]) -> i32 {
    v.iter().enumerate().map(|(k, &b)| i32::from(b) << k).sum()
}

impl PrintValues {
    pub(crate) fn of(r: &PrintRow) -> PrintValues {
        let mut reals = [None; PRINT_REALS];
        if let Some(p) = &r.placement {
            let v = [
                p.x_um,
                p.y_um,
                p.rotation_mdeg,
                p.stretch_ppm,
                p.uncertainty[0],
                p.uncertainty[1],
                p.uncertainty[2],
                p.uncertainty[3],
                p.scale_um,
                p.centre_mm[0],
                p.centre_mm[1],
            ];
            for (d, s) in reals.iter_mut().zip(v) {
                *d = real(Some(s));
            }
        }
        let q = &r.proposal;
        for (k, c) in [
            &q.correction,
            &q.change,
            &q.estimate,
            &q.estimate_uncertainty,
        ]
        .into_iter()
        .enumerate()
        {
            for (j, v) in c.as_array().into_iter().enumerate() {
                reals[11 + 3 * k + j] = real(Some(v));
            }
        }
        let count = |n: usize| Some(i32::try_from(n).unwrap_or(i32::MAX));
        PrintValues {
            reals,
            counts: match &r.placement {
                Some(p) => [count(p.pads), count(p.outliers)],
                None => [None, None],
            },
            flags: [axis_bits(q.held), axis_bits(q.limited)],
            reason: q.reason.clone(),
        }
    }

    pub(crate) fn row(self) -> PrintRow {
        let r = self.reals.map(|v| v.unwrap_or(f64::NAN));
        let placement = self.counts[0].map(|pads| PrintOffset {
            x_um: r[0],
            y_um: r[1],
            rotation_mdeg: r[2],
            stretch_ppm: r[3],
            uncertainty: [r[4], r[5], r[6], r[7]],
            scale_um: r[8],
            centre_mm: [r[9], r[10]],
            pads: pads.max(0) as usize,
            outliers: self.counts[1].unwrap_or(0).max(0) as usize,
        });
        let c = |k: usize| Correction {
            x_um: r[11 + 3 * k],
            y_um: r[12 + 3 * k],
            rotation_mdeg: r[13 + 3 * k],
        };
        let bits = |v: i32| [0, 1, 2].map(|k| v >> k & 1 == 1);
        PrintRow {
            placement,
            proposal: Proposal {
                correction: c(0),
                change: c(1),
                estimate: c(2),
                estimate_uncertainty: c(3),
                held: bits(self.flags[0]),
                limited: bits(self.flags[1]),
                reason: self.reason,
            },
        }
    }
}

/// A clean of the stencil, as a printer or an operator reported it (table `stencil_cleans`,
/// version 3).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StencilClean {
    /// The store's id of the event.
    pub id: i64,
    /// The product printed with the stencil.
    pub product: String,
    /// When the stencil was cleaned, Unix seconds.
    pub cleaned_unix_s: f64,
    /// Who says so: `operator`, the printer's name, ...
    pub source: String,
    /// A note, for a person.
    pub note: Option<String>,
}

/// A board as the store holds it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StoredBoard {
    /// The store's id of the board.
    pub id: i64,
    /// The line's run id.
    #[serde(serialize_with = "hex_id")]
    pub run_id: u64,
    /// The line that began it.
    pub line: String,
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

/// Which of a line's boards to list: of one product (`None`: any), inspected only or all.
#[derive(Debug, Clone, Default)]
pub(crate) struct Which {
    product: Option<String>,
    inspected: bool,
    /// One board by its id.
    id: Option<i64>,
}

/// One board of a pad's history ([`Store::pad_history`]): `(board id, run id, level,
/// volume_pct)`.
pub type HistoryEntry = (i64, u64, String, Option<f64>);

/// A reader's check of a store's schema version: this program's, else refused (a reader
/// never migrates).
fn check_reader_version(store: &str, found: u32) -> Result<(), StoreError> {
    if found > SCHEMA_VERSION {
        return Err(StoreError::NewerSchema {
            store: store.to_owned(),
            found,
            known: SCHEMA_VERSION,
        });
    }
    if found < SCHEMA_VERSION {
        return Err(StoreError::Invalid {
            store: store.to_owned(),
            why: format!(
                "schema version {found}, older than this program's {SCHEMA_VERSION}: a reader \
                 does not migrate it; open it once for writing (`dpsa line run` or `dpsa line \
                 boards`)"
            ),
        });
    }
    Ok(())
}

/// A run id as stored: 16 lowercase hex digits.
fn run_id_text(run_id: u64) -> String {
    format!("{run_id:016x}")
}

/// A stored run id back to its number.
fn parse_run_id(store: &str, text: &str) -> Result<u64, StoreError> {
    match u64::from_str_radix(text, 16) {
        Ok(v) if text.len() == 16 => Ok(v),
        _ => Err(StoreError::Corrupt {
            store: store.to_owned(),
            why: format!("a board's run id is {text:?}, not 16 hex digits"),
        }),
    }
}

/// NaN (a measurement that could not be made) becomes `None`, so NULL: never a NaN stored.
fn real(v: Option<f64>) -> Option<f64> {
    v.filter(|x| !x.is_nan())
}

const LEVELS: [&str; 3] = ["pass", "warn", "fail"];

/// The two connections. (PostgreSQL's client, its statements and its URL are the larger:
/// boxed, as a store is opened once and moved about.)
#[derive(Debug)]
enum Db {
    Sqlite(sqlite::Sqlite),
    Postgres(Box<pg::Pg>),
}

/// Calls the same method of whichever backend the store is on.
macro_rules! on_backend {
    ($db:expr, $b:ident => $call:expr) => {
        match $db {
            Db::Sqlite($b) => $call,
            Db::Postgres($b) => $call,
        }
    };
}

/// The line's store: one connection to an SQLite file or a PostgreSQL database, for one line.
#[derive(Debug)]
pub struct Store {
    db: Db,
    location: Location,
    line: String,
}

impl Store {
    /// Opens the store at `location` for line `line`, creating it if it does not exist (an
    /// SQLite file and its directory; on PostgreSQL the tables, in a database that must
    /// exist), and brings its schema up to [`SCHEMA_VERSION`] by migrations (see the module
    /// documentation). A store of a newer schema is refused ([`StoreError::NewerSchema`]) and
    /// left untouched; a file that is no SQLite database is [`StoreError::Corrupt`]; a line
    /// name [`check_line_name`] refuses is [`StoreError::Invalid`].
    ///
    /// SQLite: WAL mode with `synchronous = NORMAL`, foreign keys on, a busy timeout of 10 s;
    /// a crash or power cut can lose the last transactions not yet synced (each one whole,
    /// never half), never corrupt the file, and [`Store::recover`] finds the boards left open.
    /// PostgreSQL: the server's own durability (`synchronous_commit`); a connection found
    /// closed is opened again before the next call.
    pub fn open(location: &Location, line: &str) -> Result<Store, StoreError> {
        Self::open_with(location, line, MIGRATIONS)
    }

    /// Opens the store at `location` for reading only (the web pages): nothing is created,
    /// migrated or written (SQLite's read-only mode; on PostgreSQL every transaction
    /// read-only), and a store of another schema version is refused: an older one is migrated
    /// by any program that opens it for writing (`dpsa line run`, `dpsa line boards`).
    pub fn open_read_only(location: &Location, line: &str) -> Result<Store, StoreError> {
        check_line_name(line).map_err(|why| StoreError::Invalid {
            store: location.to_string(),
            why: format!("line: {why}"),
        })?;
        let db = match location {
            Location::Sqlite(path) => Db::Sqlite(sqlite::Sqlite::open_read_only(path)?),
            Location::Postgres(url) => Db::Postgres(Box::new(pg::Pg::open_read_only(url)?)),
        };
        Ok(Store {
            db,
            location: location.clone(),
            line: line.to_owned(),
        })
    }

    /// [`Store::open`] with another list of migrations (the benchmark compares schemas; tests
    /// make stores of an older version).
    fn open_with(
        location: &Location,
        line: &str,
        migrations: &[Step],
    ) -> Result<Store, StoreError> {
        check_line_name(line).map_err(|why| StoreError::Invalid {
            store: location.to_string(),
            why: format!("line: {why}"),
        })?;
        let db = match location {
            Location::Sqlite(path) => Db::Sqlite(sqlite::Sqlite::open(path, migrations)?),
            Location::Postgres(url) => Db::Postgres(Box::new(pg::Pg::open(url, migrations)?)),
        };
        Ok(Store {
            db,
            location: location.clone(),
            line: line.to_owned(),
        })
    }

    /// Where the store is.
    pub fn location(&self) -> &Location {
        &self.location
    }

    /// The line this store was opened for.
    pub fn line(&self) -> &str {
        &self.line
    }

    /// The store's schema version: [`SCHEMA_VERSION`] once open.
    pub fn schema_version(&mut self) -> Result<u32, StoreError> {
        on_backend!(&mut self.db, d => d.schema_version())
    }

    /// Claims the line for this connection, for as long as the store is open: on PostgreSQL a
    /// session advisory lock on the line's name, so that a second service of the same line
    /// (two hosts left at the default name) is refused ([`StoreError::LineInUse`]) before its
    /// [`Store::recover`] turns the first one's open boards incomplete. On SQLite nothing (a
    /// file is one host's, whose ports the second service could not take anyway).
    pub fn claim_line(&mut self) -> Result<(), StoreError> {
        match &mut self.db {
            Db::Sqlite(_) => Ok(()),
            Db::Postgres(d) => d.claim_line(&self.line),
        }
    }

    fn invalid(&self, why: String) -> StoreError {
        StoreError::Invalid {
            store: self.location.to_string(),
            why,
        }
    }

    /// A board the line began: a row in state `open`, of this store's line. Returns its id.
    /// A run id already stored for this line is refused ([`StoreError::Duplicate`]): a board
    /// is never stored twice.
    pub fn begin_board(&mut self, b: &BoardStart) -> Result<i64, StoreError> {
        if !b.started_unix_s.is_finite() {
            return Err(self.invalid(format!(
                "board {:016x} started at {} s",
                b.run_id, b.started_unix_s
            )));
        }
        on_backend!(&mut self.db, d => d.begin_board(&self.line, b))
    }

    /// Refuses, before anything is written, what a CHECK would refuse less clearly, and what
    /// one of the backends could not hold (a pad index or count past 2^31 - 1: PostgreSQL's
    /// INTEGER; a count past 2^63 - 1: either's 64 bits).
    fn validate_finish(
        &self,
        id: i64,
        ended_unix_s: f64,
        cameras: &[CameraLoss],
        outcome: &Outcome,
    ) -> Result<(), StoreError> {
        if !ended_unix_s.is_finite() {
            return Err(self.invalid(format!("board {id} ended at {ended_unix_s} s")));
        }
        for c in cameras {
            for (what, v) in [
                ("rows", c.rows),
                ("missing rows", c.missing_rows),
                ("missing packets", c.missing_packets),
                ("damaged packets", c.damaged_packets),
            ] {
                if i64::try_from(v).is_err() {
                    return Err(self.invalid(format!(
                        "board {id}, camera {}: {v} {what} is more than 2^63 - 1",
                        c.camera
                    )));
                }
            }
        }
        if let Outcome::Inspected { verdict, pads } = outcome {
            if !LEVELS.contains(&verdict.as_str()) {
                return Err(self.invalid(format!(
                    "board {id}: verdict {verdict:?} is none of pass, warn, fail"
                )));
            }
            if i32::try_from(pads.len()).is_err() {
                return Err(self.invalid(format!(
                    "board {id}: {} pads is more than 2^31 - 1",
                    pads.len()
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
                if i32::try_from(p.pad).is_err() {
                    return Err(self.invalid(format!(
                        "board {id}, pad {} ({}): a pad index past 2^31 - 1",
                        p.pad, p.name
                    )));
                }
            }
        }
        Ok(())
    }

    /// Ends board `id` in one transaction: its state, verdict or reason, end time, the
    /// cameras' loss rows and, for an inspected board, every pad row, a `defects` row per pad
    /// whose level is `fail` or `warn`, and the pads' running aggregates of this store's line
    /// (`pad_stats`). If anything fails, nothing is written and the board stays open.
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
        self.finish_board_with_print(id, ended_unix_s, cameras, outcome, None)
    }

    /// [`Store::finish_board`] with the board's print row (`prints`) in the same transaction:
    /// its placement (an inspected board's only) and the loop's proposal after it, whose
    /// correction and change must be finite.
    pub fn finish_board_with_print(
        &mut self,
        id: i64,
        ended_unix_s: f64,
        cameras: &[CameraLoss],
        outcome: &Outcome,
        print: Option<&PrintRow>,
    ) -> Result<(), StoreError> {
        self.finish_board_with_images(id, ended_unix_s, cameras, outcome, print, &[])
    }

    /// [`Store::finish_board_with_print`] with the heights around pads of the board
    /// (`pad_images`: the line keeps those of the pads that warned or failed) in the same
    /// transaction. Images of a board not inspected, of a pad not among its pad rows, two of
    /// one pad, or of a size or place that is not one ([`dpsa_inspect::crop::MAX_SIDE`]
    /// samples a side at most) are refused.
    pub fn finish_board_with_images(
        &mut self,
        id: i64,
        ended_unix_s: f64,
        cameras: &[CameraLoss],
        outcome: &Outcome,
        print: Option<&PrintRow>,
        images: &[PadImage],
    ) -> Result<(), StoreError> {
        self.validate_finish(id, ended_unix_s, cameras, outcome)?;
        let images = self.image_values(id, outcome, images)?;
        if let Some(p) = print {
            let q = &p.proposal;
            if !q
                .correction
                .as_array()
                .iter()
                .chain(&q.change.as_array())
                .all(|v| v.is_finite())
            {
                return Err(self.invalid(format!(
                    "board {id}: a printer correction that is not finite ({:?})",
                    q.correction
                )));
            }
            if let Some(m) = &p.placement {
                if matches!(outcome, Outcome::Incomplete { .. }) {
                    return Err(self.invalid(format!(
                        "board {id}: a print placement on a board never inspected"
                    )));
                }
                if ![m.x_um, m.y_um, m.rotation_mdeg, m.stretch_ppm]
                    .iter()
                    .all(|v| v.is_finite())
                {
                    return Err(self.invalid(format!(
                        "board {id}: a print placement that is not finite ({m:?})"
                    )));
                }
            }
        }
        let beside = Beside {
            print: print.map(PrintValues::of),
            images,
        };
        on_backend!(&mut self.db, d => d.finish_board(&self.line, id, ended_unix_s, cameras, outcome, &beside))
    }

    /// The rows of board `id`'s `images`, checked against its `outcome`.
    fn image_values(
        &self,
        id: i64,
        outcome: &Outcome,
        images: &[PadImage],
    ) -> Result<Vec<ImageValues>, StoreError> {
        if images.is_empty() {
            return Ok(Vec::new());
        }
        let Outcome::Inspected { pads, .. } = outcome else {
            return Err(self.invalid(format!("board {id}: pad images of a board never inspected")));
        };
        let known: std::collections::HashSet<u32> = pads.iter().map(|p| p.pad).collect();
        let mut seen = std::collections::HashSet::new();
        images
            .iter()
            .map(|im| {
                if !known.contains(&im.pad) || !seen.insert(im.pad) {
                    return Err(self.invalid(format!(
                        "board {id}: an image of pad {}, which is not one of its pad rows or \
                         has another image",
                        im.pad
                    )));
                }
                ImageValues::of(im).map_err(|why| self.invalid(format!("board {id}: {why}")))
            })
            .collect()
    }

    /// The heights kept around pad `pad` of board `board_id` (any line's), if the line kept
    /// them (a pad that warned or failed, while its board's pad rows are kept).
    pub fn pad_image(&mut self, board_id: i64, pad: u32) -> Result<Option<PadImage>, StoreError> {
        let row = on_backend!(&mut self.db, d => d.pad_image(board_id, pad))?;
        row.map(|v| {
            v.image().map_err(|why| StoreError::Corrupt {
                store: self.location.to_string(),
                why: format!("board {board_id}: {why}"),
            })
        })
        .transpose()
    }

    /// Records an operator's `decision` on pad `pad` of this line's inspected board
    /// `board_id`, by `reviewer` (not empty) at `at_unix_s`, with an optional note; its id. Only
    /// a pad that warned or failed (its `defects` row) can be reviewed; anything else is
    /// refused ([`StoreError::Invalid`]). A pad may be reviewed again: the newest decision
    /// counts.
    pub fn add_review(
        &mut self,
        board_id: i64,
        pad: u32,
        decision: Decision,
        reviewer: &str,
        at_unix_s: f64,
        note: Option<&str>,
    ) -> Result<i64, StoreError> {
        let reviewer = reviewer.trim();
        if reviewer.is_empty() || reviewer.len() > 100 || !at_unix_s.is_finite() {
            return Err(self.invalid(format!(
                "a review by {reviewer:?} at {at_unix_s} s (a name of 1 to 100 bytes, a time)"
            )));
        }
        if note.is_some_and(|n| n.len() > 2000) {
            return Err(self.invalid("a review note longer than 2,000 bytes".to_owned()));
        }
        let note = note.map(str::trim).filter(|n| !n.is_empty());
        let line = self.line.clone();
        match on_backend!(&mut self.db, d => d.add_review(&line, board_id, pad, decision, reviewer, at_unix_s, note))?
        {
            Some(id) => Ok(id),
            None => Err(self.invalid(format!(
                "board {board_id} pad {pad}: not a call to review (no such inspected board of \
                 line {line}, or the pad neither warned nor failed, or its rows were pruned)"
            ))),
        }
    }

    /// The reviews of board `board_id` (any line's), by pad, oldest first.
    pub fn reviews(&mut self, board_id: i64) -> Result<Vec<Review>, StoreError> {
        on_backend!(&mut self.db, d => d.reviews(board_id))
    }

    /// This line's reviewed calls per package family (each pad's newest decision once), by
    /// family.
    pub fn family_reviews(&mut self) -> Result<Vec<FamilyReviews>, StoreError> {
        on_backend!(&mut self.db, d => d.family_reviews(&self.line))
    }

    /// Records a clean of the stencil `product` is printed with on this line, at
    /// `cleaned_unix_s`, said by `source` (neither empty); its id. `dpsa spc` counts the
    /// stencil's clogging from the last recorded clean.
    pub fn record_clean(
        &mut self,
        product: &str,
        cleaned_unix_s: f64,
        source: &str,
        note: Option<&str>,
    ) -> Result<i64, StoreError> {
        if !cleaned_unix_s.is_finite() || product.is_empty() || source.is_empty() {
            return Err(self.invalid(format!(
                "a stencil clean of product {product:?} at {cleaned_unix_s} s from {source:?}"
            )));
        }
        on_backend!(&mut self.db, d => d.record_clean(&self.line, product, cleaned_unix_s, source, note))
    }

    /// This line's recorded cleans of `product`'s stencil, newest first, at most `limit`.
    pub fn cleans(&mut self, product: &str, limit: usize) -> Result<Vec<StencilClean>, StoreError> {
        on_backend!(&mut self.db, d => d.cleans(&self.line, product, limit))
    }

    /// This line's print rows of `product` (the print's placement on each board and the
    /// printer correction proposed after it), newest first, at most `limit`: what the loop
    /// back to the printer resumes from, and what a chart of the printer shows.
    pub fn prints(&mut self, product: &str, limit: usize) -> Result<Vec<StoredPrint>, StoreError> {
        on_backend!(&mut self.db, d => d.prints(&self.line, product, limit))
    }

    /// After a restart: every board of this store's line still open (the service died in
    /// it) becomes `incomplete` with `reason`, ended at `now_unix_s`. Returns their run ids,
    /// oldest first. Finished boards, and the open boards of other lines (in progress there),
    /// are left alone.
    pub fn recover(&mut self, reason: &str, now_unix_s: f64) -> Result<Vec<u64>, StoreError> {
        if !now_unix_s.is_finite() {
            return Err(self.invalid(format!("recovery at {now_unix_s} s")));
        }
        on_backend!(&mut self.db, d => d.recover(&self.line, reason, now_unix_s))
    }

    /// Checks the whole store (every line's rows; see "Checks" in the module documentation).
    /// `Ok(())`, or [`StoreError::Corrupt`] with what was found. Reads every pad row: seconds
    /// for a store of gigabytes.
    pub fn check(&mut self) -> Result<(), StoreError> {
        on_backend!(&mut self.db, d => d.check(None))
    }

    /// [`Store::check`]'s rules on the rows of the store's newest `boards` boards (every
    /// line's, by id) and on the aggregates, in time bounded by those boards rather than the
    /// store's age; SQLite's page and foreign-key checks, which read the whole file, are left
    /// out. What `dpsa line run` does at start when the store is larger than
    /// [`crate::service::WHOLE_CHECK_BYTES`]; `dpsa line check` checks the whole store.
    pub fn check_newest(&mut self, boards: usize) -> Result<(), StoreError> {
        on_backend!(&mut self.db, d => d.check(Some(boards)))
    }

    /// This line's boards, newest (last begun) first, at most `limit`.
    pub fn boards(&mut self, limit: usize) -> Result<Vec<StoredBoard>, StoreError> {
        let all = Which::default();
        on_backend!(&mut self.db, d => d.boards(&self.line, &all, limit))
    }

    /// Board `id` if it is this line's.
    pub fn board(&mut self, id: i64) -> Result<Option<StoredBoard>, StoreError> {
        let one = Which {
            id: Some(id),
            ..Which::default()
        };
        Ok(on_backend!(&mut self.db, d => d.boards(&self.line, &one, 1))?.pop())
    }

    /// This line's inspected boards (of `product`, or of any), newest first, at most `limit`
    /// (through the index on line, product, state and id).
    pub fn inspected_boards(
        &mut self,
        product: Option<&str>,
        limit: usize,
    ) -> Result<Vec<StoredBoard>, StoreError> {
        let which = Which {
            product: product.map(str::to_owned),
            inspected: true,
            id: None,
        };
        on_backend!(&mut self.db, d => d.boards(&self.line, &which, limit))
    }

    /// One board's pads in pad order (none for a board not inspected, or pruned); the board
    /// may be any line's. An unknown board is [`StoreError::UnknownBoard`].
    pub fn pads(&mut self, board_id: i64) -> Result<Vec<PadRow>, StoreError> {
        on_backend!(&mut self.db, d => d.pads(board_id))
    }

    /// A pad's history on this line: `(board id, run id, level, volume_pct)` of pad index
    /// `pad` of `product` over the line's last `boards` inspected boards, newest first. Boards
    /// whose pad rows were pruned, or that had no pad of that index, give no entry.
    pub fn pad_history(
        &mut self,
        product: &str,
        pad: u32,
        boards: usize,
    ) -> Result<Vec<HistoryEntry>, StoreError> {
        on_backend!(&mut self.db, d => d.pad_history(&self.line, product, pad, boards))
    }

    /// Retention: deletes the pad and defect rows of this line's boards that ended before
    /// `before_unix_s`; the boards' rows, their cameras and the per-pad running aggregates
    /// stay. Returns the pad rows deleted. Works in transactions of 50 boards, so that the
    /// line's own writes never wait long; the freed space is reused by later boards (an
    /// SQLite file does not shrink; PostgreSQL reuses it once vacuumed, which its autovacuum
    /// does). Only the boards from the oldest one that still has pads on are looked at, so a
    /// daily prune costs the boards of the retention window, not of the store's life.
    pub fn prune_pads(&mut self, before_unix_s: f64) -> Result<u64, StoreError> {
        self.prune_pads_oldest(before_unix_s, usize::MAX)
    }

    /// [`Store::prune_pads`] of at most `boards` boards, the oldest first: what the line's
    /// keeper does after each board it stores (`[retention]`, `crate::keeper`), so that the
    /// deletes are spread over the boards instead of stalling one. Returns the pad rows
    /// deleted.
    pub fn prune_pads_oldest(
        &mut self,
        before_unix_s: f64,
        boards: usize,
    ) -> Result<u64, StoreError> {
        if before_unix_s.is_nan() {
            return Err(self.invalid("pruning before NaN s".to_owned()));
        }
        let limit = i64::try_from(boards).unwrap_or(i64::MAX);
        on_backend!(&mut self.db, d => d.prune_pads(&self.line, before_unix_s, limit))
    }

    /// SQLite: copies the WAL into the database and empties it (`PRAGMA
    /// wal_checkpoint(TRUNCATE)`). PostgreSQL: nothing (the server checkpoints itself).
    fn checkpoint(&mut self) -> Result<(), StoreError> {
        match &mut self.db {
            Db::Sqlite(d) => d.checkpoint(),
            Db::Postgres(_) => Ok(()),
        }
    }

    /// The store's size in bytes and what was counted.
    pub fn bytes(&mut self) -> Result<(u64, &'static str), StoreError> {
        match (&mut self.db, &self.location) {
            (Db::Sqlite(d), Location::Sqlite(path)) => {
                Ok((d.bytes(path)?, "the database file and its WAL"))
            }
            (Db::Postgres(d), _) => Ok((
                d.bytes()?,
                "the tables with their indexes and TOAST (pg_total_relation_size)",
            )),
            (Db::Sqlite(_), Location::Postgres(_)) => {
                Err(self.invalid("an SQLite connection to a PostgreSQL URL".to_owned()))
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A value of a row read by hand ([`Store::rows`]).
    #[derive(Clone, Debug, PartialEq)]
    pub(crate) enum Raw {
        Null,
        Int(i64),
        Real(f64),
        Text(String),
    }

    impl Raw {
        fn int(&self) -> i64 {
            match self {
                Raw::Int(v) => *v,
                other => panic!("{other:?} is no integer"),
            }
        }
        fn real(&self) -> f64 {
            match self {
                Raw::Real(v) => *v,
                Raw::Int(v) => *v as f64,
                other => panic!("{other:?} is no number"),
            }
        }
        fn text(&self) -> Option<&str> {
            match self {
                Raw::Text(t) => Some(t),
                Raw::Null => None,
                other => panic!("{other:?} is no text"),
            }
        }
    }

    impl Store {
        /// Runs SQL by hand.
        fn exec(&mut self, sql: &str) -> Result<(), StoreError> {
            on_backend!(&mut self.db, d => d.exec_raw(sql))
        }

        /// The rows of SQL by hand.
        fn rows(&mut self, sql: &str) -> Vec<Vec<Raw>> {
            on_backend!(&mut self.db, d => d.query_raw(sql))
                .unwrap_or_else(|e| panic!("{sql}: {e:#?}"))
        }

        /// The one integer SQL by hand gives.
        fn int(&mut self, sql: &str) -> i64 {
            self.rows(sql)[0][0].int()
        }

        fn dialect(&self) -> schema::Dialect {
            match self.db {
                Db::Sqlite(_) => schema::Dialect::Sqlite,
                Db::Postgres(_) => schema::Dialect::Postgres,
            }
        }
    }

    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    pub(crate) enum Backend {
        Sqlite,
        Postgres,
    }

    /// Where a test's store is, and what keeps it (a temporary directory).
    pub(crate) struct Place {
        pub(crate) location: Location,
        _dir: Option<tempfile::TempDir>,
    }

    /// A new, empty place for a store: a file in a fresh directory (in a subdirectory not made
    /// yet), or a new database of the test server.
    pub(crate) fn place(b: Backend) -> Place {
        match b {
            Backend::Sqlite => {
                let dir = tempfile::tempdir().unwrap();
                Place {
                    location: Location::Sqlite(dir.path().join("sub").join("line.sqlite")),
                    _dir: Some(dir),
                }
            }
            Backend::Postgres => Place {
                location: pg_test_server::database(),
                _dir: None,
            },
        }
    }

    /// A fresh store of line `line-1`.
    fn fresh(b: Backend) -> (Place, Store) {
        let p = place(b);
        let store = Store::open(&p.location, DEFAULT_LINE).unwrap();
        (p, store)
    }

    /// Runs test function `name(Backend)` as two tests, `name::sqlite` and `name::postgres`.
    macro_rules! both {
        ($($name:ident),* $(,)?) => {$(
            mod $name {
                #[test]
                fn sqlite() {
                    super::$name(super::Backend::Sqlite)
                }
                #[test]
                fn postgres() {
                    super::$name(super::Backend::Postgres)
                }
            }
        )*};
    }

    both!(
        pad_images_and_reviews_round_trip_and_only_calls_are_reviewed,
        round_trip_of_a_board_with_pads_nan_becomes_none,
        state_machine_refuses_what_would_rewrite_a_board,
        recover_turns_open_boards_incomplete_and_leaves_finished_ones,
        check_finds_rows_written_past_the_constraints,
        pad_history_is_newest_first_and_only_inspected_boards,
        inspected_boards_are_one_products_newest_first,
        prune_deletes_pads_and_keeps_boards_and_pad_stats,
        prune_oldest_takes_at_most_the_boards_asked_oldest_first,
        check_newest_reads_the_newest_boards_rows_and_the_aggregates,
        a_newer_schema_is_refused,
        opening_a_store_again_changes_nothing,
        pad_stats_equal_sums_recomputed_from_the_pad_rows,
        two_lines_share_one_store,
        a_version_1_store_migrates_to_version_2,
        programs_opening_a_new_store_at_once_migrate_it_once,
        the_benchmark_runs_small,
        print_rows_round_trip_and_are_the_lines_newest_first,
        stencil_cleans_are_the_lines_and_products_newest_first,
        a_reader_reads_and_never_writes_nor_migrates,
    );

    /// A read-only store reads what was written, refuses every write (the database says no),
    /// and refuses a store of an older version rather than migrate it; no file is made for a
    /// store that is not there.
    fn a_reader_reads_and_never_writes_nor_migrates(b: Backend) {
        let (p, mut store) = fresh(b);
        let id = inspect(&mut store, 0x77, "mini", 3, 100.0);
        let mut r = Store::open_read_only(&p.location, DEFAULT_LINE).unwrap();
        assert_eq!(r.boards(10).unwrap()[0].id, id);
        assert_eq!(r.pads(id).unwrap().len(), 3);
        assert!(r.begin_board(&start(0x78, "mini", 1.0)).is_err());
        assert!(r.record_clean("mini", 1.0, "operator", None).is_err());
        assert_eq!(store.boards(10).unwrap().len(), 1);
        // An older store: refused, left at its version.
        let old = place(b);
        drop(Store::open_with(&old.location, DEFAULT_LINE, &MIGRATIONS[..2]).unwrap());
        let e = Store::open_read_only(&old.location, DEFAULT_LINE).unwrap_err();
        assert!(e.to_string().contains("does not migrate"), "{e}");
        let mut again = Store::open_with(&old.location, DEFAULT_LINE, &MIGRATIONS[..2]).unwrap();
        assert_eq!(again.schema_version().unwrap(), 2);
        if let Location::Sqlite(path) = &p.location {
            let none = path.with_file_name("none.sqlite");
            assert!(Store::open_read_only(&Location::Sqlite(none.clone()), DEFAULT_LINE).is_err());
            assert!(!none.exists());
        }
    }

    /// Recorded cleans come back newest first, of this line and product only; a clean without
    /// a time, a product or a source is refused.
    fn stencil_cleans_are_the_lines_and_products_newest_first(b: Backend) {
        let (p, mut store) = fresh(b);
        let mut other = Store::open(&p.location, "line-2").unwrap();
        let a = store
            .record_clean("mini", 100.0, "operator", Some("wiped by hand"))
            .unwrap();
        let c = store
            .record_clean("mini", 300.0, "printer DEK-1", None)
            .unwrap();
        store.record_clean("maxi", 200.0, "operator", None).unwrap();
        other.record_clean("mini", 400.0, "operator", None).unwrap();
        let got = store.cleans("mini", 10).unwrap();
        assert_eq!(got.iter().map(|c| c.id).collect::<Vec<_>>(), [c, a]);
        assert_eq!(got[0].source, "printer DEK-1");
        assert_eq!(got[1].note.as_deref(), Some("wiped by hand"));
        assert_eq!(got[1].cleaned_unix_s, 100.0);
        assert_eq!(store.cleans("mini", 1).unwrap().len(), 1);
        assert_eq!(other.cleans("mini", 10).unwrap()[0].cleaned_unix_s, 400.0);
        for (product, t, source) in [
            ("mini", f64::NAN, "operator"),
            ("", 1.0, "operator"),
            ("mini", 1.0, ""),
        ] {
            assert!(store.record_clean(product, t, source, None).is_err());
        }
        assert_eq!(store.cleans("mini", 10).unwrap().len(), 2);
        store.check().unwrap();
    }

    /// A print row: board `k`'s placement (none for odd `k`) and a proposal.
    fn print_row(k: u32) -> PrintRow {
        let f = f64::from(k);
        let placement = (k % 2 == 0).then(|| PrintOffset {
            x_um: 10.0 + f,
            y_um: -3.25 * f,
            rotation_mdeg: 0.5,
            stretch_ppm: -12.0,
            uncertainty: [0.3, 0.31, 0.02, f64::NAN],
            centre_mm: [40.0, 30.0],
            pads: 190 + k as usize,
            outliers: 3,
            scale_um: 4.5,
        });
        let c = |x: f64| Correction {
            x_um: x,
            y_um: -x,
            rotation_mdeg: x / 10.0,
        };
        PrintRow {
            placement,
            proposal: Proposal {
                correction: c(f),
                change: c(1.0),
                estimate: if k == 0 { c(f64::NAN) } else { c(f + 0.5) },
                estimate_uncertainty: if k == 0 { c(f64::NAN) } else { c(0.2) },
                held: [k % 2 == 0, false, true],
                limited: [false, k == 3, false],
                reason: format!("board {k}"),
            },
        }
    }

    /// Print rows come back as written (NaN as NULL as NaN), newest first, of this line and
    /// product only; a placement on a board never inspected and a correction that is not
    /// finite are refused, the board left open.
    fn print_rows_round_trip_and_are_the_lines_newest_first(b: Backend) {
        let (p, mut store) = fresh(b);
        let mut other = Store::open(&p.location, "line-2").unwrap();
        let same = |a: &PrintRow, b: &PrintRow| {
            // NaN as NULL as NaN; -0 may come back +0 (SQLite).
            let bits = |v: f64| (!v.is_nan()).then_some(v);
            let pa = |r: &PrintRow| {
                r.placement.map(|m| {
                    (
                        [m.x_um, m.y_um, m.rotation_mdeg, m.stretch_ppm, m.scale_um].map(bits),
                        m.uncertainty.map(bits),
                        m.centre_mm.map(bits),
                        m.pads,
                        m.outliers,
                    )
                })
            };
            let q = |r: &PrintRow| {
                let p = &r.proposal;
                (
                    [
                        &p.correction,
                        &p.change,
                        &p.estimate,
                        &p.estimate_uncertainty,
                    ]
                    .map(|c| c.as_array().map(bits)),
                    p.held,
                    p.limited,
                    p.reason.clone(),
                )
            };
            pa(a) == pa(b) && q(a) == q(b)
        };
        let mut ids = Vec::new();
        for k in 0..5u32 {
            let run = 0x100 + u64::from(k);
            let id = store
                .begin_board(&start(run, "mini", f64::from(k)))
                .unwrap();
            let outcome = if k == 1 {
                Outcome::Incomplete {
                    reason: "camera 2 silent".into(),
                }
            } else {
                Outcome::Inspected {
                    verdict: "pass".into(),
                    pads: vec![pad(0, "pass", Some(100.0))],
                }
            };
            store
                .finish_board_with_print(
                    id,
                    f64::from(k) + 0.5,
                    &cams(),
                    &outcome,
                    Some(&print_row(k)),
                )
                .unwrap();
            ids.push(id);
        }
        // Another product and another line's board of the same product.
        let id = store.begin_board(&start(0x200, "maxi", 9.0)).unwrap();
        let ok = Outcome::Inspected {
            verdict: "pass".into(),
            pads: vec![pad(0, "pass", Some(100.0))],
        };
        store
            .finish_board_with_print(id, 9.5, &cams(), &ok, Some(&print_row(4)))
            .unwrap();
        let id = other.begin_board(&start(0x300, "mini", 9.0)).unwrap();
        other
            .finish_board_with_print(id, 9.5, &cams(), &ok, Some(&print_row(4)))
            .unwrap();

        let rows = store.prints("mini", 10).unwrap();
        assert_eq!(
            rows.iter().map(|r| r.run_id).collect::<Vec<_>>(),
            [0x104, 0x103, 0x102, 0x101, 0x100]
        );
        for (r, k) in rows.iter().zip((0..5u32).rev()) {
            assert_eq!(r.board_id, ids[k as usize]);
            assert!(same(&r.print, &print_row(k)), "board {k}: {:?}", r.print);
        }
        assert_eq!(store.prints("mini", 2).unwrap().len(), 2);
        assert_eq!(other.prints("mini", 10).unwrap().len(), 1);
        assert!(store.prints("none", 10).unwrap().is_empty());
        store.check().unwrap();

        // Refused, and nothing of the board written.
        let id = store.begin_board(&start(0x105, "mini", 20.0)).unwrap();
        let incomplete = Outcome::Incomplete {
            reason: "cut".into(),
        };
        let e = store
            .finish_board_with_print(id, 20.5, &cams(), &incomplete, Some(&print_row(0)))
            .unwrap_err();
        assert!(e.to_string().contains("never inspected"), "{e}");
        let mut bad = print_row(1);
        bad.proposal.correction.x_um = f64::INFINITY;
        let e = store
            .finish_board_with_print(id, 20.5, &cams(), &ok, Some(&bad))
            .unwrap_err();
        assert!(e.to_string().contains("not finite"), "{e}");
        assert_eq!(store.boards(1).unwrap()[0].state, "open");
        assert_eq!(store.prints("mini", 10).unwrap().len(), 5);
    }

    /// A crop of `nx x ny` samples with an invalid one and one beyond the stored range.
    fn crop(nx: usize, ny: usize) -> dpsa_inspect::crop::PadCrop {
        let mut heights_um: Vec<f32> = (0..nx * ny).map(|k| k as f32 * 0.37 - 3.0).collect();
        if let Some(h) = heights_um.get_mut(1..3) {
            h.copy_from_slice(&[f32::NAN, 1e6]);
        }
        dpsa_inspect::crop::PadCrop {
            x0_mm: 10.25,
            y0_mm: -0.5,
            pitch_mm: 0.028,
            nx,
            ny,
            heights_um,
            outline: dpsa_gerber::pads::Outline::Circle {
                centre: [10.5, -0.2],
                diameter: 0.3,
            },
        }
    }

    /// The images of a board come back as written (to the 0.1 um step; NaN and out of range
    /// invalid); images of a board never inspected or of an unknown or repeated pad are refused;
    /// only a pad that warned or failed on this line's inspected board is reviewed; the
    /// family's rates count each pad's newest decision; pruning takes the images and keeps the
    /// reviews; the store passes its checks throughout.
    fn pad_images_and_reviews_round_trip_and_only_calls_are_reviewed(b: Backend) {
        let (p, mut store) = fresh(b);
        let mut other = Store::open(&p.location, "line-2").unwrap();
        let ok = Outcome::Inspected {
            verdict: "fail".into(),
            pads: vec![
                pad(0, "pass", Some(100.0)),
                pad(1, "fail", Some(20.0)),
                pad(2, "warn", Some(140.0)),
            ],
        };
        let image = |pad: u32, family: Option<&str>, c: dpsa_inspect::crop::PadCrop| PadImage {
            pad,
            family: family.map(str::to_owned),
            crop: c,
        };
        let images = [
            image(1, Some("bga"), crop(7, 5)),
            image(2, None, crop(3, 9)),
        ];
        let id = store.begin_board(&start(0x10, "mini", 1.0)).unwrap();
        // Refused: a board never inspected, an unknown pad, one pad twice, a bad size.
        let incomplete = Outcome::Incomplete {
            reason: "cut".into(),
        };
        for (outcome, imgs) in [
            (&incomplete, vec![images[0].clone()]),
            (&ok, vec![image(7, None, crop(2, 2))]),
            (&ok, vec![images[0].clone(), images[0].clone()]),
            (&ok, vec![image(1, None, crop(0, 2))]),
            (&ok, vec![image(1, None, crop(300, 2))]),
        ] {
            let e = store
                .finish_board_with_images(id, 2.0, &cams(), outcome, None, &imgs)
                .unwrap_err();
            assert!(matches!(e, StoreError::Invalid { .. }), "{e}");
        }
        assert_eq!(store.boards(1).unwrap()[0].state, "open");
        store
            .finish_board_with_images(id, 2.0, &cams(), &ok, None, &images)
            .unwrap();
        for want in &images {
            let got = store.pad_image(id, want.pad).unwrap().expect("stored");
            assert_eq!(got.family, want.family);
            let (a, w) = (&got.crop, &want.crop);
            assert_eq!(
                (a.nx, a.ny, a.x0_mm, a.y0_mm, a.pitch_mm),
                (w.nx, w.ny, w.x0_mm, w.y0_mm, w.pitch_mm)
            );
            assert_eq!(a.outline, w.outline);
            for (k, (x, y)) in a.heights_um.iter().zip(&w.heights_um).enumerate() {
                if k == 1 || k == 2 {
                    assert!(x.is_nan());
                } else {
                    assert!((x - y).abs() <= 0.05 + 1e-4, "{k}: {x} {y}");
                }
            }
        }
        assert!(store.pad_image(id, 0).unwrap().is_none());
        store.check().unwrap();

        // Reviews: calls only, this line's only.
        let r1 = store
            .add_review(
                id,
                1,
                Decision::FalseCall,
                "ana",
                5.0,
                Some("smear on the mask"),
            )
            .unwrap();
        store
            .add_review(id, 2, Decision::Confirmed, " bo ", 6.0, Some("  "))
            .unwrap();
        let r3 = store
            .add_review(id, 1, Decision::Confirmed, "carl", 7.0, None)
            .unwrap();
        assert!(r3 > r1);
        for (pad, who, t) in [
            (0, "ana", 8.0),
            (9, "ana", 8.0),
            (1, "", 8.0),
            (1, "ana", f64::NAN),
        ] {
            let e = store
                .add_review(id, pad, Decision::Confirmed, who, t, None)
                .unwrap_err();
            assert!(matches!(e, StoreError::Invalid { .. }), "{e}");
        }
        assert!(other
            .add_review(id, 1, Decision::Confirmed, "ana", 8.0, None)
            .is_err());
        let got = store.reviews(id).unwrap();
        assert_eq!(
            got.iter()
                .map(|r| (r.pad, r.decision, r.reviewer.as_str(), r.family.as_deref()))
                .collect::<Vec<_>>(),
            [
                (1, Decision::FalseCall, "ana", Some("bga")),
                (1, Decision::Confirmed, "carl", Some("bga")),
                (2, Decision::Confirmed, "bo", None),
            ]
        );
        assert_eq!(got[0].note.as_deref(), Some("smear on the mask"));
        assert_eq!(got[2].note, None);
        // The newest decision counts: pad 1 is confirmed now.
        let f = store.family_reviews().unwrap();
        assert_eq!(f.len(), 2);
        assert_eq!(
            (f[0].family.as_deref(), f[0].confirmed, f[0].false_calls),
            (None, 1, 0)
        );
        assert_eq!(
            (f[1].family.as_deref(), f[1].confirmed, f[1].false_calls),
            (Some("bga"), 1, 0)
        );
        store
            .add_review(id, 1, Decision::FalseCall, "dora", 9.0, None)
            .unwrap();
        assert_eq!(
            store.family_reviews().unwrap()[1].false_call_rate(),
            Some(1.0)
        );
        assert!(other.family_reviews().unwrap().is_empty());
        store.check().unwrap();

        // Retention takes the images with the pad rows; the reviews and their families stay.
        store.prune_pads(100.0).unwrap();
        assert!(store.pad_image(id, 1).unwrap().is_none());
        assert_eq!(store.reviews(id).unwrap().len(), 4);
        assert_eq!(store.family_reviews().unwrap()[1].false_calls, 1);
        store.check().unwrap();
    }

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

    /// The store's name in its error sentences.
    fn named(b: Backend) -> &'static str {
        match b {
            Backend::Sqlite => "line.sqlite",
            Backend::Postgres => "postgres://postgres@127.0.0.1:",
        }
    }

    fn round_trip_of_a_board_with_pads_nan_becomes_none(b: Backend) {
        let (_p, mut store) = fresh(b);
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
        let nan = match b {
            Backend::Sqlite => "SELECT count(*) FROM pads WHERE volume_pct != volume_pct",
            Backend::Postgres => {
                "SELECT count(*) FROM pads WHERE 'NaN' IN (volume_pct, volume_um3, height_um)"
            }
        };
        assert_eq!(store.int(nan), 0);
        let board = &store.boards(10).unwrap()[0];
        assert_eq!(
            board,
            &StoredBoard {
                id,
                run_id: 0xdead_beef_0000_0001,
                line: DEFAULT_LINE.to_owned(),
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
        assert_eq!(
            store.rows("SELECT run_id, line FROM boards"),
            [[
                Raw::Text("deadbeef00000001".into()),
                Raw::Text("line-1".into())
            ]]
        );
        let defects = store.rows("SELECT pad, level, class FROM defects ORDER BY pad");
        let t = |s: &str| Raw::Text(s.to_owned());
        assert_eq!(
            defects,
            [
                [Raw::Int(1), t("warn"), t("insufficient")],
                [Raw::Int(2), t("fail"), t("not measurable")],
                [Raw::Int(3), t("fail"), t("not measurable")],
            ]
        );
        store.check().unwrap();
    }

    fn state_machine_refuses_what_would_rewrite_a_board(b: Backend) {
        let (_p, mut store) = fresh(b);
        let id = store.begin_board(&start(7, "p", 1.0)).unwrap();
        // A run id is stored once.
        let dup = store.begin_board(&start(7, "p", 2.0)).unwrap_err();
        assert!(
            matches!(dup, StoreError::Duplicate { run_id: 7, .. }),
            "{dup}"
        );
        assert!(dup.to_string().contains(named(b)), "{dup}");
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
        let huge_pad = Outcome::Inspected {
            verdict: "pass".to_owned(),
            pads: vec![pad(u32::MAX, "pass", Some(1.0))],
        };
        let e = store.finish_board(id, 3.0, &[], &huge_pad).unwrap_err();
        assert!(matches!(e, StoreError::Invalid { .. }), "{e}");
        // A failure half way (two pads of one index) rolls the whole board back.
        let twice = Outcome::Inspected {
            verdict: "pass".to_owned(),
            pads: vec![pad(0, "pass", Some(1.0)), pad(0, "pass", Some(2.0))],
        };
        let e = store.finish_board(id, 3.0, &cams(), &twice).unwrap_err();
        assert!(
            matches!(e, StoreError::Sqlite { .. } | StoreError::Postgres { .. }),
            "{e}"
        );
        assert_eq!(store.boards(1).unwrap()[0].state, "open");
        assert_eq!(store.boards(1).unwrap()[0].cameras, []);
        assert_eq!(store.pads(id).unwrap(), []);
        // Incomplete: a reason, never a verdict nor pads.
        let why = Outcome::Incomplete {
            reason: "camera 1 silent".to_owned(),
        };
        store.finish_board(id, 3.0, &cams(), &why).unwrap();
        let board = store.boards(1).unwrap()[0].clone();
        assert_eq!(board.state, "incomplete");
        assert_eq!(board.verdict, None);
        assert_eq!(board.incomplete_reason.as_deref(), Some("camera 1 silent"));
        assert_eq!(board.pads, 0);
        assert_eq!(board.cameras, cams());
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
        assert_eq!(store.boards(1).unwrap()[0], board);
        let e = store.finish_board(id + 100, 4.0, &[], &why).unwrap_err();
        assert!(matches!(e, StoreError::UnknownBoard { .. }), "{e}");
        // The schema's CHECKs hold even against SQL written by hand.
        for sql in [
            "UPDATE boards SET verdict = 'fail'",
            "UPDATE boards SET incomplete_reason = NULL",
            "UPDATE boards SET state = 'open'",
            "UPDATE boards SET state = 'inspected'",
            "UPDATE boards SET line = ''",
            "UPDATE boards SET run_id = 'ABCDEF0000000000'",
        ] {
            assert!(store.exec(sql).is_err(), "{sql} was accepted");
        }
        store.check().unwrap();
    }

    fn recover_turns_open_boards_incomplete_and_leaves_finished_ones(b: Backend) {
        let p = place(b);
        let (done, incomplete);
        {
            let mut store = Store::open(&p.location, DEFAULT_LINE).unwrap();
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
        let before = Store::open(&p.location, DEFAULT_LINE)
            .unwrap()
            .boards(10)
            .unwrap();
        let mut store = Store::open(&p.location, DEFAULT_LINE).unwrap();
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
        store.check().unwrap();
    }

    #[test]
    fn check_passes_on_a_fresh_sqlite_store_and_fails_on_garbage() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("line.sqlite");
        let location = Location::Sqlite(path.clone());
        {
            let mut store = Store::open(&location, DEFAULT_LINE).unwrap();
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
        match Store::open(&location, DEFAULT_LINE) {
            Err(e) => assert!(e.to_string().contains("line.sqlite"), "{e}"),
            Ok(mut store) => {
                let e = store.check().unwrap_err();
                assert!(matches!(e, StoreError::Corrupt { .. }), "{e}");
                assert!(e.to_string().contains("line.sqlite"), "{e}");
            }
        }
        // A file that is not a database at all.
        let junk = dir.path().join("junk.sqlite");
        std::fs::write(&junk, vec![0x42u8; 10_000]).unwrap();
        let e = Store::open(&Location::Sqlite(junk), DEFAULT_LINE).unwrap_err();
        assert!(matches!(e, StoreError::Corrupt { .. }), "{e}");
    }

    /// Rows written by hand past the constraints (switched off as each database allows) are
    /// found by `check`, which names what is wrong; undone, the store checks out again.
    fn check_finds_rows_written_past_the_constraints(b: Backend) {
        let (_p, mut store) = fresh(b);
        let id = inspect(&mut store, 1, "p", 5, 100.0);
        let flagged = store.begin_board(&start(2, "p", 2.0)).unwrap();
        store
            .finish_board(
                flagged,
                2.5,
                &cams(),
                &Outcome::Inspected {
                    verdict: "fail".to_owned(),
                    pads: vec![pad(0, "pass", Some(100.0)), pad(1, "fail", Some(20.0))],
                },
            )
            .unwrap();
        store.begin_board(&start(3, "p", 3.0)).unwrap();
        store.check().unwrap();
        let (off, on) = match b {
            Backend::Sqlite => ("PRAGMA foreign_keys = OFF;", "PRAGMA foreign_keys = ON;"),
            Backend::Postgres => (
                "SET session_replication_role = replica;",
                "RESET session_replication_role;",
            ),
        };
        let cases = [
            (
                format!(
                    "{off} INSERT INTO pads (board_id, pad, name, level, coverage) \
                     VALUES (999, 0, 'x', 'pass', 1); {on}"
                ),
                "DELETE FROM pads WHERE board_id = 999".to_owned(),
                "refer to missing rows|of a board not in the store",
            ),
            (
                format!("UPDATE boards SET pads = 6 WHERE id = {id}"),
                format!("UPDATE boards SET pads = 5 WHERE id = {id}"),
                "not as many as its pad count",
            ),
            (
                format!("DELETE FROM defects WHERE board_id = {flagged}"),
                format!(
                    "INSERT INTO defects (board_id, pad, level, class) \
                     VALUES ({flagged}, 1, 'fail', 'insufficient')"
                ),
                "one defect row per pad",
            ),
            (
                format!("UPDATE pads SET level = 'warn' WHERE board_id = {flagged} AND pad = 1"),
                format!("UPDATE pads SET level = 'fail' WHERE board_id = {flagged} AND pad = 1"),
                "defect rows without the pad row",
            ),
            (
                "UPDATE pad_stats SET fails = boards + 1 WHERE pad = 0".to_owned(),
                "UPDATE pad_stats SET fails = 0 WHERE pad = 0".to_owned(),
                "fails + warns <= boards",
            ),
        ];
        for (damage, undo, said) in &cases {
            store.exec(damage).unwrap();
            let e = store.check().unwrap_err();
            assert!(matches!(e, StoreError::Corrupt { .. }), "{e}");
            let text = e.to_string();
            assert!(
                said.split('|').any(|s| text.contains(s)) && text.contains(named(b)),
                "{damage}: {text}"
            );
            store.exec(undo).unwrap();
            store.check().unwrap();
        }
        if b == Backend::Postgres {
            for (damage, undo, said) in [
                (
                    "UPDATE pads SET volume_pct = 'NaN' WHERE pad = 0",
                    "UPDATE pads SET volume_pct = 100 WHERE pad = 0",
                    "NaN",
                ),
                (
                    "ALTER TABLE pads DISABLE TRIGGER ALL",
                    "ALTER TABLE pads ENABLE TRIGGER ALL",
                    "2 triggers switched off (foreign keys not kept)",
                ),
                (
                    "ALTER TABLE pads ADD CONSTRAINT no_r0 CHECK (name <> 'R0-1') NOT VALID",
                    "ALTER TABLE pads DROP CONSTRAINT no_r0",
                    "constraints not validated",
                ),
                (
                    "DROP TRIGGER boards_id_fixed ON boards",
                    "CREATE TRIGGER boards_id_fixed BEFORE UPDATE OF id ON boards FOR EACH ROW \
                     WHEN (OLD.id IS DISTINCT FROM NEW.id) EXECUTE FUNCTION boards_id_fixed()",
                    "of the 4 triggers that keep pads' foreign key missing",
                ),
            ] {
                store.exec(damage).unwrap();
                let e = store.check().unwrap_err().to_string();
                assert!(e.contains(said), "{damage}: {e}");
                store.exec(undo).unwrap();
                store.check().unwrap();
            }
        }
    }

    fn pad_history_is_newest_first_and_only_inspected_boards(b: Backend) {
        let (_p, mut store) = fresh(b);
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
        assert_eq!(store.pad_history("a", u32::MAX, 10).unwrap(), []);
        assert_eq!(store.pad_history("b", 0, 10).unwrap()[0].0, b1);
    }

    fn inspected_boards_are_one_products_newest_first(b: Backend) {
        let (_p, mut store) = fresh(b);
        let a1 = inspect(&mut store, 1, "a", 3, 100.0);
        let b1 = inspect(&mut store, 2, "b", 3, 50.0);
        let _open = store.begin_board(&start(3, "a", 3.0)).unwrap();
        let a2 = inspect(&mut store, 4, "a", 3, 110.0);
        let gone = store.begin_board(&start(5, "a", 5.0)).unwrap();
        store
            .finish_board(
                gone,
                5.5,
                &[],
                &Outcome::Incomplete {
                    reason: "cut".to_owned(),
                },
            )
            .unwrap();
        let ids = |v: Vec<StoredBoard>| v.into_iter().map(|x| x.id).collect::<Vec<_>>();
        assert_eq!(
            ids(store.inspected_boards(Some("a"), 10).unwrap()),
            [a2, a1]
        );
        assert_eq!(ids(store.inspected_boards(Some("a"), 1).unwrap()), [a2]);
        assert_eq!(ids(store.inspected_boards(None, 10).unwrap()), [a2, b1, a1]);
        assert_eq!(
            ids(store.inspected_boards(Some("c"), 10).unwrap()),
            Vec::<i64>::new()
        );
        // `boards` still lists every state.
        assert_eq!(store.boards(10).unwrap().len(), 5);
    }

    /// `(pad, boards, sum_volume_pct, fails)` of every aggregate row, by line and pad.
    fn stats(s: &mut Store) -> Vec<(String, i64, i64, f64, i64)> {
        s.rows("SELECT line, pad, boards, sum_volume_pct, fails FROM pad_stats ORDER BY line, pad")
            .iter()
            .map(|r| {
                (
                    r[0].text().unwrap_or("").to_owned(),
                    r[1].int(),
                    r[2].int(),
                    r[3].real(),
                    r[4].int(),
                )
            })
            .collect()
    }

    fn prune_deletes_pads_and_keeps_boards_and_pad_stats(b: Backend) {
        let (_p, mut store) = fresh(b);
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
        let before = stats(&mut store);
        // Boards 1 and 2 ended at 1.5 and 2.5; board 10 at 10.5.
        assert_eq!(store.prune_pads(5.0).unwrap(), 40);
        assert_eq!(store.pads(old).unwrap(), []);
        assert_eq!(store.pads(id).unwrap(), []);
        assert_eq!(store.pads(new).unwrap().len(), 20);
        assert_eq!(store.int("SELECT count(*) FROM defects"), 0);
        assert_eq!(store.boards(10).unwrap(), boards);
        assert_eq!(stats(&mut store), before);
        assert_eq!(
            before[3],
            ("line-1".to_owned(), 3, 3, 103.0 + 20.0 + 103.0, 1)
        );
        assert_eq!(store.pad_history("p", 0, 10).unwrap().len(), 1);
        assert_eq!(store.prune_pads(5.0).unwrap(), 0);
        store.check().unwrap();
    }

    fn prune_oldest_takes_at_most_the_boards_asked_oldest_first(b: Backend) {
        let (_p, mut store) = fresh(b);
        // Boards 1, 2, 3 and 5 inspected (ended at run id + 0.5), board 4 incomplete (no
        // pads: never counted against the limit).
        let ids: Vec<i64> = [1, 2, 3]
            .iter()
            .map(|&r| inspect(&mut store, r, "p", 7, 100.0))
            .collect();
        let four = store.begin_board(&start(4, "p", 4.0)).unwrap();
        let gone = Outcome::Incomplete {
            reason: "camera 1 silent".to_owned(),
        };
        store.finish_board(four, 4.5, &cams(), &gone).unwrap();
        let five = inspect(&mut store, 5, "p", 7, 100.0);
        let stats_before = stats(&mut store);
        let left = |s: &mut Store| -> Vec<usize> {
            ids.iter()
                .chain([&five])
                .map(|&id| s.pads(id).unwrap().len())
                .collect()
        };
        assert_eq!(store.prune_pads_oldest(5.0, 0).unwrap(), 0);
        assert_eq!(left(&mut store), [7, 7, 7, 7]);
        assert_eq!(store.prune_pads_oldest(5.0, 2).unwrap(), 14);
        assert_eq!(left(&mut store), [0, 0, 7, 7]);
        // Only board 3 is before 5 s and still has pads; board 5 ended at 5.5 s.
        assert_eq!(store.prune_pads_oldest(5.0, 2).unwrap(), 7);
        assert_eq!(left(&mut store), [0, 0, 0, 7]);
        assert_eq!(store.prune_pads_oldest(5.0, 2).unwrap(), 0);
        assert_eq!(store.prune_pads_oldest(6.0, 2).unwrap(), 7);
        assert_eq!(left(&mut store), [0, 0, 0, 0]);
        assert_eq!(store.boards(10).unwrap().len(), 5);
        assert_eq!(stats(&mut store), stats_before);
        assert!(store.prune_pads_oldest(f64::NAN, 2).is_err());
        store.check().unwrap();
    }

    fn check_newest_reads_the_newest_boards_rows_and_the_aggregates(b: Backend) {
        let (_p, mut store) = fresh(b);
        let ids: Vec<i64> = (1..=3)
            .map(|r| inspect(&mut store, r, "p", 5, 100.0))
            .collect();
        store.check_newest(1).unwrap();
        // A row of the oldest board damaged: found by the whole check and by the newest
        // three, not by the newest two.
        for (damage, undo) in [
            (
                format!("UPDATE boards SET pads = 6 WHERE id = {}", ids[0]),
                format!("UPDATE boards SET pads = 5 WHERE id = {}", ids[0]),
            ),
            (
                // A warning without its defect row.
                format!(
                    "UPDATE pads SET level = 'warn' WHERE board_id = {} AND pad = 0",
                    ids[0]
                ),
                format!(
                    "UPDATE pads SET level = 'pass' WHERE board_id = {} AND pad = 0",
                    ids[0]
                ),
            ),
            (
                format!(
                    "INSERT INTO defects (board_id, pad, level, class) \
                     VALUES ({}, 1, 'fail', 'insufficient')",
                    ids[0]
                ),
                format!("DELETE FROM defects WHERE board_id = {}", ids[0]),
            ),
        ] {
            store.exec(&damage).unwrap();
            assert!(store.check().is_err(), "{damage}");
            assert!(store.check_newest(3).is_err(), "{damage}");
            store.check_newest(2).unwrap();
            store.exec(&undo).unwrap();
        }
        // The newest board's rows and the aggregates are always read.
        for (damage, undo) in [
            (
                // A warning without its defect row.
                format!(
                    "UPDATE pads SET level = 'warn' WHERE board_id = {} AND pad = 0",
                    ids[2]
                ),
                format!(
                    "UPDATE pads SET level = 'pass' WHERE board_id = {} AND pad = 0",
                    ids[2]
                ),
            ),
            (
                "UPDATE pad_stats SET fails = boards + 1 WHERE pad = 0".to_owned(),
                "UPDATE pad_stats SET fails = 0 WHERE pad = 0".to_owned(),
            ),
        ] {
            store.exec(&damage).unwrap();
            let e = store.check_newest(1).unwrap_err();
            assert!(matches!(e, StoreError::Corrupt { .. }), "{e}");
            store.exec(&undo).unwrap();
        }
        store.check().unwrap();
        store.check_newest(usize::MAX).unwrap();
    }

    /// Sets the store's schema version by hand.
    fn set_version(store: &mut Store, v: u32) {
        let sql = match store.dialect() {
            schema::Dialect::Sqlite => format!("PRAGMA user_version = {v}"),
            schema::Dialect::Postgres => format!("UPDATE schema_version SET version = {v}"),
        };
        store.exec(&sql).unwrap();
    }

    fn a_newer_schema_is_refused(b: Backend) {
        let p = place(b);
        set_version(&mut Store::open(&p.location, DEFAULT_LINE).unwrap(), 99);
        let e = Store::open(&p.location, DEFAULT_LINE).unwrap_err();
        assert!(
            matches!(e, StoreError::NewerSchema { found: 99, known, .. } if known == SCHEMA_VERSION),
            "{e}"
        );
        let text = e.to_string();
        assert!(text.contains(named(b)) && text.contains("99"), "{text}");
        // Left untouched.
        let left = match b {
            Backend::Sqlite => {
                let Location::Sqlite(path) = &p.location else {
                    unreachable!()
                };
                rusqlite::Connection::open(path)
                    .unwrap()
                    .pragma_query_value(None, "user_version", |r| r.get::<_, i64>(0))
                    .unwrap()
            }
            Backend::Postgres => {
                let Location::Postgres(url) = &p.location else {
                    unreachable!()
                };
                let mut c = url.config().unwrap().connect(postgres::NoTls).unwrap();
                i64::from(
                    c.query_one("SELECT version FROM schema_version", &[])
                        .unwrap()
                        .get::<_, i32>(0),
                )
            }
        };
        assert_eq!(left, 99);
    }

    /// The store's tables, columns and indexes, in terms both dialects share: a column's
    /// kind (int, real, text, bytes) and NOT NULL, the primary key, every other index (its name if
    /// made by CREATE INDEX; its columns, UNIQUE, WHERE), the foreign keys.
    fn schema_summary(store: &mut Store) -> Vec<String> {
        let kind = |t: &str| match t.to_ascii_lowercase().as_str() {
            "integer" | "bigint" => "int".to_owned(),
            "real" | "double precision" => "real".to_owned(),
            "blob" | "bytea" => "bytes".to_owned(),
            "text" => "text".to_owned(),
            other => other.to_owned(),
        };
        let mut out = Vec::new();
        match store.dialect() {
            schema::Dialect::Sqlite => {
                let tables = store.rows(
                    "SELECT name FROM sqlite_schema WHERE type = 'table' \
                     AND name NOT LIKE 'sqlite_%' ORDER BY name",
                );
                for t in tables {
                    let t = t[0].text().unwrap().to_owned();
                    let mut pk = Vec::new();
                    for c in store.rows(&format!(
                        "SELECT name, type, \"notnull\", pk FROM pragma_table_info('{t}') ORDER BY cid"
                    )) {
                        let (name, ty, notnull, in_pk) =
                            (c[0].text().unwrap(), c[1].text().unwrap(), c[2].int(), c[3].int());
                        let not_null = notnull == 1 || in_pk > 0;
                        out.push(format!("column {t}.{name} {} not null {not_null}", kind(ty)));
                        if in_pk > 0 {
                            pk.push((in_pk, name.to_owned()));
                        }
                    }
                    pk.sort();
                    let pk: Vec<String> = pk.into_iter().map(|(_, n)| n).collect();
                    out.push(format!("primary key {t} ({})", pk.join(", ")));
                    for i in store.rows(&format!(
                        "SELECT name, \"unique\", origin, partial FROM pragma_index_list('{t}')"
                    )) {
                        let (name, unique, origin, partial) = (
                            i[0].text().unwrap(),
                            i[1].int(),
                            i[2].text().unwrap(),
                            i[3].int(),
                        );
                        if origin == "pk" {
                            continue;
                        }
                        let cols: Vec<String> = store
                            .rows(&format!(
                                "SELECT name FROM pragma_index_info('{name}') ORDER BY seqno"
                            ))
                            .iter()
                            .map(|c| c[0].text().unwrap().to_owned())
                            .collect();
                        let shown = if origin == "c" { name } else { "(constraint)" };
                        out.push(format!(
                            "index {t} {shown} ({}) unique {} partial {}",
                            cols.join(", "),
                            unique == 1,
                            partial == 1
                        ));
                    }
                    for f in store.rows(&format!(
                        "SELECT \"table\", \"from\", \"to\", on_delete FROM pragma_foreign_key_list('{t}')"
                    )) {
                        out.push(format!(
                            "foreign key {t}.{} -> {}.{} on delete {}",
                            f[1].text().unwrap(),
                            f[0].text().unwrap(),
                            f[2].text().unwrap(),
                            f[3].text().unwrap().to_ascii_lowercase()
                        ));
                    }
                }
            }
            schema::Dialect::Postgres => {
                let here = "current_schema()::regnamespace";
                for c in store.rows(&format!(
                    "SELECT c.relname, a.attname, format_type(a.atttypid, a.atttypmod), a.attnotnull
                     FROM pg_attribute AS a JOIN pg_class AS c ON c.oid = a.attrelid
                     WHERE c.relnamespace = {here} AND c.relkind = 'r'
                       AND c.relname <> 'schema_version' AND a.attnum > 0 AND NOT a.attisdropped
                     ORDER BY c.relname, a.attnum"
                )) {
                    let t = c[0].text().unwrap();
                    let notnull = c[3].int() == 1;
                    out.push(format!(
                        "column {t}.{} {} not null {notnull}",
                        c[1].text().unwrap(),
                        kind(c[2].text().unwrap())
                    ));
                }
                for i in store.rows(&format!(
                    "SELECT t.relname, ic.relname, i.indisunique::int, i.indisprimary::int,
                            (i.indpred IS NOT NULL)::int,
                            (EXISTS (SELECT 1 FROM pg_constraint AS k WHERE k.conindid = i.indexrelid))::int,
                            (SELECT string_agg(a.attname, ', ' ORDER BY k.n)
                             FROM unnest(i.indkey::int2[]) WITH ORDINALITY AS k(attnum, n)
                             JOIN pg_attribute AS a ON a.attrelid = t.oid AND a.attnum = k.attnum)
                     FROM pg_index AS i JOIN pg_class AS t ON t.oid = i.indrelid
                     JOIN pg_class AS ic ON ic.oid = i.indexrelid
                     WHERE t.relnamespace = {here} AND t.relname <> 'schema_version'"
                )) {
                    let t = i[0].text().unwrap();
                    let cols = i[6].text().unwrap();
                    if i[3].int() == 1 {
                        out.push(format!("primary key {t} ({cols})"));
                        continue;
                    }
                    let shown = if i[5].int() == 1 { "(constraint)" } else { i[1].text().unwrap() };
                    out.push(format!(
                        "index {t} {shown} ({cols}) unique {} partial {}",
                        i[2].int() == 1,
                        i[4].int() == 1
                    ));
                }
                for f in store.rows(&format!(
                    "SELECT c.relname, a.attname, r.relname, ra.attname, k.confdeltype::text
                     FROM pg_constraint AS k JOIN pg_class AS c ON c.oid = k.conrelid
                     JOIN pg_class AS r ON r.oid = k.confrelid
                     JOIN pg_attribute AS a ON a.attrelid = c.oid AND a.attnum = k.conkey[1]
                     JOIN pg_attribute AS ra ON ra.attrelid = r.oid AND ra.attnum = k.confkey[1]
                     WHERE k.contype = 'f' AND k.connamespace = {here}"
                )) {
                    let on_delete = match f[4].text().unwrap() {
                        "c" => "cascade",
                        "a" => "no action",
                        other => other,
                    };
                    out.push(format!(
                        "foreign key {}.{} -> {}.{} on delete {on_delete}",
                        f[0].text().unwrap(),
                        f[1].text().unwrap(),
                        f[2].text().unwrap(),
                        f[3].text().unwrap()
                    ));
                }
                // From version 2, `pads`' foreign key is kept by triggers (schema.rs).
                let triggers = store.rows(&format!(
                    "SELECT c.relname, t.tgname FROM pg_trigger AS t
                     JOIN pg_class AS c ON c.oid = t.tgrelid
                     WHERE c.relnamespace = {here} AND NOT t.tgisinternal"
                ));
                let has = |table: &str, name: &str| {
                    triggers
                        .iter()
                        .any(|r| r[0].text() == Some(table) && r[1].text() == Some(name))
                };
                if schema::POSTGRES_PADS_KEY_TRIGGERS
                    .iter()
                    .all(|(t, n)| has(t, n))
                {
                    out.push("foreign key pads.board_id -> boards.id on delete cascade".to_owned());
                }
            }
        }
        out.sort();
        out
    }

    /// Every WITHOUT ROWID table's primary key is its first columns, in order: SQLite 3.40
    /// (Debian 12's `sqlite3`) reports NULLs that are not there in `PRAGMA integrity_check`
    /// otherwise.
    #[test]
    fn sqlite_keys_lead_their_tables() {
        let (_p, mut store) = fresh(Backend::Sqlite);
        let tables = store.rows(
            "SELECT name FROM sqlite_schema WHERE type = 'table' AND sql LIKE '%WITHOUT ROWID%'",
        );
        assert_eq!(tables.len(), 6);
        for t in tables {
            let t = t[0].text().unwrap();
            for c in store.rows(&format!("SELECT cid, pk FROM pragma_table_info('{t}')")) {
                let (cid, pk) = (c[0].int(), c[1].int());
                assert!(
                    pk == 0 || pk == cid + 1,
                    "{t}: column {cid} is key column {pk}"
                );
            }
        }
    }

    /// Both backends hold the same tables, columns (kinds, NOT NULL, order), keys and
    /// indexes after every migration step: version 1, and version 2 reached from it.
    #[test]
    fn both_backends_hold_the_same_tables_columns_and_indexes() {
        for version in 1..=SCHEMA_VERSION as usize {
            let mut summaries = Vec::new();
            for b in [Backend::Sqlite, Backend::Postgres] {
                let p = place(b);
                let mut store =
                    Store::open_with(&p.location, DEFAULT_LINE, &MIGRATIONS[..version]).unwrap();
                assert_eq!(store.schema_version().unwrap(), version as u32);
                summaries.push(schema_summary(&mut store));
            }
            assert!(summaries[0].len() > 40, "{:#?}", summaries[0]);
            let only = |a: &[String], b: &[String]| -> Vec<String> {
                a.iter().filter(|x| !b.contains(x)).cloned().collect()
            };
            assert_eq!(
                (
                    only(&summaries[0], &summaries[1]),
                    only(&summaries[1], &summaries[0])
                ),
                (vec![], vec![]),
                "version {version}: only in SQLite, only in PostgreSQL"
            );
            assert_eq!(
                summaries[0], summaries[1],
                "version {version}: column order"
            );
        }
    }

    fn opening_a_store_again_changes_nothing(b: Backend) {
        let p = place(b);
        let (boards, pads, schema) = {
            let mut store = Store::open(&p.location, DEFAULT_LINE).unwrap();
            let id = inspect(&mut store, 1, "p", 7, 100.0);
            store.begin_board(&start(2, "p", 2.0)).unwrap();
            let schema = schema_summary(&mut store);
            (store.boards(10).unwrap(), store.pads(id).unwrap(), schema)
        };
        for _ in 0..2 {
            let mut store = Store::open(&p.location, DEFAULT_LINE).unwrap();
            assert_eq!(store.schema_version().unwrap(), SCHEMA_VERSION);
            assert_eq!(store.boards(10).unwrap(), boards);
            assert_eq!(store.pads(boards[1].id).unwrap(), pads);
            assert_eq!(schema_summary(&mut store), schema);
        }
    }

    fn pad_stats_equal_sums_recomputed_from_the_pad_rows(b: Backend) {
        let (_p, mut store) = fresh(b);
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
        let mut want = std::collections::BTreeMap::<(String, i64), Sums>::new();
        for board in store.boards(100).unwrap() {
            for p in store.pads(board.id).unwrap() {
                let Some(v) = p.volume_pct else { continue };
                let e = want
                    .entry((board.product.clone(), i64::from(p.pad)))
                    .or_insert((0, 0.0, 0.0, 0, 0, 0));
                e.0 += 1;
                e.1 += v;
                e.2 += v * v;
                e.3 += i64::from(p.level == "fail");
                e.4 += i64::from(p.level == "warn");
                e.5 = e.5.max(board.id);
            }
        }
        let got: Vec<((String, i64), Sums)> = store
            .rows(
                "SELECT product, pad, boards, sum_volume_pct, sum_sq_volume_pct, fails, warns, \
                 last_board_id, line FROM pad_stats ORDER BY product, pad",
            )
            .iter()
            .map(|r| {
                assert_eq!(r[8].text(), Some(DEFAULT_LINE));
                (
                    (r[0].text().unwrap().to_owned(), r[1].int()),
                    (
                        r[2].int(),
                        r[3].real(),
                        r[4].real(),
                        r[5].int(),
                        r[6].int(),
                        r[7].int(),
                    ),
                )
            })
            .collect();
        assert_eq!(got.len(), want.len());
        for ((key, g), (wkey, w)) in got.iter().zip(&want) {
            assert_eq!(key, wkey);
            assert_eq!((g.0, g.3, g.4, g.5), (w.0, w.3, w.4, w.5), "{key:?}");
            assert!((g.1 - w.1).abs() < 1e-9 * w.1.abs().max(1.0), "{key:?}");
            assert!((g.2 - w.2).abs() < 1e-9 * w.2.abs().max(1.0), "{key:?}");
        }
        assert!(got.iter().any(|(_, g)| g.3 > 0) && got.iter().any(|(_, g)| g.4 > 0));
        store.check().unwrap();
    }

    /// Two lines on one store: each its own boards, run ids, recovery, history, aggregates
    /// and retention.
    fn two_lines_share_one_store(b: Backend) {
        let p = place(b);
        let mut a = Store::open(&p.location, "smt-a").unwrap();
        let mut l2 = Store::open(&p.location, "smt-b").unwrap();
        a.claim_line().unwrap();
        l2.claim_line().unwrap();
        // The same run id on both lines: two boards.
        let a1 = inspect(&mut a, 1, "p", 4, 100.0);
        let b1 = inspect(&mut l2, 1, "p", 4, 50.0);
        assert_ne!(a1, b1);
        let e = a.begin_board(&start(1, "p", 9.0)).unwrap_err();
        assert!(
            matches!(&e, StoreError::Duplicate { line, run_id: 1, .. } if line == "smt-a"),
            "{e}"
        );
        assert!(e.to_string().contains("smt-a"), "{e}");
        // Line B's board in progress while line A restarts.
        l2.begin_board(&start(2, "p", 2.0)).unwrap();
        a.begin_board(&start(3, "p", 3.0)).unwrap();
        drop(a);
        let mut a = Store::open(&p.location, "smt-a").unwrap();
        a.claim_line().unwrap();
        assert_eq!(a.recover("line A restarted", 10.0).unwrap(), [3]);
        let bs = l2.boards(10).unwrap();
        assert_eq!(bs.len(), 2);
        assert!(bs.iter().all(|x| x.line == "smt-b"));
        assert_eq!((bs[0].run_id, bs[0].state.as_str()), (2, "open"));
        let as_ = a.boards(10).unwrap();
        assert_eq!(
            as_.iter()
                .map(|x| (x.run_id, x.state.as_str(), x.line.as_str()))
                .collect::<Vec<_>>(),
            [(3, "incomplete", "smt-a"), (1, "inspected", "smt-a")]
        );
        // A board of the other line is read by its id.
        assert_eq!(a.pads(b1).unwrap().len(), 4);
        // History and aggregates per line.
        assert_eq!(
            a.pad_history("p", 1, 10).unwrap(),
            [(a1, 1, "pass".to_owned(), Some(101.0))]
        );
        assert_eq!(
            l2.pad_history("p", 1, 10).unwrap(),
            [(b1, 1, "pass".to_owned(), Some(51.0))]
        );
        let s = stats(&mut a);
        assert_eq!(s.len(), 8);
        assert_eq!(s[1], ("smt-a".to_owned(), 1, 1, 101.0, 0));
        assert_eq!(s[5], ("smt-b".to_owned(), 1, 1, 51.0, 0));
        // Retention of line A leaves line B's pads.
        assert_eq!(a.prune_pads(100.0).unwrap(), 4);
        assert_eq!(l2.pads(b1).unwrap().len(), 4);
        a.check().unwrap();
        assert_eq!(l2.recover("line B restarted", 11.0).unwrap(), [2]);
        l2.check().unwrap();
    }

    /// A version-1 store with boards, pads and aggregates, made as version 1 made them (its
    /// schema, rows written by hand), opened by this program: at version 2, every row kept,
    /// the boards and aggregates line `line-1`'s, the keys and cascades working.
    fn a_version_1_store_migrates_to_version_2(b: Backend) {
        let p = place(b);
        {
            let mut v1 = Store::open_with(&p.location, DEFAULT_LINE, &MIGRATIONS[..1]).unwrap();
            assert_eq!(v1.schema_version().unwrap(), 1);
            v1.exec(
                "INSERT INTO boards (run_id, product, program_hash, calibration_hash, \
                 started_unix_s, ended_unix_s, state, verdict, pads) \
                 VALUES ('00000000000000a1', 'p', 'h', 'c', 1.0, 1.5, 'inspected', 'fail', 3);
                 INSERT INTO boards (run_id, product, program_hash, calibration_hash, \
                 started_unix_s, state) VALUES ('00000000000000a2', 'p', 'h', 'c', 2.0, 'open');
                 INSERT INTO board_cameras VALUES (1, 0, 100, 0, 0, 0);
                 INSERT INTO pads (board_id, pad, name, level, class, volume_pct, coverage) VALUES
                     (1, 0, 'R1-1', 'pass', NULL, 100.0, 1.0),
                     (1, 1, 'R1-2', 'fail', 'insufficient', 20.0, 1.0),
                     (1, 2, 'R2-1', 'pass', NULL, 99.0, 1.0);
                 INSERT INTO defects VALUES (1, 1, 'fail', 'insufficient');
                 INSERT INTO pad_stats VALUES
                     ('p', 0, 1, 100.0, 10000.0, 0, 0, 1),
                     ('p', 1, 1, 20.0, 400.0, 1, 0, 1),
                     ('p', 2, 1, 99.0, 9801.0, 0, 0, 1);",
            )
            .unwrap();
        }
        // At version 2 and on, to the newest.
        let mut store = Store::open(&p.location, DEFAULT_LINE).unwrap();
        assert_eq!(store.schema_version().unwrap(), SCHEMA_VERSION);
        store.check().unwrap();
        let boards = store.boards(10).unwrap();
        assert_eq!(
            boards
                .iter()
                .map(|x| (x.id, x.run_id, x.line.as_str(), x.state.as_str(), x.pads))
                .collect::<Vec<_>>(),
            [
                (2, 0xa2, "line-1", "open", 0),
                (1, 0xa1, "line-1", "inspected", 3)
            ]
        );
        assert_eq!(boards[1].cameras.len(), 1);
        assert_eq!(store.pads(1).unwrap().len(), 3);
        assert_eq!(
            stats(&mut store),
            [
                ("line-1".to_owned(), 0, 1, 100.0, 0),
                ("line-1".to_owned(), 1, 1, 20.0, 1),
                ("line-1".to_owned(), 2, 1, 99.0, 0),
            ]
        );
        // The open board of version 1 is line-1's to recover.
        assert_eq!(store.recover("upgraded", 3.0).unwrap(), [0xa2]);
        // Run ids per line now; ids go on after the old ones; the aggregates go on.
        let e = store.begin_board(&start(0xa1, "p", 4.0)).unwrap_err();
        assert!(matches!(e, StoreError::Duplicate { .. }), "{e}");
        // (PostgreSQL's identity spent a value on the refused insert: ids may skip.)
        let mut other = Store::open(&p.location, "line-2").unwrap();
        let next = inspect(&mut other, 0xa1, "p", 3, 100.0);
        assert!(next > 2, "{next}");
        assert!(inspect(&mut store, 0xa3, "p", 3, 100.0) > next);
        assert_eq!(stats(&mut store)[0], ("line-1".to_owned(), 0, 2, 200.0, 0));
        // The foreign keys hold and cascade to the new `boards`.
        let orphan = "INSERT INTO pads (board_id, pad, name, level, coverage) \
                      VALUES (999, 0, 'x', 'pass', 1)";
        assert!(store.exec(orphan).is_err(), "an orphan pad was accepted");
        let moved = "UPDATE pads SET board_id = 999 WHERE board_id = 1";
        assert!(store.exec(moved).is_err(), "a pad was moved to no board");
        if b == Backend::Postgres {
            let renumbered = "UPDATE boards SET id = DEFAULT WHERE id = 1";
            assert!(store.exec(renumbered).is_err(), "a board's id changed");
        }
        store.exec("DELETE FROM boards WHERE id = 1").unwrap();
        assert_eq!(
            store.int("SELECT count(*) FROM pads WHERE board_id = 1")
                + store.int("SELECT count(*) FROM defects WHERE board_id = 1")
                + store.int("SELECT count(*) FROM board_cameras WHERE board_id = 1"),
            0
        );
        store.check().unwrap();
        if b == Backend::Sqlite {
            // Nothing of the copy left; `pads` as version 1 made it.
            assert_eq!(
                store.int("SELECT count(*) FROM sqlite_schema WHERE name LIKE '%v2%'"),
                0
            );
            let pads_sql = store.rows("SELECT sql FROM sqlite_schema WHERE name = 'pads'");
            assert!(
                include_str!("store/v1_as_shipped.sql").contains(pads_sql[0][0].text().unwrap())
            );
        }
    }

    fn programs_opening_a_new_store_at_once_migrate_it_once(b: Backend) {
        let p = place(b);
        let location = p.location.clone();
        let opened: Vec<Result<u32, String>> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..4)
                .map(|i| {
                    let location = location.clone();
                    s.spawn(move || {
                        let mut store = Store::open(&location, &format!("line-{i}"))
                            .map_err(|e| format!("{e:#?}"))?;
                        inspect(&mut store, 1, "p", 3, 100.0);
                        store.schema_version().map_err(|e| e.to_string())
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for o in &opened {
            assert_eq!(o.as_ref(), Ok(&SCHEMA_VERSION));
        }
        let mut store = Store::open(&location, "line-0").unwrap();
        assert_eq!(store.int("SELECT count(*) FROM boards"), 4);
        store.check().unwrap();
    }

    /// Line B's service on the line A is serving is refused (PostgreSQL); line A's lock is
    /// gone with its connection.
    #[test]
    fn a_second_service_of_the_same_line_is_refused_on_postgres() {
        let p = place(Backend::Postgres);
        let mut first = Store::open(&p.location, "smt-1").unwrap();
        first.claim_line().unwrap();
        first.claim_line().unwrap();
        let mut second = Store::open(&p.location, "smt-1").unwrap();
        let e = second.claim_line().unwrap_err();
        assert!(
            matches!(&e, StoreError::LineInUse { line, .. } if line == "smt-1"),
            "{e}"
        );
        assert!(e.to_string().contains("`line` name"), "{e}");
        Store::open(&p.location, "smt-2")
            .unwrap()
            .claim_line()
            .unwrap();
        drop(first);
        second.claim_line().unwrap();
    }

    /// The server cuts the connection: the call during it fails, the next ones work on a
    /// new connection, which holds the line again.
    #[test]
    fn a_cut_postgres_connection_is_opened_again() {
        let p = place(Backend::Postgres);
        let mut store = Store::open(&p.location, "smt-1").unwrap();
        store.claim_line().unwrap();
        inspect(&mut store, 1, "p", 3, 100.0);
        let Db::Postgres(pg) = &mut store.db else {
            unreachable!()
        };
        let pid = pg.backend_pid();
        let Location::Postgres(url) = &p.location else {
            unreachable!()
        };
        let mut admin = url.config().unwrap().connect(postgres::NoTls).unwrap();
        admin
            .execute("SELECT pg_terminate_backend($1)", &[&pid])
            .unwrap();
        // Until the client has seen the cut, a call may fail; then it connects again.
        let mut ok = 0;
        for run in 2..6 {
            if store.begin_board(&start(run, "p", run as f64)).is_ok() {
                ok += 1;
            }
        }
        assert!(ok >= 3, "{ok} of 4 boards begun after the cut");
        assert_eq!(store.boards(10).unwrap().len(), 1 + ok);
        let e = Store::open(&p.location, "smt-1")
            .unwrap()
            .claim_line()
            .unwrap_err();
        assert!(matches!(e, StoreError::LineInUse { .. }), "{e}");
    }

    #[test]
    fn a_password_is_never_shown() {
        for (url, shown) in [
            (
                "postgres://line:s3cret@127.0.0.1:1/factory",
                "postgres://line:***@127.0.0.1:1/factory",
            ),
            (
                "postgresql://line:s3cret@127.0.0.1:1/factory?password=s3cret&connect_timeout=2",
                "postgresql://line:***@127.0.0.1:1/factory?password=***&connect_timeout=2",
            ),
            (
                "postgres://127.0.0.1:1/factory?user=line&password=s3cret",
                "postgres://127.0.0.1:1/factory?user=line&password=***",
            ),
        ] {
            let l = Location::from_arg(url).unwrap();
            assert_eq!(l.to_string(), shown);
            assert!(!format!("{l:?}").contains("s3cret"), "{l:?}");
            // Nothing listens on port 1: the error names the store, without the password.
            let e = Store::open(&l, DEFAULT_LINE).unwrap_err();
            let text = format!("{e} / {:?}", anyhow_chain(&e));
            assert!(
                text.contains("127.0.0.1:1") && !text.contains("s3cret"),
                "{text}"
            );
        }
        for bad in [
            "mysql://line:s3cret@host/db",
            "postgres://line:s3cret@host:notaport/db",
        ] {
            let e = Location::from_arg(bad).unwrap_err();
            assert!(!e.contains("s3cret") && e.contains("***"), "{e}");
        }
        let e = Location::postgres("host=db password=s3cret").unwrap_err();
        assert!(!e.contains("s3cret"), "{e}");
        assert_eq!(
            Location::from_arg("data/line.sqlite").unwrap(),
            Location::Sqlite(PathBuf::from("data/line.sqlite"))
        );
    }

    /// An error and its sources, as the CLI prints them.
    fn anyhow_chain(e: &dyn std::error::Error) -> Vec<String> {
        let mut out = vec![e.to_string()];
        let mut s = e.source();
        while let Some(x) = s {
            out.push(x.to_string());
            s = x.source();
        }
        out
    }

    #[test]
    fn line_names_are_checked() {
        for ok in ["line-1", "SMT_3", "a", "hall.2-line.7", &"x".repeat(64)] {
            check_line_name(ok).unwrap();
        }
        for bad in ["", "line 1", "line/1", "ligne-é", &"x".repeat(65), "a'b"] {
            assert!(check_line_name(bad).is_err(), "{bad:?}");
        }
        let dir = tempfile::tempdir().unwrap();
        let e = Store::open(&Location::Sqlite(dir.path().join("s.sqlite")), "").unwrap_err();
        assert!(matches!(e, StoreError::Invalid { .. }), "{e}");
        assert!(!dir.path().join("s.sqlite").exists());
    }

    fn the_benchmark_runs_small(b: Backend) {
        let p = place(b);
        let r = bench::run_at(&p.location, 30, 200).unwrap();
        assert_eq!(r.backend, b_name(b));
        assert_eq!(r.boards, 30);
        assert!(r.pad_rows > 0 && r.pad_rows <= 30 * 200);
        assert!(r.insert.pads_per_s > 0.0 && r.history.median_ms >= 0.0);
        assert_eq!(r.history.entries, r.inspected_boards);
        assert!(r.prune.pad_rows_deleted > 0);
        // The keeper's calls take the boards left, two at a time.
        let k = &r.prune;
        assert!(k.keeper_calls > 0 && k.keeper_pad_rows_deleted > 0);
        assert_eq!(k.pad_rows_deleted + k.keeper_pad_rows_deleted, r.pad_rows);
        assert!(k.keeper_pad_rows_deleted <= (k.keeper_calls * 2 * 200) as u64);
        assert!(k.keeper_call_median_ms <= k.keeper_call_max_ms);
        assert!(r.size.bytes > 0);
        let json = serde_json::to_string(&r).unwrap();
        assert!(json.contains("\"goals\""), "{json}");
        bench::remove_scratch(&p.location).unwrap();
        if let Location::Sqlite(path) = &p.location {
            assert!(!path.exists());
        }
    }

    fn b_name(b: Backend) -> &'static str {
        match b {
            Backend::Sqlite => "sqlite",
            Backend::Postgres => "postgres",
        }
    }
}
