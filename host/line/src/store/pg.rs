//! The store on PostgreSQL: one database for many lines, through rust-postgres's synchronous
//! client over plain TCP (no TLS: loopback, or the factory's own network).
//!
//! What differs from SQLite, and why:
//! - The schema's version is the one row of `schema_version`; the migrations run in one
//!   transaction under a transaction-scoped advisory lock ([`MIGRATION_LOCK`]), so two lines
//!   starting at once on a new database do not both migrate it: the second waits, then finds
//!   it done. PostgreSQL's DDL is transactional, so a failed step leaves the version it found.
//! - Pad rows go in by binary `COPY` (one message stream, no statement per row); the defect
//!   rows and the aggregates are made from them on the server (`INSERT ... SELECT`), so a
//!   board costs a handful of round trips whatever its pads.
//! - A line's service holds a session advisory lock on its line name ([`Pg::claim_line`]):
//!   with one database for all lines, a second service started with the same `line` (the
//!   default name on two hosts) would otherwise turn the first one's open boards incomplete
//!   at its start.
//! - A connection found closed (the server restarted, a network cut) is opened again before
//!   the next call; the call during which it broke fails (its transaction is rolled back by
//!   the server), as any store error does.

use super::review::{
    family_reviews, Decision, FamilyReviews, ImageValues, Review, FAMILY_REVIEWS_SQL,
    IMAGE_COLUMNS, INSERT_REVIEW_SQL, REVIEW_COLUMNS,
};
use super::schema::{self, Dialect, Step};
use super::{
    insert_print_sql, parse_run_id, real, run_id_text, select_prints_sql, Beside, BoardStart,
    CameraLoss, HistoryEntry, Outcome, PadRow, PgUrl, PrintValues, StencilClean, StoreError,
    StoredBoard, StoredPrint, Which, PRINT_REALS, PRUNE_BOARDS_PER_TRANSACTION,
};
use std::sync::LazyLock;

/// A print row's insert and a line's print rows, in PostgreSQL's `$N` (built once: the
/// statement cache keys on the text).
static INSERT_PRINT: LazyLock<String> = LazyLock::new(|| insert_print_sql('$'));
static SELECT_PRINTS: LazyLock<String> = LazyLock::new(|| select_prints_sql('$'));
/// The review statements shared with SQLite, in `$N`.
static INSERT_REVIEW: LazyLock<String> =
    LazyLock::new(|| format!("{} RETURNING id", dollars(INSERT_REVIEW_SQL)));
static FAMILY_REVIEWS: LazyLock<String> = LazyLock::new(|| dollars(FAMILY_REVIEWS_SQL));
static INSERT_IMAGE: LazyLock<String> = LazyLock::new(|| {
    format!(
        "INSERT INTO pad_images (board_id, pad, {IMAGE_COLUMNS}) \
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11)"
    )
});
static SELECT_IMAGE: LazyLock<String> = LazyLock::new(|| {
    format!("SELECT {IMAGE_COLUMNS} FROM pad_images WHERE board_id = $1 AND pad = $2")
});
static SELECT_REVIEWS: LazyLock<String> = LazyLock::new(|| {
    format!("SELECT {REVIEW_COLUMNS} FROM reviews WHERE board_id = $1 ORDER BY pad, id")
});

/// SQLite's `?N` placeholders as PostgreSQL's `$N`.
fn dollars(sql: &str) -> String {
    let mut out = String::with_capacity(sql.len());
    let mut it = sql.chars().peekable();
    while let Some(c) = it.next() {
        if c == '?' && it.peek().is_some_and(|d| d.is_ascii_digit()) {
            out.push('$');
        } else {
            out.push(c);
        }
    }
    out
}
use postgres::binary_copy::BinaryCopyInWriter;
use postgres::error::SqlState;
use postgres::types::Type;
use postgres::{Client, GenericClient, IsolationLevel, NoTls, Statement};
use std::collections::HashMap;
use std::time::Duration;

/// The first key of every advisory lock this program takes: `dpsa` in ASCII.
const LOCK_CLASS: i32 = 0x6470_7361;

/// The advisory lock the migrations are run under: (class, 0).
const MIGRATION_LOCK: (i32, i32) = (LOCK_CLASS, 0);

/// The first key of a line's lock; the second is a hash of its name ([`line_key`]).
const LINE_LOCK_CLASS: i32 = LOCK_CLASS + 1;

/// How long [`Pg::claim_line`] waits for a line's lock: the server ends the session of a
/// service that stopped (or was killed) a moment after its connection closed, not at once.
const CLAIM_WAIT: Duration = Duration::from_secs(2);

/// How long a connection attempt may take when the URL does not say (`connect_timeout`).
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

/// The columns of a pad row, in `COPY` order, with their types.
const PAD_COLUMNS: &str = "board_id, pad, name, level, class, volume_um3, volume_pct, area_mm2, \
     area_pct, height_um, height_pct, offset_x_um, offset_y_um, coverage, uncertainty_um3";
const PAD_TYPES: [Type; 15] = [
    Type::INT8,
    Type::INT4,
    Type::TEXT,
    Type::TEXT,
    Type::TEXT,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
    Type::FLOAT8,
];

/// Adds board `$3`'s pads (of line `$1`, product `$2`) that have a volume to the line's
/// running aggregates, in two statements: the rows there updated (returning their pads), then
/// only the pads not counted yet (`$4`; none once a product's first board is in) inserted.
/// One `INSERT ... ON CONFLICT DO UPDATE` (SQLite's way) locks every row it updates before
/// it updates it, a second write per row: measured 20 % slower. The update must come first
/// (else it would count the new rows twice). The insert names its pads rather than asking
/// for those without a row (`NOT EXISTS`), whose plan, on a table not analysed yet, compared
/// every pad with every row: 1.4 s a board (measured) until autovacuum analysed it. It keeps
/// `ON CONFLICT` for a row another connection inserted meanwhile (a line has one writer, so
/// only SQL by hand could): it waits for that one and adds to it, as the update would have.
const UPDATE_PAD_STATS: &str = "UPDATE pad_stats AS s SET \
     boards = s.boards + 1, \
     sum_volume_pct = s.sum_volume_pct + p.volume_pct, \
     sum_sq_volume_pct = s.sum_sq_volume_pct + p.volume_pct * p.volume_pct, \
     fails = s.fails + (p.level = 'fail')::int, \
     warns = s.warns + (p.level = 'warn')::int, \
     last_board_id = p.board_id \
     FROM pads AS p \
     WHERE p.board_id = $3 AND p.volume_pct IS NOT NULL \
     AND s.line = $1 AND s.product = $2 AND s.pad = p.pad \
     RETURNING s.pad";

/// See [`UPDATE_PAD_STATS`].
const INSERT_PAD_STATS: &str = "INSERT INTO pad_stats (line, product, pad, boards, \
     sum_volume_pct, sum_sq_volume_pct, fails, warns, last_board_id) \
     SELECT $1, $2, p.pad, 1, p.volume_pct, p.volume_pct * p.volume_pct, \
            (p.level = 'fail')::int, (p.level = 'warn')::int, p.board_id \
     FROM pads AS p WHERE p.board_id = $3 AND p.pad = ANY($4) AND p.volume_pct IS NOT NULL \
     ON CONFLICT (line, product, pad) DO UPDATE SET \
     boards = pad_stats.boards + 1, \
     sum_volume_pct = pad_stats.sum_volume_pct + excluded.sum_volume_pct, \
     sum_sq_volume_pct = pad_stats.sum_sq_volume_pct + excluded.sum_sq_volume_pct, \
     fails = pad_stats.fails + excluded.fails, \
     warns = pad_stats.warns + excluded.warns, \
     last_board_id = excluded.last_board_id";

/// The second key of line `line`'s advisory lock: FNV-1a of its name, folded to 32 bits.
/// Two names of one hash would share a lock (refused as in use, never silently shared).
fn line_key(line: &str) -> i32 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in line.as_bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    ((h >> 32) ^ h) as u32 as i32
}

/// A PostgreSQL identifier, quoted.
fn quote_ident(name: &str) -> String {
    format!("\"{}\"", name.replace('"', "\"\""))
}

/// Connects to `url` (its schema, if it names one, first on the search path).
fn connect(url: &PgUrl, name: &str) -> Result<Client, StoreError> {
    let mut config = url.config().map_err(|why| StoreError::Invalid {
        store: name.to_owned(),
        why,
    })?;
    if config.get_connect_timeout().is_none() {
        config.connect_timeout(CONNECT_TIMEOUT);
    }
    if config.get_application_name().is_none() {
        config.application_name("dpsa-line");
    }
    // The server's notices (e.g. "relation already exists, skipping") are of no use here.
    config.notice_callback(|_| {});
    let mut client = config.connect(NoTls).map_err(pg_err(name))?;
    if let Some(schema) = url.schema() {
        client
            .batch_execute(&format!("SET search_path TO {}", quote_ident(schema)))
            .map_err(pg_err(name))?;
    }
    Ok(client)
}

/// Maps a client error to a [`StoreError`] of the store `name`.
fn pg_err(name: &str) -> impl Fn(postgres::Error) -> StoreError + '_ {
    move |source| StoreError::Postgres {
        store: name.to_owned(),
        source,
    }
}

/// Reads the schema's version: 0 when there is no `schema_version` table (a new database).
fn read_version(client: &mut impl GenericClient, name: &str) -> Result<u32, StoreError> {
    let err = pg_err(name);
    let exists: bool = client
        .query_one("SELECT to_regclass('schema_version') IS NOT NULL", &[])
        .map_err(&err)?
        .get(0);
    if !exists {
        return Ok(0);
    }
    let v: Option<i32> = client
        .query_opt("SELECT version FROM schema_version", &[])
        .map_err(&err)?
        .map(|r| r.get(0));
    Ok(v.map_or(0, |v| v.max(0) as u32))
}

/// One connection to one database.
pub(super) struct Pg {
    client: Client,
    url: PgUrl,
    /// The store, as errors name it (the URL without its password).
    name: String,
    /// Prepared statements by their text (prepared once per connection).
    statements: HashMap<&'static str, Statement>,
    /// The line whose lock this connection holds, to take again after a reconnection.
    claimed: Option<String>,
    /// Every transaction read-only (a reader's connection), set again after a reconnection.
    read_only: bool,
}

impl std::fmt::Debug for Pg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pg").field("store", &self.name).finish()
    }
}

/// A statement of `cache`, prepared on `client` the first time.
fn prepared(
    client: &mut impl GenericClient,
    cache: &mut HashMap<&'static str, Statement>,
    sql: &'static str,
) -> Result<Statement, postgres::Error> {
    if let Some(s) = cache.get(sql) {
        return Ok(s.clone());
    }
    let s = client.prepare(sql)?;
    cache.insert(sql, s.clone());
    Ok(s)
}

/// `v` as PostgreSQL's BIGINT, or the sentence refusing it.
fn int8(v: u64, what: &str) -> Result<i64, String> {
    i64::try_from(v).map_err(|_| format!("{what} {v} is more than a BIGINT holds"))
}

impl Pg {
    /// Connects and brings the database's schema up to `migrations.len()`; see
    /// [`super::Store::open`].
    pub(super) fn open(url: &PgUrl, migrations: &[Step]) -> Result<Pg, StoreError> {
        let name = url.to_string();
        let mut client = connect(url, &name)?;
        let known = migrations.len() as u32;
        let found = read_version(&mut client, &name)?;
        if found > known {
            return Err(StoreError::NewerSchema {
                store: name,
                found,
                known,
            });
        }
        if found < known {
            Self::migrate(&mut client, &name, migrations)?;
        }
        Ok(Pg {
            client,
            url: url.clone(),
            name,
            statements: HashMap::new(),
            claimed: None,
            read_only: false,
        })
    }

    /// Connects for reading only: every transaction of the session read-only (the server
    /// refuses a write), the schema at this program's version (never migrated: an older store
    /// is refused with what to do).
    pub(super) fn open_read_only(url: &PgUrl) -> Result<Pg, StoreError> {
        let name = url.to_string();
        let mut client = connect(url, &name)?;
        client
            .batch_execute("SET default_transaction_read_only = on")
            .map_err(pg_err(&name))?;
        let found = read_version(&mut client, &name)?;
        super::check_reader_version(&name, found)?;
        Ok(Pg {
            client,
            url: url.clone(),
            name,
            statements: HashMap::new(),
            claimed: None,
            read_only: true,
        })
    }

    /// All the migrations the database lacks, in one transaction under the migration lock;
    /// the version is read again once the lock is held.
    fn migrate(client: &mut Client, name: &str, migrations: &[Step]) -> Result<(), StoreError> {
        let err = pg_err(name);
        let known = migrations.len() as u32;
        let mut tx = client.transaction().map_err(&err)?;
        tx.execute(
            "SELECT pg_advisory_xact_lock($1, $2)",
            &[&MIGRATION_LOCK.0, &MIGRATION_LOCK.1],
        )
        .map_err(&err)?;
        tx.batch_execute(schema::POSTGRES_VERSION_TABLE)
            .map_err(&err)?;
        let found = read_version(&mut tx, name)?;
        if found > known {
            return Err(StoreError::NewerSchema {
                store: name.to_owned(),
                found,
                known,
            });
        }
        for step in &migrations[found as usize..] {
            tx.batch_execute(&step.sql(Dialect::Postgres))
                .map_err(&err)?;
        }
        tx.execute(
            "INSERT INTO schema_version (one, version) VALUES (TRUE, $1) \
             ON CONFLICT (one) DO UPDATE SET version = excluded.version",
            &[&(known as i32)],
        )
        .map_err(&err)?;
        tx.commit().map_err(&err)
    }

    /// The client, connected again first if the connection was found closed.
    fn ready(&mut self) -> Result<(), StoreError> {
        if self.client.is_closed() {
            tracing::warn!(store = %self.name, "the connection to the store was closed: connecting again");
            self.client = connect(&self.url, &self.name)?;
            self.statements.clear();
            if self.read_only {
                self.client
                    .batch_execute("SET default_transaction_read_only = on")
                    .map_err(pg_err(&self.name))?;
            }
            if let Some(line) = self.claimed.take() {
                self.claim_line(&line)?;
            }
        }
        Ok(())
    }

    pub(super) fn schema_version(&mut self) -> Result<u32, StoreError> {
        self.ready()?;
        read_version(&mut self.client, &self.name)
    }

    /// Takes line `line`'s lock for as long as this connection lives, waiting up to
    /// [`CLAIM_WAIT`] for it, or says it is held. A service whose host died holds it until
    /// the server finds the connection dead (its TCP keepalive), or an administrator ends
    /// that session (`pg_terminate_backend`).
    pub(super) fn claim_line(&mut self, line: &str) -> Result<(), StoreError> {
        if self.claimed.as_deref() == Some(line) {
            return Ok(());
        }
        self.ready()?;
        let waited = std::time::Instant::now();
        loop {
            let got: bool = self
                .client
                .query_one(
                    "SELECT pg_try_advisory_lock($1, $2)",
                    &[&LINE_LOCK_CLASS, &line_key(line)],
                )
                .map_err(pg_err(&self.name))?
                .get(0);
            if got {
                self.claimed = Some(line.to_owned());
                return Ok(());
            }
            if waited.elapsed() >= CLAIM_WAIT {
                return Err(StoreError::LineInUse {
                    store: self.name.clone(),
                    line: line.to_owned(),
                });
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    pub(super) fn begin_board(&mut self, line: &str, b: &BoardStart) -> Result<i64, StoreError> {
        self.ready()?;
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let result = prepared(
            client,
            statements,
            "INSERT INTO boards (run_id, product, program_hash, calibration_hash, \
             started_unix_s, state, line) VALUES ($1, $2, $3, $4, $5, 'open', $6) RETURNING id",
        )
        .and_then(|s| {
            client.query_one(
                &s,
                &[
                    &run_id_text(b.run_id),
                    &b.product,
                    &b.program_hash,
                    &b.calibration_hash,
                    &b.started_unix_s,
                    &line,
                ],
            )
        });
        match result {
            Ok(row) => Ok(row.get(0)),
            Err(e) if e.code() == Some(&SqlState::UNIQUE_VIOLATION) => Err(StoreError::Duplicate {
                store: name.clone(),
                line: line.to_owned(),
                run_id: b.run_id,
            }),
            Err(e) => Err(pg_err(name)(e)),
        }
    }

    pub(super) fn finish_board(
        &mut self,
        line: &str,
        id: i64,
        ended_unix_s: f64,
        cameras: &[CameraLoss],
        outcome: &Outcome,
        beside: &Beside,
    ) -> Result<(), StoreError> {
        let (print, images) = (beside.print.as_ref(), beside.images.as_slice());
        self.ready()?;
        let invalid = |why: String| StoreError::Invalid {
            store: self.name.clone(),
            why,
        };
        let mut losses = Vec::with_capacity(cameras.len());
        for c in cameras {
            let what = |w: &str| format!("board {id}, camera {}: {w}", c.camera);
            losses.push((
                i32::from(c.camera),
                int8(c.rows, &what("rows")).map_err(invalid)?,
                int8(c.missing_rows, &what("missing rows")).map_err(invalid)?,
                int8(c.missing_packets, &what("missing packets")).map_err(invalid)?,
                int8(c.damaged_packets, &what("damaged packets")).map_err(invalid)?,
            ));
        }
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let name = name.as_str();
        let err = pg_err(name);
        let mut tx = client.transaction().map_err(&err)?;
        // The board's row locked until the commit: a second finish (another connection of
        // the same line) waits and then finds it no longer open.
        let s = prepared(
            &mut tx,
            statements,
            "SELECT state, product FROM boards WHERE id = $1 FOR UPDATE",
        )
        .map_err(&err)?;
        let row = tx.query_opt(&s, &[&id]).map_err(&err)?;
        let product: String = match row {
            None => {
                return Err(StoreError::UnknownBoard {
                    store: name.to_owned(),
                    id,
                })
            }
            Some(r) if r.get::<_, &str>(0) != "open" => {
                return Err(StoreError::NotOpen {
                    store: name.to_owned(),
                    id,
                    state: r.get(0),
                })
            }
            Some(r) => r.get(1),
        };
        let s = prepared(
            &mut tx,
            statements,
            "INSERT INTO board_cameras (board_id, camera, rows, missing_rows, missing_packets, \
             damaged_packets) VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .map_err(&err)?;
        for (camera, rows, missing_rows, missing_packets, damaged_packets) in &losses {
            tx.execute(
                &s,
                &[
                    &id,
                    camera,
                    rows,
                    missing_rows,
                    missing_packets,
                    damaged_packets,
                ],
            )
            .map_err(&err)?;
        }
        match outcome {
            Outcome::Inspected { verdict, pads } => {
                let sink = tx
                    .copy_in(&format!(
                        "COPY pads ({PAD_COLUMNS}) FROM STDIN (FORMAT binary)"
                    ))
                    .map_err(&err)?;
                let mut w = BinaryCopyInWriter::new(sink, &PAD_TYPES);
                for p in pads {
                    // Checked by the store before anything is written.
                    let pad = i32::try_from(p.pad).unwrap_or(i32::MAX);
                    w.write(&[
                        &id,
                        &pad,
                        &p.name,
                        &p.level,
                        &p.class,
                        &real(p.volume_um3),
                        &real(p.volume_pct),
                        &real(p.area_mm2),
                        &real(p.area_pct),
                        &real(p.height_um),
                        &real(p.height_pct),
                        &real(p.offset_x_um),
                        &real(p.offset_y_um),
                        &p.coverage,
                        &real(p.uncertainty_um3),
                    ])
                    .map_err(&err)?;
                }
                w.finish().map_err(&err)?;
                let s = prepared(
                    &mut tx,
                    statements,
                    "INSERT INTO defects (board_id, pad, level, class) \
                     SELECT board_id, pad, level, class FROM pads \
                     WHERE board_id = $1 AND level <> 'pass'",
                )
                .map_err(&err)?;
                tx.execute(&s, &[&id]).map_err(&err)?;
                let s = prepared(&mut tx, statements, UPDATE_PAD_STATS).map_err(&err)?;
                let counted: std::collections::HashSet<i32> = tx
                    .query(&s, &[&line, &product, &id])
                    .map_err(&err)?
                    .iter()
                    .map(|r| r.get(0))
                    .collect();
                let missing: Vec<i32> = pads
                    .iter()
                    .filter(|p| real(p.volume_pct).is_some())
                    .filter_map(|p| i32::try_from(p.pad).ok())
                    .filter(|p| !counted.contains(p))
                    .collect();
                if !missing.is_empty() {
                    let s = prepared(&mut tx, statements, INSERT_PAD_STATS).map_err(&err)?;
                    tx.execute(&s, &[&line, &product, &id, &missing])
                        .map_err(&err)?;
                }
                let s = prepared(&mut tx, statements, INSERT_IMAGE.as_str()).map_err(&err)?;
                for v in images {
                    // Pad indices and sides checked by the store before anything is written.
                    let (pad, nx, ny) = (
                        i32::try_from(v.pad).unwrap_or(i32::MAX),
                        v.nx as i32,
                        v.ny as i32,
                    );
                    tx.execute(
                        &s,
                        &[
                            &id,
                            &pad,
                            &v.family,
                            &v.x0_mm,
                            &v.y0_mm,
                            &v.pitch_mm,
                            &nx,
                            &ny,
                            &v.lsb_um,
                            &v.heights,
                            &v.outline,
                        ],
                    )
                    .map_err(&err)?;
                }
                let s = prepared(
                    &mut tx,
                    statements,
                    "UPDATE boards SET state = 'inspected', verdict = $2, ended_unix_s = $3, \
                     pads = $4 WHERE id = $1",
                )
                .map_err(&err)?;
                // At most 2^31 - 1 pads, checked by the store before anything is written.
                let n = i32::try_from(pads.len()).unwrap_or(i32::MAX);
                tx.execute(&s, &[&id, verdict, &ended_unix_s, &n])
                    .map_err(&err)?;
            }
            Outcome::Incomplete { reason } => {
                let s = prepared(
                    &mut tx,
                    statements,
                    "UPDATE boards SET state = 'incomplete', incomplete_reason = $2, \
                     ended_unix_s = $3 WHERE id = $1",
                )
                .map_err(&err)?;
                tx.execute(&s, &[&id, reason, &ended_unix_s])
                    .map_err(&err)?;
            }
        }
        if let Some(v) = print {
            let mut p: Vec<&(dyn postgres::types::ToSql + Sync)> = vec![&id];
            p.extend(
                v.reals
                    .iter()
                    .map(|r| r as &(dyn postgres::types::ToSql + Sync)),
            );
            p.extend(
                v.counts
                    .iter()
                    .map(|r| r as &(dyn postgres::types::ToSql + Sync)),
            );
            p.extend(
                v.flags
                    .iter()
                    .map(|r| r as &(dyn postgres::types::ToSql + Sync)),
            );
            p.push(&v.reason);
            let s = prepared(&mut tx, statements, INSERT_PRINT.as_str()).map_err(&err)?;
            tx.execute(&s, &p).map_err(&err)?;
        }
        tx.commit().map_err(&err)
    }

    pub(super) fn pad_image(
        &mut self,
        board_id: i64,
        pad: u32,
    ) -> Result<Option<ImageValues>, StoreError> {
        self.ready()?;
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let Ok(p) = i32::try_from(pad) else {
            return Ok(None);
        };
        let s = prepared(client, statements, SELECT_IMAGE.as_str()).map_err(&err)?;
        let row = client.query_opt(&s, &[&board_id, &p]).map_err(&err)?;
        Ok(row.map(|r| {
            let (nx, ny): (i32, i32) = (r.get(4), r.get(5));
            ImageValues {
                pad,
                family: r.get(0),
                x0_mm: r.get(1),
                y0_mm: r.get(2),
                pitch_mm: r.get(3),
                nx: u32::try_from(nx).unwrap_or(0),
                ny: u32::try_from(ny).unwrap_or(0),
                lsb_um: r.get(6),
                heights: r.get(7),
                outline: r.get(8),
            }
        }))
    }

    #[allow(clippy::too_many_arguments)]
    pub(super) fn add_review(
        &mut self,
        line: &str,
        board_id: i64,
        pad: u32,
        decision: Decision,
        reviewer: &str,
        at_unix_s: f64,
        note: Option<&str>,
    ) -> Result<Option<i64>, StoreError> {
        self.ready()?;
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let Ok(p) = i32::try_from(pad) else {
            return Ok(None);
        };
        let s = prepared(client, statements, INSERT_REVIEW.as_str()).map_err(&err)?;
        let row = client
            .query_opt(
                &s,
                &[
                    &board_id,
                    &p,
                    &decision.name(),
                    &reviewer,
                    &at_unix_s,
                    &note,
                    &line,
                ],
            )
            .map_err(&err)?;
        Ok(row.map(|r| r.get(0)))
    }

    pub(super) fn reviews(&mut self, board_id: i64) -> Result<Vec<Review>, StoreError> {
        self.ready()?;
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(client, statements, SELECT_REVIEWS.as_str()).map_err(&err)?;
        let rows = client.query(&s, &[&board_id]).map_err(&err)?;
        rows.iter()
            .map(|r| {
                let d: String = r.get(4);
                let pad: i32 = r.get(2);
                Ok(Review {
                    id: r.get(0),
                    board_id: r.get(1),
                    pad: u32::try_from(pad).unwrap_or(0),
                    family: r.get(3),
                    decision: Decision::from_name(&d).ok_or_else(|| StoreError::Corrupt {
                        store: name.clone(),
                        why: format!("a review's decision {d:?}"),
                    })?,
                    reviewer: r.get(5),
                    reviewed_unix_s: r.get(6),
                    note: r.get(7),
                })
            })
            .collect()
    }

    pub(super) fn family_reviews(&mut self, line: &str) -> Result<Vec<FamilyReviews>, StoreError> {
        self.ready()?;
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(client, statements, FAMILY_REVIEWS.as_str()).map_err(&err)?;
        let rows = client.query(&s, &[&line]).map_err(&err)?;
        Ok(family_reviews(
            rows.iter()
                .map(|r| (r.get(0), r.get(1), r.get(2)))
                .collect(),
        ))
    }

    pub(super) fn record_clean(
        &mut self,
        line: &str,
        product: &str,
        cleaned_unix_s: f64,
        source: &str,
        note: Option<&str>,
    ) -> Result<i64, StoreError> {
        self.ready()?;
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(
            client,
            statements,
            "INSERT INTO stencil_cleans (line, product, cleaned_unix_s, source, note) \
             VALUES ($1, $2, $3, $4, $5) RETURNING id",
        )
        .map_err(&err)?;
        let row = client
            .query_one(&s, &[&line, &product, &cleaned_unix_s, &source, &note])
            .map_err(&err)?;
        Ok(row.get(0))
    }

    pub(super) fn cleans(
        &mut self,
        line: &str,
        product: &str,
        limit: usize,
    ) -> Result<Vec<StencilClean>, StoreError> {
        self.ready()?;
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(
            client,
            statements,
            "SELECT id, product, cleaned_unix_s, source, note FROM stencil_cleans \
             WHERE line = $1 AND product = $2 ORDER BY cleaned_unix_s DESC, id DESC LIMIT $3",
        )
        .map_err(&err)?;
        let rows = client.query(&s, &[&line, &product, &limit]).map_err(&err)?;
        Ok(rows
            .iter()
            .map(|r| StencilClean {
                id: r.get(0),
                product: r.get(1),
                cleaned_unix_s: r.get(2),
                source: r.get(3),
                note: r.get(4),
            })
            .collect())
    }

    pub(super) fn prints(
        &mut self,
        line: &str,
        product: &str,
        limit: usize,
    ) -> Result<Vec<StoredPrint>, StoreError> {
        self.ready()?;
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(client, statements, SELECT_PRINTS.as_str()).map_err(&err)?;
        let rows = client.query(&s, &[&line, &product, &limit]).map_err(&err)?;
        rows.iter()
            .map(|r| {
                let mut reals = [None; PRINT_REALS];
                for (k, v) in reals.iter_mut().enumerate() {
                    *v = r.get(2 + k);
                }
                let at = 2 + PRINT_REALS;
                let v = PrintValues {
                    reals,
                    counts: [r.get(at), r.get(at + 1)],
                    flags: [r.get(at + 2), r.get(at + 3)],
                    reason: r.get(at + 4),
                };
                Ok(StoredPrint {
                    board_id: r.get(0),
                    run_id: parse_run_id(name, r.get(1))?,
                    print: v.row(),
                })
            })
            .collect()
    }

    pub(super) fn recover(
        &mut self,
        line: &str,
        reason: &str,
        now_unix_s: f64,
    ) -> Result<Vec<u64>, StoreError> {
        self.ready()?;
        let rows = self
            .client
            .query(
                "UPDATE boards SET state = 'incomplete', incomplete_reason = $1, \
                 ended_unix_s = $2 WHERE state = 'open' AND line = $3 RETURNING id, run_id",
                &[&reason, &now_unix_s, &line],
            )
            .map_err(pg_err(&self.name))?;
        let mut found: Vec<(i64, String)> = rows.iter().map(|r| (r.get(0), r.get(1))).collect();
        found.sort();
        found
            .iter()
            .map(|(_, t)| parse_run_id(&self.name, t))
            .collect()
    }

    /// The rules of [`schema::INVARIANTS`] and [`schema::POSTGRES_INVARIANTS`], in one
    /// read-only snapshot (the other lines go on writing meanwhile), on every board's rows
    /// (`newest` `None`) or the newest boards'.
    pub(super) fn check(&mut self, newest: Option<usize>) -> Result<(), StoreError> {
        self.ready()?;
        let name = self.name.as_str();
        let err = pg_err(name);
        let mut tx = self
            .client
            .build_transaction()
            .isolation_level(IsolationLevel::RepeatableRead)
            .read_only(true)
            .start()
            .map_err(&err)?;
        let version = read_version(&mut tx, name)?;
        let from_board: Option<i64> = match newest {
            None => None,
            Some(n) => tx
                .query_one(
                    "SELECT min(id) FROM (SELECT id FROM boards ORDER BY id DESC LIMIT $1) AS n",
                    &[&i64::try_from(n).unwrap_or(i64::MAX)],
                )
                .map_err(&err)?
                .get(0),
        };
        let mut broken = Vec::new();
        if version != super::SCHEMA_VERSION {
            broken.push(format!(
                "its schema_version table says {version}, not {}",
                super::SCHEMA_VERSION
            ));
        }
        for (what, sql) in schema::INVARIANTS.iter().chain(schema::POSTGRES_INVARIANTS) {
            let n: i64 = tx
                .query_one(&schema::rule(sql, Dialect::Postgres, from_board), &[])
                .map_err(&err)?
                .get(0);
            if n != 0 {
                broken.push(format!("{n} {what}"));
            }
        }
        tx.commit().map_err(&err)?;
        super::broken_rules(name, &broken)
    }

    pub(super) fn boards(
        &mut self,
        line: &str,
        which: &Which,
        limit: usize,
    ) -> Result<Vec<StoredBoard>, StoreError> {
        self.ready()?;
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(
            client,
            statements,
            "SELECT id, run_id, product, program_hash, calibration_hash, started_unix_s, \
             ended_unix_s, state, verdict, incomplete_reason, pads, line \
             FROM boards WHERE line = $1 AND ($2::text IS NULL OR product = $2) \
             AND (NOT $3 OR state = 'inspected') AND ($5::bigint IS NULL OR id = $5) \
             ORDER BY id DESC LIMIT $4",
        )
        .map_err(&err)?;
        let rows = client
            .query(
                &s,
                &[&line, &which.product, &which.inspected, &limit, &which.id],
            )
            .map_err(&err)?;
        let cams = prepared(
            client,
            statements,
            "SELECT camera, rows, missing_rows, missing_packets, damaged_packets \
             FROM board_cameras WHERE board_id = $1 ORDER BY camera",
        )
        .map_err(&err)?;
        let mut boards = Vec::with_capacity(rows.len());
        for r in rows {
            let id: i64 = r.get(0);
            let mut cameras = Vec::new();
            for c in client.query(&cams, &[&id]).map_err(&err)? {
                cameras.push(CameraLoss {
                    camera: u8::try_from(c.get::<_, i32>(0)).map_err(|_| StoreError::Corrupt {
                        store: name.clone(),
                        why: format!("board {id} has a camera {}", c.get::<_, i32>(0)),
                    })?,
                    rows: c.get::<_, i64>(1).max(0) as u64,
                    missing_rows: c.get::<_, i64>(2).max(0) as u64,
                    missing_packets: c.get::<_, i64>(3).max(0) as u64,
                    damaged_packets: c.get::<_, i64>(4).max(0) as u64,
                });
            }
            boards.push(StoredBoard {
                id,
                run_id: parse_run_id(name, r.get(1))?,
                line: r.get(11),
                product: r.get(2),
                program_hash: r.get(3),
                calibration_hash: r.get(4),
                started_unix_s: r.get(5),
                ended_unix_s: r.get(6),
                state: r.get(7),
                verdict: r.get(8),
                incomplete_reason: r.get(9),
                pads: r.get::<_, i32>(10).max(0) as u64,
                cameras,
            });
        }
        Ok(boards)
    }

    pub(super) fn pads(&mut self, board_id: i64) -> Result<Vec<PadRow>, StoreError> {
        self.ready()?;
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(client, statements, "SELECT 1 FROM boards WHERE id = $1").map_err(&err)?;
        if client.query_opt(&s, &[&board_id]).map_err(&err)?.is_none() {
            return Err(StoreError::UnknownBoard {
                store: name.clone(),
                id: board_id,
            });
        }
        let s = prepared(
            client,
            statements,
            "SELECT pad, name, level, class, volume_um3, volume_pct, area_mm2, area_pct, \
             height_um, height_pct, offset_x_um, offset_y_um, coverage, uncertainty_um3 \
             FROM pads WHERE board_id = $1 ORDER BY pad",
        )
        .map_err(&err)?;
        let rows = client.query(&s, &[&board_id]).map_err(&err)?;
        Ok(rows
            .iter()
            .map(|r| PadRow {
                pad: r.get::<_, i32>(0).max(0) as u32,
                name: r.get(1),
                level: r.get(2),
                class: r.get(3),
                volume_um3: r.get(4),
                volume_pct: r.get(5),
                area_mm2: r.get(6),
                area_pct: r.get(7),
                height_um: r.get(8),
                height_pct: r.get(9),
                offset_x_um: r.get(10),
                offset_y_um: r.get(11),
                coverage: r.get(12),
                uncertainty_um3: r.get(13),
            })
            .collect())
    }

    pub(super) fn pad_history(
        &mut self,
        line: &str,
        product: &str,
        pad: u32,
        boards: usize,
    ) -> Result<Vec<HistoryEntry>, StoreError> {
        self.ready()?;
        let limit = i64::try_from(boards).unwrap_or(i64::MAX);
        // A pad index past INTEGER's range is on no board.
        let Ok(pad) = i32::try_from(pad) else {
            return Ok(Vec::new());
        };
        let Pg {
            client,
            statements,
            name,
            ..
        } = self;
        let err = pg_err(name);
        let s = prepared(
            client,
            statements,
            "SELECT b.id, b.run_id, p.level, p.volume_pct \
             FROM (SELECT id, run_id FROM boards \
                   WHERE line = $4 AND product = $1 AND state = 'inspected' \
                   ORDER BY id DESC LIMIT $3) AS b \
             JOIN pads AS p ON p.board_id = b.id AND p.pad = $2 \
             ORDER BY b.id DESC",
        )
        .map_err(&err)?;
        let rows = client
            .query(&s, &[&product, &pad, &limit, &line])
            .map_err(&err)?;
        rows.iter()
            .map(|r| {
                Ok((
                    r.get::<_, i64>(0),
                    parse_run_id(name, r.get(1))?,
                    r.get::<_, String>(2),
                    r.get::<_, Option<f64>>(3),
                ))
            })
            .collect()
    }

    pub(super) fn prune_pads(
        &mut self,
        line: &str,
        before_unix_s: f64,
        limit: i64,
    ) -> Result<u64, StoreError> {
        self.ready()?;
        let err = pg_err(&self.name);
        let ids: Vec<i64> = self
            .client
            .query(
                "SELECT id FROM boards \
                 WHERE id >= (SELECT min(board_id) FROM pads) AND line = $2 \
                 AND ended_unix_s < $1 \
                 AND EXISTS (SELECT 1 FROM pads WHERE board_id = boards.id) \
                 ORDER BY id LIMIT $3",
                &[&before_unix_s, &line, &limit],
            )
            .map_err(&err)?
            .iter()
            .map(|r| r.get(0))
            .collect();
        let mut deleted = 0u64;
        for chunk in ids.chunks(PRUNE_BOARDS_PER_TRANSACTION) {
            let chunk = chunk.to_vec();
            let mut tx = self.client.transaction().map_err(&err)?;
            tx.execute("DELETE FROM pad_images WHERE board_id = ANY($1)", &[&chunk])
                .map_err(&err)?;
            tx.execute("DELETE FROM defects WHERE board_id = ANY($1)", &[&chunk])
                .map_err(&err)?;
            deleted += tx
                .execute("DELETE FROM pads WHERE board_id = ANY($1)", &[&chunk])
                .map_err(&err)?;
            tx.commit().map_err(&err)?;
        }
        Ok(deleted)
    }

    /// The tables of the store's schema with their indexes and TOAST, bytes
    /// (`pg_total_relation_size`).
    pub(super) fn bytes(&mut self) -> Result<u64, StoreError> {
        self.ready()?;
        let n: i64 = self
            .client
            .query_one(
                "SELECT coalesce(sum(pg_total_relation_size(c.oid)), 0)::bigint FROM pg_class AS c \
                 WHERE c.relnamespace = current_schema()::regnamespace AND c.relkind = 'r'",
                &[],
            )
            .map_err(pg_err(&self.name))?
            .get(0);
        Ok(n.max(0) as u64)
    }

    /// Makes schema `schema` of the database at `url` anew, empty (dropping one of that name
    /// with everything in it), or only drops it (`create` false). The benchmark's scratch
    /// space.
    pub(super) fn scratch_schema(
        url: &PgUrl,
        schema: &str,
        create: bool,
    ) -> Result<(), StoreError> {
        let name = url.to_string();
        let mut client = connect(&url.without_schema(), &name)?;
        let q = quote_ident(schema);
        let sql = if create {
            format!("DROP SCHEMA IF EXISTS {q} CASCADE; CREATE SCHEMA {q}")
        } else {
            format!("DROP SCHEMA IF EXISTS {q} CASCADE")
        };
        client.batch_execute(&sql).map_err(pg_err(&name))
    }
}

#[cfg(test)]
impl Pg {
    /// Runs `sql` (tests: SQL by hand against the store).
    pub(super) fn exec_raw(&mut self, sql: &str) -> Result<(), StoreError> {
        self.ready()?;
        self.client.batch_execute(sql).map_err(pg_err(&self.name))
    }

    /// Every row of `sql`, each value as [`super::tests::Raw`].
    pub(super) fn query_raw(
        &mut self,
        sql: &str,
    ) -> Result<Vec<Vec<super::tests::Raw>>, StoreError> {
        use super::tests::Raw;
        self.ready()?;
        let rows = self.client.query(sql, &[]).map_err(pg_err(&self.name))?;
        Ok(rows
            .iter()
            .map(|r| {
                r.columns()
                    .iter()
                    .enumerate()
                    .map(|(i, c)| {
                        let t = c.type_();
                        let v = if *t == Type::INT2 {
                            r.get::<_, Option<i16>>(i).map(|v| Raw::Int(v.into()))
                        } else if *t == Type::INT4 {
                            r.get::<_, Option<i32>>(i).map(|v| Raw::Int(v.into()))
                        } else if *t == Type::INT8 {
                            r.get::<_, Option<i64>>(i).map(Raw::Int)
                        } else if *t == Type::FLOAT8 {
                            r.get::<_, Option<f64>>(i).map(Raw::Real)
                        } else if *t == Type::FLOAT4 {
                            r.get::<_, Option<f32>>(i).map(|v| Raw::Real(v.into()))
                        } else if *t == Type::BOOL {
                            r.get::<_, Option<bool>>(i).map(|v| Raw::Int(v.into()))
                        } else {
                            r.get::<_, Option<String>>(i).map(Raw::Text)
                        };
                        v.unwrap_or(Raw::Null)
                    })
                    .collect()
            })
            .collect())
    }

    /// This connection's server process id (tests: to cut it).
    pub(super) fn backend_pid(&mut self) -> i32 {
        self.client
            .query_one("SELECT pg_backend_pid()", &[])
            .map(|r| r.get(0))
            .unwrap_or(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// How a board's pad rows go in fastest: binary COPY (what the store does) against one
    /// prepared INSERT per row and multi-row INSERTs of 500 rows, 6,000 pads a board, on the
    /// test server (`fsync` off: the commit's cost is left out, the same for all three).
    /// `cargo test -p dpsa-line -- --ignored --nocapture pad_rows_by` prints ms per board.
    #[test]
    #[ignore = "a measurement: half a minute"]
    fn pad_rows_by_copy_and_by_insert() {
        let location = super::super::pg_test_server::database();
        let super::super::Location::Postgres(url) = &location else {
            unreachable!()
        };
        let mut store = super::super::Store::open(&location, "l").unwrap();
        let ids: Vec<i64> = (0..60u64)
            .map(|run| {
                store
                    .begin_board(&BoardStart {
                        run_id: run,
                        product: "p".into(),
                        program_hash: "h".into(),
                        calibration_hash: "c".into(),
                        started_unix_s: run as f64,
                    })
                    .unwrap()
            })
            .collect();
        drop(store);
        let mut c = connect(url, "test").unwrap();
        let pads: Vec<(i32, String, f64)> = (0..6000)
            .map(|i| (i, format!("U{}-{}", i / 5, i % 5), 100.0 + f64::from(i % 7)))
            .collect();
        let mut boards = ids.into_iter();
        let mut time = |name: &str, f: &mut dyn FnMut(&mut Client, i64)| {
            let mut ms = Vec::new();
            for _ in 0..20 {
                let id = boards.next().unwrap();
                let t = std::time::Instant::now();
                f(&mut c, id);
                ms.push(t.elapsed().as_secs_f64() * 1e3);
            }
            ms.sort_by(f64::total_cmp);
            println!(
                "{name}: {:.1} ms per board of 6,000 pads (median of 20)",
                ms[10]
            );
        };
        let cols = "board_id, pad, name, level, volume_pct, coverage";
        time("binary COPY", &mut |c, id| {
            let mut tx = c.transaction().unwrap();
            let sink = tx
                .copy_in(&format!("COPY pads ({cols}) FROM STDIN (FORMAT binary)"))
                .unwrap();
            let types = [
                Type::INT8,
                Type::INT4,
                Type::TEXT,
                Type::TEXT,
                Type::FLOAT8,
                Type::FLOAT8,
            ];
            let mut w = BinaryCopyInWriter::new(sink, &types);
            for (pad, name, v) in &pads {
                w.write(&[&id, pad, name, &"pass", v, &1.0f64]).unwrap();
            }
            w.finish().unwrap();
            tx.commit().unwrap();
        });
        time("one INSERT per row", &mut |c, id| {
            let mut tx = c.transaction().unwrap();
            let s = tx
                .prepare(&format!(
                    "INSERT INTO pads ({cols}) VALUES ($1, $2, $3, 'pass', $4, 1)"
                ))
                .unwrap();
            for (pad, name, v) in &pads {
                tx.execute(&s, &[&id, pad, name, v]).unwrap();
            }
            tx.commit().unwrap();
        });
        time("INSERTs of 500 rows", &mut |c, id| {
            let mut tx = c.transaction().unwrap();
            let values: Vec<String> = (0..500)
                .map(|k| {
                    format!(
                        "($1, ${}, ${}, 'pass', ${}, 1)",
                        3 * k + 2,
                        3 * k + 3,
                        3 * k + 4
                    )
                })
                .collect();
            let s = tx
                .prepare(&format!(
                    "INSERT INTO pads ({cols}) VALUES {}",
                    values.join(", ")
                ))
                .unwrap();
            for chunk in pads.chunks(500) {
                let mut params: Vec<&(dyn postgres::types::ToSql + Sync)> = vec![&id];
                for (pad, name, v) in chunk {
                    params.push(pad);
                    params.push(name);
                    params.push(v);
                }
                tx.execute(&s, &params).unwrap();
            }
            tx.commit().unwrap();
        });
    }
}
