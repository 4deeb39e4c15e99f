//! The store on SQLite: one file, WAL, the schema's version in `PRAGMA user_version`.

use super::review::{
    family_reviews, Decision, FamilyReviews, ImageValues, Review, FAMILY_REVIEWS_SQL,
    IMAGE_COLUMNS, INSERT_REVIEW_SQL, REVIEW_COLUMNS,
};
use super::schema::{self, Dialect, Step};
use super::{
    insert_print_sql, parse_run_id, real, run_id_text, select_prints_sql, Beside, BoardStart,
    CameraLoss, HistoryEntry, Outcome, PadRow, PrintValues, StencilClean, StoreError, StoredBoard,
    StoredPrint, Which, PRINT_REALS, PRUNE_BOARDS_PER_TRANSACTION,
};
use rusqlite::{params, Connection, OptionalExtension, TransactionBehavior};
use std::path::Path;
use std::time::Duration;

/// How long a statement waits for another connection's lock before it gives up (busy).
const BUSY_TIMEOUT: Duration = Duration::from_secs(10);

/// One connection to one store file.
#[derive(Debug)]
pub(super) struct Sqlite {
    pub(super) conn: Connection,
    /// The file, as errors name it.
    name: String,
}

/// Maps an SQLite error to a [`StoreError`] of the store `name`: a damaged file (or one that
/// is no database) becomes [`StoreError::Corrupt`].
fn sql_err(name: &str, source: rusqlite::Error) -> StoreError {
    use rusqlite::ErrorCode::{DatabaseCorrupt, NotADatabase};
    match source.sqlite_error_code() {
        Some(DatabaseCorrupt | NotADatabase) => StoreError::Corrupt {
            store: name.to_owned(),
            why: source.to_string(),
        },
        _ => StoreError::Sqlite {
            store: name.to_owned(),
            source,
        },
    }
}

/// `PRAGMA user_version`, which must be a version (not negative).
fn user_version(conn: &Connection, name: &str) -> Result<u32, StoreError> {
    let v: i64 = conn
        .pragma_query_value(None, "user_version", |r| r.get(0))
        .map_err(|e| sql_err(name, e))?;
    u32::try_from(v).map_err(|_| StoreError::Corrupt {
        store: name.to_owned(),
        why: format!("its schema version (user_version) is {v}"),
    })
}

/// Is `e` a UNIQUE (or primary key) constraint refusing a row?
fn is_unique_violation(e: &rusqlite::Error) -> bool {
    e.sqlite_error().is_some_and(|f| {
        f.extended_code == rusqlite::ffi::SQLITE_CONSTRAINT_UNIQUE
            || f.extended_code == rusqlite::ffi::SQLITE_CONSTRAINT_PRIMARYKEY
    })
}

const INSERT_PAD: &str = "INSERT INTO pads (board_id, pad, name, level, class, volume_um3, volume_pct, \
     area_mm2, area_pct, height_um, height_pct, offset_x_um, offset_y_um, coverage, uncertainty_um3) \
     VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15)";

/// Adds board `?2`'s pads (of product `?1`, line `?3`) that have a volume to the line's
/// running aggregates.
const UPSERT_PAD_STATS: &str = "INSERT INTO pad_stats (line, product, pad, boards, sum_volume_pct, \
     sum_sq_volume_pct, fails, warns, last_board_id) \
     SELECT ?3, ?1, pad, 1, volume_pct, volume_pct * volume_pct, level = 'fail', level = 'warn', board_id \
     FROM pads WHERE board_id = ?2 AND volume_pct IS NOT NULL \
     ON CONFLICT (line, product, pad) DO UPDATE SET \
     boards = boards + 1, \
     sum_volume_pct = sum_volume_pct + excluded.sum_volume_pct, \
     sum_sq_volume_pct = sum_sq_volume_pct + excluded.sum_sq_volume_pct, \
     fails = fails + excluded.fails, \
     warns = warns + excluded.warns, \
     last_board_id = excluded.last_board_id";

impl Sqlite {
    /// Opens (creating it and its directory) and migrates the store file `path`; see
    /// [`super::Store::open`].
    ///
    /// The connection is in WAL mode with `synchronous = NORMAL`, foreign keys on and a busy
    /// timeout of 10 s. `NORMAL` does not sync the disk at every commit, only when the WAL is
    /// checkpointed into the database; with WAL that is safe: a commit appends its pages to
    /// the WAL and a crash or power cut can lose at most the last transactions not yet synced
    /// (each one whole, never half), never corrupt the file.
    pub(super) fn open(path: &Path, migrations: &[Step]) -> Result<Sqlite, StoreError> {
        let name = path.display().to_string();
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|source| StoreError::Io {
                store: name.clone(),
                source,
            })?;
        }
        let err = |e| sql_err(&name, e);
        let mut conn = Connection::open(path).map_err(err)?;
        conn.busy_timeout(BUSY_TIMEOUT).map_err(err)?;
        let known = migrations.len() as u32;
        let found = user_version(&conn, &name)?;
        if found > known {
            return Err(StoreError::NewerSchema {
                store: name,
                found,
                known,
            });
        }
        // Switching a new file to WAL takes an exclusive lock, and SQLite answers "busy" at
        // once (its busy timeout not waited) when another connection is switching it too:
        // two programs opening a new store together. Tried again within the busy timeout.
        let asked = std::time::Instant::now();
        let mode: String = loop {
            match conn.pragma_update_and_check(None, "journal_mode", "WAL", |r| r.get(0)) {
                Err(e)
                    if e.sqlite_error_code() == Some(rusqlite::ErrorCode::DatabaseBusy)
                        && asked.elapsed() < BUSY_TIMEOUT =>
                {
                    std::thread::sleep(Duration::from_millis(20));
                }
                other => break other.map_err(err)?,
            }
        };
        if !mode.eq_ignore_ascii_case("wal") {
            return Err(StoreError::Invalid {
                store: name,
                why: format!("SQLite could not put it in WAL mode (journal mode is {mode})"),
            });
        }
        conn.pragma_update(None, "synchronous", "NORMAL")
            .map_err(err)?;
        conn.set_prepared_statement_cache_capacity(32);
        if found < known {
            // Off while the schema changes: a step that makes a table anew drops the old one,
            // which with foreign keys on would delete its children's rows. PRAGMA
            // foreign_keys cannot change inside a transaction, hence here.
            conn.pragma_update(None, "foreign_keys", "OFF")
                .map_err(err)?;
            Self::migrate(&mut conn, &name, migrations)?;
        }
        conn.pragma_update(None, "foreign_keys", "ON")
            .map_err(err)?;
        Ok(Sqlite { conn, name })
    }

    /// Opens an existing store file for reading only (SQLite's read-only mode: no write, no
    /// migration, no file made); its schema must be this program's version.
    pub(super) fn open_read_only(path: &Path) -> Result<Sqlite, StoreError> {
        let name = path.display().to_string();
        if !path.is_file() {
            return Err(StoreError::Io {
                store: name,
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "no store file"),
            });
        }
        let err = |e| sql_err(&name, e);
        let conn = Connection::open_with_flags(
            path,
            rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY | rusqlite::OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(err)?;
        conn.busy_timeout(BUSY_TIMEOUT).map_err(err)?;
        let found = user_version(&conn, &name)?;
        super::check_reader_version(&name, found)?;
        Ok(Sqlite { conn, name })
    }

    /// Applies the migrations the store lacks, one transaction each. The version is read
    /// again inside each (write-locked) transaction, so two programs opening a new store at
    /// once do not both migrate it. Each step must leave no row pointing to a missing board
    /// (`PRAGMA foreign_key_check`, as foreign keys are off).
    fn migrate(conn: &mut Connection, name: &str, migrations: &[Step]) -> Result<(), StoreError> {
        let err = |e| sql_err(name, e);
        let known = migrations.len() as u32;
        loop {
            let tx = conn
                .transaction_with_behavior(TransactionBehavior::Immediate)
                .map_err(err)?;
            let v = user_version(&tx, name)?;
            if v > known {
                return Err(StoreError::NewerSchema {
                    store: name.to_owned(),
                    found: v,
                    known,
                });
            }
            if v == known {
                return tx.commit().map_err(err);
            }
            tx.execute_batch(&migrations[v as usize].sql(Dialect::Sqlite))
                .map_err(err)?;
            let orphans: i64 = tx
                .query_row("SELECT count(*) FROM pragma_foreign_key_check", [], |r| {
                    r.get(0)
                })
                .map_err(err)?;
            if orphans > 0 {
                return Err(StoreError::Corrupt {
                    store: name.to_owned(),
                    why: format!(
                        "migrating it to version {} left {orphans} row(s) pointing to missing rows",
                        v + 1
                    ),
                });
            }
            tx.pragma_update(None, "user_version", v + 1).map_err(err)?;
            tx.commit().map_err(err)?;
        }
    }

    fn err(&self) -> impl Fn(rusqlite::Error) -> StoreError + '_ {
        |e| sql_err(&self.name, e)
    }

    pub(super) fn schema_version(&mut self) -> Result<u32, StoreError> {
        user_version(&self.conn, &self.name)
    }

    pub(super) fn begin_board(&mut self, line: &str, b: &BoardStart) -> Result<i64, StoreError> {
        let result = self
            .conn
            .prepare_cached(
                "INSERT INTO boards (run_id, product, program_hash, calibration_hash, \
                 started_unix_s, state, line) VALUES (?1, ?2, ?3, ?4, ?5, 'open', ?6)",
            )
            .and_then(|mut s| {
                s.execute(params![
                    run_id_text(b.run_id),
                    b.product,
                    b.program_hash,
                    b.calibration_hash,
                    b.started_unix_s,
                    line
                ])
            });
        match result {
            Ok(_) => Ok(self.conn.last_insert_rowid()),
            Err(e) if is_unique_violation(&e) => Err(StoreError::Duplicate {
                store: self.name.clone(),
                line: line.to_owned(),
                run_id: b.run_id,
            }),
            Err(e) => Err(sql_err(&self.name, e)),
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
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
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
                    store: name.to_owned(),
                    id,
                })
            }
            Some((state, _)) if state != "open" => {
                return Err(StoreError::NotOpen {
                    store: name.to_owned(),
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
                        .and_then(|mut s| s.execute(params![product, id, line]))
                        .map_err(err)?;
                    let mut s = tx
                        .prepare_cached(&format!(
                            "INSERT INTO pad_images (board_id, pad, {IMAGE_COLUMNS}) \
                             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)"
                        ))
                        .map_err(err)?;
                    for v in images {
                        s.execute(params![
                            id, v.pad, v.family, v.x0_mm, v.y0_mm, v.pitch_mm, v.nx, v.ny,
                            v.lsb_um, v.heights, v.outline
                        ])
                        .map_err(err)?;
                    }
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
        if let Some(v) = print {
            let mut p: Vec<&dyn rusqlite::ToSql> = vec![&id];
            p.extend(v.reals.iter().map(|r| r as &dyn rusqlite::ToSql));
            p.extend(v.counts.iter().map(|r| r as &dyn rusqlite::ToSql));
            p.extend(v.flags.iter().map(|r| r as &dyn rusqlite::ToSql));
            p.push(&v.reason);
            tx.prepare_cached(&insert_print_sql('?'))
                .and_then(|mut s| s.execute(rusqlite::params_from_iter(p)))
                .map_err(err)?;
        }
        tx.commit().map_err(err)
    }

    pub(super) fn pad_image(
        &mut self,
        board_id: i64,
        pad: u32,
    ) -> Result<Option<ImageValues>, StoreError> {
        let name = self.name.as_str();
        self.conn
            .prepare_cached(&format!(
                "SELECT {IMAGE_COLUMNS} FROM pad_images WHERE board_id = ?1 AND pad = ?2"
            ))
            .and_then(|mut s| {
                s.query_row(params![board_id, pad], |r| {
                    Ok(ImageValues {
                        pad,
                        family: r.get(0)?,
                        x0_mm: r.get(1)?,
                        y0_mm: r.get(2)?,
                        pitch_mm: r.get(3)?,
                        nx: r.get(4)?,
                        ny: r.get(5)?,
                        lsb_um: r.get(6)?,
                        heights: r.get(7)?,
                        outline: r.get(8)?,
                    })
                })
                .optional()
            })
            .map_err(|e| sql_err(name, e))
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
        let n = self
            .conn
            .prepare_cached(INSERT_REVIEW_SQL)
            .and_then(|mut s| {
                s.execute(params![
                    board_id,
                    pad,
                    decision.name(),
                    reviewer,
                    at_unix_s,
                    note,
                    line
                ])
            })
            .map_err(self.err())?;
        Ok((n == 1).then(|| self.conn.last_insert_rowid()))
    }

    pub(super) fn reviews(&mut self, board_id: i64) -> Result<Vec<Review>, StoreError> {
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
        let mut s = self
            .conn
            .prepare_cached(&format!(
                "SELECT {REVIEW_COLUMNS} FROM reviews WHERE board_id = ?1 ORDER BY pad, id"
            ))
            .map_err(err)?;
        let rows = s
            .query_map([board_id], |r| {
                let d: String = r.get(4)?;
                Ok(Review {
                    id: r.get(0)?,
                    board_id: r.get(1)?,
                    pad: r.get(2)?,
                    family: r.get(3)?,
                    decision: Decision::from_name(&d).ok_or_else(|| {
                        rusqlite::Error::FromSqlConversionFailure(
                            4,
                            rusqlite::types::Type::Text,
                            format!("a decision {d:?}").into(),
                        )
                    })?,
                    reviewer: r.get(5)?,
                    reviewed_unix_s: r.get(6)?,
                    note: r.get(7)?,
                })
            })
            .map_err(err)?;
        rows.collect::<Result<_, _>>().map_err(err)
    }

    pub(super) fn family_reviews(&mut self, line: &str) -> Result<Vec<FamilyReviews>, StoreError> {
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
        let mut s = self.conn.prepare_cached(FAMILY_REVIEWS_SQL).map_err(err)?;
        let rows = s
            .query_map([line], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
            .map_err(err)?;
        Ok(family_reviews(rows.collect::<Result<_, _>>().map_err(err)?))
    }

    pub(super) fn record_clean(
        &mut self,
        line: &str,
        product: &str,
        cleaned_unix_s: f64,
        source: &str,
        note: Option<&str>,
    ) -> Result<i64, StoreError> {
        self.conn
            .prepare_cached(
                "INSERT INTO stencil_cleans (line, product, cleaned_unix_s, source, note) \
                 VALUES (?1, ?2, ?3, ?4, ?5)",
            )
            .and_then(|mut s| s.execute(params![line, product, cleaned_unix_s, source, note]))
            .map_err(self.err())?;
        Ok(self.conn.last_insert_rowid())
    }

    pub(super) fn cleans(
        &mut self,
        line: &str,
        product: &str,
        limit: usize,
    ) -> Result<Vec<StencilClean>, StoreError> {
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
        let mut s = self
            .conn
            .prepare_cached(
                "SELECT id, product, cleaned_unix_s, source, note FROM stencil_cleans \
                 WHERE line = ?1 AND product = ?2 ORDER BY cleaned_unix_s DESC, id DESC LIMIT ?3",
            )
            .map_err(err)?;
        let rows = s
            .query_map(params![line, product, limit], |r| {
                Ok(StencilClean {
                    id: r.get(0)?,
                    product: r.get(1)?,
                    cleaned_unix_s: r.get(2)?,
                    source: r.get(3)?,
                    note: r.get(4)?,
                })
            })
            .map_err(err)?;
        rows.collect::<Result<_, _>>().map_err(err)
    }

    pub(super) fn prints(
        &mut self,
        line: &str,
        product: &str,
        limit: usize,
    ) -> Result<Vec<StoredPrint>, StoreError> {
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
        let mut s = self
            .conn
            .prepare_cached(&select_prints_sql('?'))
            .map_err(err)?;
        let rows = s
            .query_map(params![line, product, limit], |r| {
                let mut reals = [None; PRINT_REALS];
                for (k, v) in reals.iter_mut().enumerate() {
                    *v = r.get(2 + k)?;
                }
                let at = 2 + PRINT_REALS;
                Ok((
                    r.get::<_, i64>(0)?,
                    r.get::<_, String>(1)?,
                    PrintValues {
                        reals,
                        counts: [r.get(at)?, r.get(at + 1)?],
                        flags: [r.get(at + 2)?, r.get(at + 3)?],
                        reason: r.get(at + 4)?,
                    },
                ))
            })
            .map_err(err)?;
        let mut out = Vec::new();
        for row in rows {
            let (board_id, run, v) = row.map_err(err)?;
            out.push(StoredPrint {
                board_id,
                run_id: parse_run_id(name, &run)?,
                print: v.row(),
            });
        }
        Ok(out)
    }

    pub(super) fn recover(
        &mut self,
        line: &str,
        reason: &str,
        now_unix_s: f64,
    ) -> Result<Vec<u64>, StoreError> {
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(err)?;
        let texts: Vec<String> = {
            let mut s = tx
                .prepare("SELECT run_id FROM boards WHERE state = 'open' AND line = ?1 ORDER BY id")
                .map_err(err)?;
            let rows = s.query_map([line], |r| r.get(0)).map_err(err)?;
            rows.collect::<Result<_, _>>().map_err(err)?
        };
        tx.execute(
            "UPDATE boards SET state = 'incomplete', incomplete_reason = ?1, ended_unix_s = ?2 \
             WHERE state = 'open' AND line = ?3",
            params![reason, now_unix_s, line],
        )
        .map_err(err)?;
        tx.commit().map_err(err)?;
        texts.iter().map(|t| parse_run_id(name, t)).collect()
    }

    /// The whole store (`newest` `None`): `PRAGMA integrity_check` (every page, every
    /// index), `PRAGMA foreign_key_check`, then the rules of [`schema::INVARIANTS`] in one
    /// read transaction. The newest boards only: the rules on their rows (the pages are not
    /// read: SQLite has no check of part of a file).
    pub(super) fn check(&mut self, newest: Option<usize>) -> Result<(), StoreError> {
        if newest.is_none() {
            self.check_pages()?;
        }
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
        // One snapshot for all the rules (a writer may go on meanwhile).
        let tx = self.conn.transaction().map_err(err)?;
        let from_board: Option<i64> = match newest {
            None => None,
            Some(n) => tx
                .query_row(
                    "SELECT min(id) FROM (SELECT id FROM boards ORDER BY id DESC LIMIT ?1)",
                    [i64::try_from(n).unwrap_or(i64::MAX)],
                    |r| r.get(0),
                )
                .map_err(err)?,
        };
        let mut broken = Vec::new();
        for (what, sql) in schema::INVARIANTS {
            let n: i64 = tx
                .query_row(&schema::rule(sql, Dialect::Sqlite, from_board), [], |r| {
                    r.get(0)
                })
                .map_err(err)?;
            if n != 0 {
                broken.push(format!("{n} {what}"));
            }
        }
        tx.commit().map_err(err)?;
        super::broken_rules(name, &broken)
    }

    /// `PRAGMA integrity_check` and `PRAGMA foreign_key_check`.
    fn check_pages(&mut self) -> Result<(), StoreError> {
        let corrupt = |why: String| StoreError::Corrupt {
            store: self.name.clone(),
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

    pub(super) fn boards(
        &mut self,
        line: &str,
        which: &Which,
        limit: usize,
    ) -> Result<Vec<StoredBoard>, StoreError> {
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let mut s = self
            .conn
            .prepare_cached(
                "SELECT id, run_id, product, program_hash, calibration_hash, started_unix_s, \
                 ended_unix_s, state, verdict, incomplete_reason, pads, line \
                 FROM boards WHERE line = ?1 AND (?2 IS NULL OR product = ?2) \
                 AND (?3 = 0 OR state = 'inspected') AND (?5 IS NULL OR id = ?5) \
                 ORDER BY id DESC LIMIT ?4",
            )
            .map_err(self.err())?;
        let rows = s
            .query_map(
                params![line, which.product, which.inspected, limit, which.id],
                |r| {
                    Ok((
                        r.get::<_, String>(1)?,
                        StoredBoard {
                            id: r.get(0)?,
                            run_id: 0,
                            line: r.get(11)?,
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
                },
            )
            .map_err(self.err())?;
        let mut boards = Vec::new();
        for row in rows {
            let (run_id, mut board) = row.map_err(self.err())?;
            board.run_id = parse_run_id(&self.name, &run_id)?;
            boards.push(board);
        }
        drop(s);
        for board in &mut boards {
            board.cameras = self.cameras(board.id)?;
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

    pub(super) fn pads(&mut self, board_id: i64) -> Result<Vec<PadRow>, StoreError> {
        let known = self
            .conn
            .prepare_cached("SELECT 1 FROM boards WHERE id = ?1")
            .and_then(|mut s| s.exists([board_id]))
            .map_err(self.err())?;
        if !known {
            return Err(StoreError::UnknownBoard {
                store: self.name.clone(),
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

    pub(super) fn pad_history(
        &mut self,
        line: &str,
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
                       WHERE line = ?4 AND product = ?1 AND state = 'inspected' \
                       ORDER BY id DESC LIMIT ?3) AS b \
                 JOIN pads AS p ON p.board_id = b.id AND p.pad = ?2 \
                 ORDER BY b.id DESC",
            )
            .map_err(self.err())?;
        let rows = s
            .query_map(params![product, pad, limit, line], |r| {
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
            out.push((id, parse_run_id(&self.name, &run_id)?, level, volume_pct));
        }
        Ok(out)
    }

    pub(super) fn prune_pads(
        &mut self,
        line: &str,
        before_unix_s: f64,
        limit: i64,
    ) -> Result<u64, StoreError> {
        let name = self.name.as_str();
        let err = |e| sql_err(name, e);
        let ids: Vec<i64> = {
            let mut s = self
                .conn
                .prepare(
                    "SELECT id FROM boards \
                     WHERE id >= (SELECT min(board_id) FROM pads) AND line = ?2 \
                     AND ended_unix_s < ?1 \
                     AND EXISTS (SELECT 1 FROM pads WHERE board_id = boards.id) \
                     ORDER BY id LIMIT ?3",
                )
                .map_err(err)?;
            let rows = s
                .query_map(params![before_unix_s, line, limit], |r| r.get(0))
                .map_err(err)?;
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
                let mut images = tx
                    .prepare_cached("DELETE FROM pad_images WHERE board_id = ?1")
                    .map_err(err)?;
                for id in chunk {
                    images.execute([id]).map_err(err)?;
                    defects.execute([id]).map_err(err)?;
                    deleted += pads.execute([id]).map_err(err)? as u64;
                }
            }
            tx.commit().map_err(err)?;
        }
        Ok(deleted)
    }

    /// Copies the WAL into the database and empties it (`PRAGMA wal_checkpoint(TRUNCATE)`).
    pub(super) fn checkpoint(&mut self) -> Result<(), StoreError> {
        self.conn
            .query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |_| Ok(()))
            .map_err(self.err())
    }

    /// The store file and its WAL, bytes.
    pub(super) fn bytes(&mut self, path: &Path) -> Result<u64, StoreError> {
        let mut wal = path.to_owned().into_os_string();
        wal.push("-wal");
        let mut bytes = 0;
        for file in [path.as_os_str(), wal.as_os_str()] {
            match std::fs::metadata(file) {
                Ok(m) => bytes += m.len(),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(source) => {
                    return Err(StoreError::Io {
                        store: self.name.clone(),
                        source,
                    })
                }
            }
        }
        Ok(bytes)
    }
}

#[cfg(test)]
impl Sqlite {
    /// Runs `sql` (tests: SQL by hand against the store).
    pub(super) fn exec_raw(&mut self, sql: &str) -> Result<(), StoreError> {
        self.conn.execute_batch(sql).map_err(self.err())
    }

    /// Every row of `sql`, each value as [`super::tests::Raw`].
    pub(super) fn query_raw(
        &mut self,
        sql: &str,
    ) -> Result<Vec<Vec<super::tests::Raw>>, StoreError> {
        use super::tests::Raw;
        use rusqlite::types::ValueRef;
        let mut s = self.conn.prepare(sql).map_err(self.err())?;
        let n = s.column_count();
        let rows = s
            .query_map([], |r| {
                (0..n)
                    .map(|i| {
                        Ok(match r.get_ref(i)? {
                            ValueRef::Null => Raw::Null,
                            ValueRef::Integer(v) => Raw::Int(v),
                            ValueRef::Real(v) => Raw::Real(v),
                            ValueRef::Text(t) => Raw::Text(String::from_utf8_lossy(t).into()),
                            ValueRef::Blob(_) => Raw::Text("(blob)".into()),
                        })
                    })
                    .collect::<Result<Vec<_>, rusqlite::Error>>()
            })
            .map_err(self.err())?;
        rows.collect::<Result<_, _>>().map_err(self.err())
    }
}
