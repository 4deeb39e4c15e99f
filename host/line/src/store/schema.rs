//! The store's schema in one place: the migration steps, in order, for both dialects.
//!
//! A step both dialects run is one text in the SQL they share, with the few words in which
//! they differ written as `{word}` ([`WORDS`]: the SQLite and the PostgreSQL spelling side by
//! side). A step only one text cannot say (SQLite cannot drop a constraint or change a primary
//! key in place, PostgreSQL can) is given as two texts, one above the other, that end in the
//! same tables, columns and indexes; a test compares what the two backends hold after every
//! step (`both_backends_hold_the_same_tables_columns_and_indexes`).
//!
//! The version a store is at: SQLite's `PRAGMA user_version`; on PostgreSQL the one row of
//! [`POSTGRES_VERSION_TABLE`]. Never edit a step that has shipped: add the next.

use std::borrow::Cow;

/// Which SQL.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Dialect {
    /// SQLite (rusqlite's bundled library).
    Sqlite,
    /// PostgreSQL 12 or later.
    Postgres,
}

/// The words the dialects spell differently: `(word, SQLite, PostgreSQL)`.
///
/// - `id`: the store's row id. SQLite's `INTEGER PRIMARY KEY` is the rowid itself;
///   PostgreSQL's identity column is its equivalent (values given by the database, never by
///   an insert).
/// - `int64`: a 64-bit count or id. SQLite's INTEGER holds 64 bits, PostgreSQL's only 32.
///   (Columns written plain `INTEGER` hold small numbers, a pad or camera index, and are
///   32-bit on PostgreSQL.)
/// - `real`: a double. SQLite's REAL is 8 bytes, PostgreSQL's REAL only 4.
/// - `run_id_is_hex`: 16 lowercase hex digits; SQLite has GLOB, PostgreSQL regular
///   expressions.
/// - `blob`, `bytes_of`: bytes and their count. SQLite's BLOB and `length()`, PostgreSQL's
///   BYTEA and `octet_length()`.
/// - `without_rowid`: SQLite keeps a WITHOUT ROWID table in its primary key's B-tree;
///   PostgreSQL's tables are heaps with the primary key an index beside them (nothing to say).
pub(crate) const WORDS: &[(&str, &str, &str)] = &[
    (
        "id",
        "INTEGER PRIMARY KEY",
        "BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY",
    ),
    ("int64", "INTEGER", "BIGINT"),
    ("real", "REAL", "DOUBLE PRECISION"),
    (
        "run_id_is_hex",
        "length(run_id) = 16 AND run_id NOT GLOB '*[^0-9a-f]*'",
        "run_id ~ '^[0-9a-f]{16}$'",
    ),
    ("blob", "BLOB", "BYTEA"),
    ("bytes_of", "length", "octet_length"),
    ("without_rowid", " WITHOUT ROWID", ""),
];

/// Fills in the `{word}`s of `template` for `dialect`, in one pass (a spelling is never read
/// again for words: PostgreSQL's `{16}` stays). A `{` that opens no known word is kept as it
/// is, so the database refuses the text rather than this program guessing.
pub(crate) fn render(template: &str, dialect: Dialect) -> String {
    let mut out = String::with_capacity(template.len() + 256);
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let after = &rest[open + 1..];
        let word = after
            .find('}')
            .map(|close| &after[..close])
            .and_then(|w| WORDS.iter().find(|(name, _, _)| *name == w));
        match word {
            Some((name, sqlite, postgres)) => {
                out.push_str(match dialect {
                    Dialect::Sqlite => sqlite,
                    Dialect::Postgres => postgres,
                });
                rest = &after[name.len() + 1..];
            }
            None => {
                out.push('{');
                rest = after;
            }
        }
    }
    out.push_str(rest);
    out
}

/// Rule `sql` of [`INVARIANTS`] or [`POSTGRES_INVARIANTS`] in `dialect`, on the rows of the
/// boards from id `from_board` on (`None`: every board).
pub(crate) fn rule(sql: &str, dialect: Dialect, from_board: Option<i64>) -> String {
    // The lowest id both databases read as a 64-bit integer literal (`-9223372036854775808`
    // is a numeric in PostgreSQL: a minus before a number too large).
    let from = from_board.unwrap_or(i64::MIN + 1);
    render(sql, dialect).replace("{from_board}", &from.to_string())
}

/// One migration step: takes a store from version `i` to `i + 1`.
#[derive(Clone, Debug)]
pub(crate) enum Step {
    /// One text for both dialects, with `{word}`s ([`render`]).
    Both(Cow<'static, str>),
    /// A text per dialect, ending in the same schema.
    Each {
        /// For SQLite.
        sqlite: Cow<'static, str>,
        /// For PostgreSQL.
        postgres: Cow<'static, str>,
    },
}

impl Step {
    /// The step's SQL for `dialect`.
    pub(crate) fn sql(&self, dialect: Dialect) -> String {
        match (self, dialect) {
            (Step::Both(t), d) => render(t, d),
            (Step::Each { sqlite, .. }, Dialect::Sqlite) => sqlite.to_string(),
            (Step::Each { postgres, .. }, Dialect::Postgres) => postgres.to_string(),
        }
    }
}

/// The migrations, in order: `MIGRATIONS[i]` takes a store from version `i` to `i + 1`.
pub(crate) const MIGRATIONS: &[Step] = &[
    Step::Both(Cow::Borrowed(V1)),
    Step::Each {
        sqlite: Cow::Borrowed(V2_SQLITE),
        postgres: Cow::Borrowed(V2_POSTGRES),
    },
    Step::Both(Cow::Borrowed(V3)),
    Step::Both(Cow::Borrowed(V4)),
];

/// Version 1: the tables of the module documentation, one line's.
///
/// For SQLite this renders, byte for byte, the text version 1 shipped with (checked by a
/// test), so a store made then and one made now hold the same schema.
///
/// The CHECKs of the per-pad tables compare with `=` joined by OR, never `IN (...)`: SQLite
/// evaluates a CHECK's `IN` list by building a small temporary table every row, which more
/// than doubled the time of a pad insert (measured: 53 against 23 ms per board of 6,000 pads).
pub(crate) const V1: &str = "
CREATE TABLE boards (
    id                {id},
    run_id            TEXT NOT NULL UNIQUE
                      CHECK ({run_id_is_hex}),
    product           TEXT NOT NULL,
    program_hash      TEXT NOT NULL,
    calibration_hash  TEXT NOT NULL,
    started_unix_s    {real} NOT NULL,
    ended_unix_s      {real},
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
    board_id        {int64} NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    camera          INTEGER NOT NULL CHECK (camera BETWEEN 0 AND 255),
    rows            {int64} NOT NULL CHECK (rows >= 0),
    missing_rows    {int64} NOT NULL CHECK (missing_rows >= 0),
    missing_packets {int64} NOT NULL CHECK (missing_packets >= 0),
    damaged_packets {int64} NOT NULL CHECK (damaged_packets >= 0),
    PRIMARY KEY (board_id, camera)
){without_rowid};

CREATE TABLE pads (
    board_id        {int64} NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    pad             INTEGER NOT NULL CHECK (pad >= 0),
    name            TEXT NOT NULL,
    level           TEXT NOT NULL CHECK (level = 'pass' OR level = 'warn' OR level = 'fail'),
    class           TEXT,
    volume_um3      {real},
    volume_pct      {real},
    area_mm2        {real},
    area_pct        {real},
    height_um       {real},
    height_pct      {real},
    offset_x_um     {real},
    offset_y_um     {real},
    coverage        {real} NOT NULL CHECK (coverage BETWEEN 0 AND 1),
    uncertainty_um3 {real},
    PRIMARY KEY (board_id, pad)
){without_rowid};

CREATE TABLE defects (
    board_id {int64} NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    pad      INTEGER NOT NULL,
    level    TEXT NOT NULL CHECK (level = 'warn' OR level = 'fail'),
    class    TEXT,
    PRIMARY KEY (board_id, pad)
){without_rowid};

CREATE TABLE alarms (
    id            {id},
    raised_unix_s {real} NOT NULL,
    product       TEXT NOT NULL,
    pad           INTEGER,
    rule          TEXT NOT NULL,
    message       TEXT NOT NULL
);

CREATE TABLE pad_stats (
    product           TEXT NOT NULL,
    pad               INTEGER NOT NULL,
    boards            {int64} NOT NULL,
    sum_volume_pct    {real} NOT NULL,
    sum_sq_volume_pct {real} NOT NULL,
    fails             {int64} NOT NULL,
    warns             {int64} NOT NULL,
    last_board_id     {int64} NOT NULL,
    PRIMARY KEY (product, pad)
){without_rowid};
";

/// Version 2, SQLite: many lines in one store. `boards` gains a last column `line` and
/// `pad_stats` a first one (the boards and aggregates of a version-1 store are line
/// `line-1`'s, [`crate::store::DEFAULT_LINE`]); a run id is unique per line, no longer in the
/// whole store; `pad_stats` is kept per line, keyed `(line, product, pad)`.
///
/// `line` leads `pad_stats` because its key does: a WITHOUT ROWID table whose primary key is
/// not its first columns in order is reported "NULL value in pad_stats.boards" by the
/// `PRAGMA integrity_check` of SQLite 3.40 (Debian 12's `sqlite3`; the bundled library is
/// right), a false alarm to anyone checking the file by hand.
///
/// SQLite cannot drop v1's `UNIQUE` on `run_id` nor change `pad_stats`' primary key in place,
/// so both tables are made anew and their rows copied (ids kept), the documented way: foreign
/// keys are off while a store migrates, so dropping the old `boards` deletes no pad (the
/// children's `REFERENCES boards` name the new table once it is renamed), and the migration
/// runs `PRAGMA foreign_key_check` before it commits. `boards` is a row per board: copying it
/// is quick even for years of boards; `pads` is not touched.
pub(crate) const V2_SQLITE: &str = "
CREATE TABLE boards_v2 (
    id                INTEGER PRIMARY KEY,
    run_id            TEXT NOT NULL
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
    line              TEXT NOT NULL CHECK (line <> ''),
    CHECK ((state = 'open' AND ended_unix_s IS NULL AND verdict IS NULL
                AND incomplete_reason IS NULL AND pads = 0)
        OR (state = 'inspected' AND ended_unix_s IS NOT NULL AND verdict IS NOT NULL
                AND incomplete_reason IS NULL)
        OR (state = 'incomplete' AND ended_unix_s IS NOT NULL AND verdict IS NULL
                AND incomplete_reason IS NOT NULL AND pads = 0))
);
INSERT INTO boards_v2 (id, run_id, product, program_hash, calibration_hash, started_unix_s,
                       ended_unix_s, state, verdict, incomplete_reason, pads, line)
    SELECT id, run_id, product, program_hash, calibration_hash, started_unix_s,
           ended_unix_s, state, verdict, incomplete_reason, pads, 'line-1' FROM boards;
DROP TABLE boards;
ALTER TABLE boards_v2 RENAME TO boards;
CREATE INDEX boards_by_product ON boards (product, state, id);
CREATE INDEX boards_by_end ON boards (ended_unix_s);
CREATE INDEX boards_open ON boards (id) WHERE state = 'open';
CREATE UNIQUE INDEX boards_by_run ON boards (line, run_id);
CREATE INDEX boards_by_line ON boards (line, product, state, id);

CREATE TABLE pad_stats_v2 (
    line              TEXT NOT NULL CHECK (line <> ''),
    product           TEXT NOT NULL,
    pad               INTEGER NOT NULL,
    boards            INTEGER NOT NULL,
    sum_volume_pct    REAL NOT NULL,
    sum_sq_volume_pct REAL NOT NULL,
    fails             INTEGER NOT NULL,
    warns             INTEGER NOT NULL,
    last_board_id     INTEGER NOT NULL,
    PRIMARY KEY (line, product, pad)
) WITHOUT ROWID;
INSERT INTO pad_stats_v2 (line, product, pad, boards, sum_volume_pct, sum_sq_volume_pct,
                          fails, warns, last_board_id)
    SELECT 'line-1', product, pad, boards, sum_volume_pct, sum_sq_volume_pct, fails, warns,
           last_board_id FROM pad_stats;
DROP TABLE pad_stats;
ALTER TABLE pad_stats_v2 RENAME TO pad_stats;
";

/// Version 2, PostgreSQL: the same as [`V2_SQLITE`], `boards` in place (`line` added with the
/// default `line-1` for the rows already there and the default then dropped, as SQLite's
/// copied table has none: every insert names its line), `pad_stats` made anew as SQLite's, its
/// `line` first. (`boards_run_id_key` and `pads_board_id_fkey` are the names PostgreSQL gave
/// version 1's constraints.)
///
/// Two things for the speed of a board's pads, both measured (6,000 pads a board, this
/// machine's PostgreSQL 15 with its default settings):
/// - `pads`' foreign key to `boards` is kept by statement-level triggers instead of the
///   FOREIGN KEY constraint, which checks every row with a query of its own: 70 of the 90 ms
///   an insert of a board's pads took; a check of the whole statement's rows at once takes a
///   few ms (the distinct board ids of the statement's rows, one lookup each: one for a
///   board's COPY). What the constraint did, they do: a pad row of a board not in `boards` is
///   refused (insert, COPY or update), deleting boards deletes their pads (ON DELETE
///   CASCADE), and a board's id cannot change. (The constraint also locks the board's row
///   against a concurrent delete while the pads go in; the store's `finish_board` holds that
///   row locked itself.) The other tables keep their constraints: a few rows a board.
/// - `pad_stats` leaves half of each page free (`fillfactor = 50`): every board updates one
///   row per pad, and an update that fits on its row's page leaves the primary key alone
///   (PostgreSQL's "HOT" update): 30 - 50 ms a board against 60 - 120 ms. SQLite has no such
///   setting (it updates in place).
pub(crate) const V2_POSTGRES: &str = "
ALTER TABLE boards ADD COLUMN line TEXT NOT NULL DEFAULT 'line-1' CHECK (line <> '');
ALTER TABLE boards ALTER COLUMN line DROP DEFAULT;
ALTER TABLE boards DROP CONSTRAINT boards_run_id_key;
CREATE UNIQUE INDEX boards_by_run ON boards (line, run_id);
CREATE INDEX boards_by_line ON boards (line, product, state, id);

CREATE TABLE pad_stats_v2 (
    line              TEXT NOT NULL CHECK (line <> ''),
    product           TEXT NOT NULL,
    pad               INTEGER NOT NULL,
    boards            BIGINT NOT NULL,
    sum_volume_pct    DOUBLE PRECISION NOT NULL,
    sum_sq_volume_pct DOUBLE PRECISION NOT NULL,
    fails             BIGINT NOT NULL,
    warns             BIGINT NOT NULL,
    last_board_id     BIGINT NOT NULL
) WITH (fillfactor = 50);
INSERT INTO pad_stats_v2 (line, product, pad, boards, sum_volume_pct, sum_sq_volume_pct,
                          fails, warns, last_board_id)
    SELECT 'line-1', product, pad, boards, sum_volume_pct, sum_sq_volume_pct, fails, warns,
           last_board_id FROM pad_stats;
DROP TABLE pad_stats;
ALTER TABLE pad_stats_v2 RENAME TO pad_stats;
ALTER TABLE pad_stats ADD CONSTRAINT pad_stats_pkey PRIMARY KEY (line, product, pad);

ALTER TABLE pads DROP CONSTRAINT pads_board_id_fkey;
CREATE FUNCTION pads_board_exists() RETURNS trigger LANGUAGE plpgsql
SET search_path FROM CURRENT AS $$
BEGIN
    IF EXISTS (SELECT 1 FROM (SELECT DISTINCT board_id FROM new_pads) AS p
               WHERE NOT EXISTS (SELECT 1 FROM boards AS b WHERE b.id = p.board_id)) THEN
        RAISE foreign_key_violation USING MESSAGE =
            'insert or update on table \"pads\" refers to a board not in \"boards\"';
    END IF;
    RETURN NULL;
END $$;
CREATE TRIGGER pads_board_exists_on_insert AFTER INSERT ON pads
    REFERENCING NEW TABLE AS new_pads
    FOR EACH STATEMENT EXECUTE FUNCTION pads_board_exists();
CREATE TRIGGER pads_board_exists_on_update AFTER UPDATE ON pads
    REFERENCING NEW TABLE AS new_pads
    FOR EACH STATEMENT EXECUTE FUNCTION pads_board_exists();
CREATE FUNCTION boards_delete_pads() RETURNS trigger LANGUAGE plpgsql
SET search_path FROM CURRENT AS $$
BEGIN
    DELETE FROM pads WHERE board_id IN (SELECT id FROM old_boards);
    RETURN NULL;
END $$;
CREATE TRIGGER boards_delete_pads AFTER DELETE ON boards
    REFERENCING OLD TABLE AS old_boards
    FOR EACH STATEMENT EXECUTE FUNCTION boards_delete_pads();
CREATE FUNCTION boards_id_fixed() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    RAISE foreign_key_violation USING MESSAGE =
        'a board''s id never changes: its pads refer to it';
END $$;
CREATE TRIGGER boards_id_fixed BEFORE UPDATE OF id ON boards
    FOR EACH ROW WHEN (OLD.id IS DISTINCT FROM NEW.id) EXECUTE FUNCTION boards_id_fixed();
";

/// Version 3: `prints`, a row per board the line finished (inspected or incomplete): the
/// print's placement measured on it (NULL when it could not be fitted, or the board was never
/// inspected) and the printer correction the loop proposed after it (`crate::printer`). One
/// row a board: the plain foreign key on both dialects. The placement's columns are all set or
/// all NULL; the loop's estimate is NULL until its first placement. And `stencil_cleans`: the
/// stencil's cleans as a printer or an operator reported them, per line and product.
pub(crate) const V3: &str = "
CREATE TABLE prints (
    board_id                 {int64} NOT NULL PRIMARY KEY REFERENCES boards (id) ON DELETE CASCADE,
    x_um                     {real},
    y_um                     {real},
    rotation_mdeg            {real},
    stretch_ppm              {real},
    u_x_um                   {real},
    u_y_um                   {real},
    u_rotation_mdeg          {real},
    u_stretch_ppm            {real},
    scale_um                 {real},
    centre_x_mm              {real},
    centre_y_mm              {real},
    pads_used                INTEGER CHECK (pads_used >= 0),
    outliers                 INTEGER CHECK (outliers >= 0),
    correction_x_um          {real} NOT NULL,
    correction_y_um          {real} NOT NULL,
    correction_rotation_mdeg {real} NOT NULL,
    change_x_um              {real} NOT NULL,
    change_y_um              {real} NOT NULL,
    change_rotation_mdeg     {real} NOT NULL,
    estimate_x_um            {real},
    estimate_y_um            {real},
    estimate_rotation_mdeg   {real},
    u_estimate_x_um          {real},
    u_estimate_y_um          {real},
    u_estimate_rotation_mdeg {real},
    held                     INTEGER NOT NULL CHECK (held BETWEEN 0 AND 7),
    limited                  INTEGER NOT NULL CHECK (limited BETWEEN 0 AND 7),
    reason                   TEXT NOT NULL,
    CHECK ((x_um IS NULL) = (pads_used IS NULL))
){without_rowid};

CREATE TABLE stencil_cleans (
    id             {id},
    line           TEXT NOT NULL CHECK (line <> ''),
    product        TEXT NOT NULL CHECK (product <> ''),
    cleaned_unix_s {real} NOT NULL,
    source         TEXT NOT NULL CHECK (source <> ''),
    note           TEXT
);
CREATE INDEX stencil_cleans_by_line ON stencil_cleans (line, product, cleaned_unix_s);
";

/// Version 4, for the operator's pages: `pad_images`, the heights above the local surface
/// around each pad that warned or failed (`dpsa_inspect::crop`), stored with the board; and
/// `reviews`, an operator's decision on such a pad (confirmed, or a false call), who and when,
/// with the pad's package family copied in so that the false-call rates outlive the pruned pad
/// rows. A store of version 3 gains both empty.
pub(crate) const V4: &str = "
CREATE TABLE pad_images (
    board_id {int64} NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    pad      INTEGER NOT NULL CHECK (pad >= 0),
    family   TEXT,
    x0_mm    {real} NOT NULL,
    y0_mm    {real} NOT NULL,
    pitch_mm {real} NOT NULL CHECK (pitch_mm > 0),
    nx       INTEGER NOT NULL CHECK (nx BETWEEN 1 AND 256),
    ny       INTEGER NOT NULL CHECK (ny BETWEEN 1 AND 256),
    lsb_um   {real} NOT NULL CHECK (lsb_um > 0),
    heights  {blob} NOT NULL,
    outline  TEXT NOT NULL,
    CHECK ({bytes_of}(heights) = 2 * nx * ny),
    PRIMARY KEY (board_id, pad)
){without_rowid};

CREATE TABLE reviews (
    id              {id},
    board_id        {int64} NOT NULL REFERENCES boards (id) ON DELETE CASCADE,
    pad             INTEGER NOT NULL CHECK (pad >= 0),
    family          TEXT,
    decision        TEXT NOT NULL CHECK (decision = 'confirmed' OR decision = 'false_call'),
    reviewer        TEXT NOT NULL CHECK (reviewer <> ''),
    reviewed_unix_s {real} NOT NULL,
    note            TEXT
);
CREATE INDEX reviews_by_board ON reviews (board_id, pad, id);
";

/// The triggers that keep `pads`' foreign key on PostgreSQL ([`V2_POSTGRES`]), with their
/// tables (a test finds them in place of the constraint).
#[cfg(test)]
pub(crate) const POSTGRES_PADS_KEY_TRIGGERS: [(&str, &str); 4] = [
    ("pads", "pads_board_exists_on_insert"),
    ("pads", "pads_board_exists_on_update"),
    ("boards", "boards_delete_pads"),
    ("boards", "boards_id_fixed"),
];

/// PostgreSQL's schema version: one row (`one` is its key and always true), made by the first
/// migration's transaction.
pub(crate) const POSTGRES_VERSION_TABLE: &str = "
CREATE TABLE IF NOT EXISTS schema_version (
    one     BOOLEAN PRIMARY KEY DEFAULT TRUE CHECK (one),
    version INTEGER NOT NULL CHECK (version >= 0)
);
";

/// The rules [`crate::store::Store::check`] verifies on the rows, both dialects: each a query
/// counting the rows that break it, with what it says of them. `{from_board}` (filled in by
/// [`rule`]) bounds the rows of boards to the boards from that id on: the lowest possible id
/// for the whole store, the oldest of the newest boards for
/// [`crate::store::Store::check_newest`]; the aggregates and the stencil's cleans are read
/// whole either way (a few rows per pad and product). They restate the schema's
/// CHECKs and foreign keys (a database whose constraints were switched off or dropped, or
/// whose rows were written past them, is caught) and add what the store keeps true without a
/// constraint saying so: a board's pad rows number its `pads`, only inspected boards have pad
/// rows, every pad that warned or failed has its `defects` row and every `defects` row its pad.
/// The last queries read every pad row once: seconds for a store of gigabytes.
pub(crate) const INVARIANTS: &[(&str, &str)] = &[
    (
        "boards whose state disagrees with their end, verdict, reason or pad count, or whose \
         run id, state, verdict or line is not one the schema allows",
        "SELECT count(*) FROM boards WHERE id >= {from_board} AND NOT (
            ((state = 'open' AND ended_unix_s IS NULL AND verdict IS NULL
                AND incomplete_reason IS NULL AND pads = 0)
            OR (state = 'inspected' AND ended_unix_s IS NOT NULL AND verdict IS NOT NULL
                AND incomplete_reason IS NULL)
            OR (state = 'incomplete' AND ended_unix_s IS NOT NULL AND verdict IS NULL
                AND incomplete_reason IS NOT NULL AND pads = 0))
            AND ({run_id_is_hex})
            AND state IN ('open', 'inspected', 'incomplete')
            AND (verdict IS NULL OR verdict IN ('pass', 'warn', 'fail'))
            AND pads >= 0 AND line <> '')",
    ),
    (
        "camera rows out of range (camera 0..=255, counts >= 0)",
        "SELECT count(*) FROM board_cameras WHERE board_id >= {from_board}
            AND NOT (camera BETWEEN 0 AND 255 AND rows >= 0
            AND missing_rows >= 0 AND missing_packets >= 0 AND damaged_packets >= 0)",
    ),
    (
        "pad rows out of range (pad >= 0, level pass / warn / fail, coverage 0..=1)",
        "SELECT count(*) FROM pads WHERE board_id >= {from_board} AND NOT (pad >= 0
            AND (level = 'pass' OR level = 'warn' OR level = 'fail')
            AND coverage BETWEEN 0 AND 1)",
    ),
    (
        "aggregate rows out of range (at least one board, fails + warns <= boards, a line)",
        "SELECT count(*) FROM pad_stats WHERE NOT (boards >= 1 AND fails >= 0 AND warns >= 0
            AND fails + warns <= boards AND sum_sq_volume_pct >= 0 AND line <> '')",
    ),
    (
        "camera rows of a board that is not in the store",
        "SELECT count(*) FROM board_cameras AS c
            WHERE c.board_id >= {from_board} AND NOT EXISTS (SELECT 1 FROM boards AS b WHERE b.id = c.board_id)",
    ),
    (
        "defect rows without the pad row they stand for (same board, pad and level)",
        "SELECT count(*) FROM defects AS d WHERE d.board_id >= {from_board}
            AND NOT EXISTS (SELECT 1 FROM pads AS p
            WHERE p.board_id = d.board_id AND p.pad = d.pad AND p.level = d.level)",
    ),
    (
        "boards whose pad rows are of a board not in the store, of a board not inspected, \
         not as many as its pad count, or not one defect row per pad that warned or failed",
        "SELECT count(*) FROM
            (SELECT board_id, count(*) AS n,
                    sum(CASE WHEN level = 'pass' THEN 0 ELSE 1 END) AS flagged
             FROM pads WHERE board_id >= {from_board} GROUP BY board_id) AS p
            LEFT JOIN boards AS b ON b.id = p.board_id
            LEFT JOIN (SELECT board_id, count(*) AS n FROM defects
                WHERE board_id >= {from_board} GROUP BY board_id) AS d
                ON d.board_id = p.board_id
            WHERE b.id IS NULL OR b.state <> 'inspected' OR b.pads <> p.n
                OR coalesce(d.n, 0) <> p.flagged",
    ),
    (
        "print rows of a board not in the store or still open, with a placement on a board \
         not inspected, or out of range (held and limited 0..=7, counts >= 0)",
        "SELECT count(*) FROM prints AS p LEFT JOIN boards AS b ON b.id = p.board_id
            WHERE p.board_id >= {from_board} AND (b.id IS NULL OR b.state = 'open'
                OR (p.x_um IS NOT NULL AND b.state <> 'inspected')
                OR NOT (p.held BETWEEN 0 AND 7 AND p.limited BETWEEN 0 AND 7
                    AND coalesce(p.pads_used, 0) >= 0 AND coalesce(p.outliers, 0) >= 0
                    AND (p.x_um IS NULL) = (p.pads_used IS NULL)))",
    ),
    (
        "pad images of a board not in the store or not inspected, of a pad the board's rows \
         do not name, or whose heights are not two bytes a sample",
        "SELECT count(*) FROM pad_images AS i LEFT JOIN boards AS b ON b.id = i.board_id
            WHERE i.board_id >= {from_board} AND (b.id IS NULL OR b.state <> 'inspected'
                OR NOT EXISTS (SELECT 1 FROM pads AS p
                    WHERE p.board_id = i.board_id AND p.pad = i.pad)
                OR {bytes_of}(i.heights) <> 2 * i.nx * i.ny)",
    ),
    (
        "reviews of a board not in the store or not inspected, or not of a pad that warned \
         or failed while the board's pad rows are kept",
        "SELECT count(*) FROM reviews AS r LEFT JOIN boards AS b ON b.id = r.board_id
            WHERE r.board_id >= {from_board} AND (b.id IS NULL OR b.state <> 'inspected'
                OR NOT (r.decision = 'confirmed' OR r.decision = 'false_call')
                OR (EXISTS (SELECT 1 FROM pads AS p WHERE p.board_id = r.board_id)
                    AND NOT EXISTS (SELECT 1 FROM defects AS d
                        WHERE d.board_id = r.board_id AND d.pad = r.pad)))",
    ),
];

/// The rules only PostgreSQL needs checked: it stores a NaN (SQLite turns one into NULL), its
/// constraints can be switched off table by table (`ALTER TABLE ... DISABLE TRIGGER ALL`
/// switches the foreign keys off; `NOT VALID` adds a constraint unchecked on the rows there),
/// and `pads`' foreign key is triggers, which can be dropped.
pub(crate) const POSTGRES_INVARIANTS: &[(&str, &str)] = &[
    (
        "NaN values (a measurement that could not be made is NULL, never NaN)",
        "SELECT (SELECT count(*) FROM pads WHERE board_id >= {from_board}
                    AND 'NaN' IN (volume_um3, volume_pct, area_mm2,
                    area_pct, height_um, height_pct, offset_x_um, offset_y_um, coverage,
                    uncertainty_um3))
              + (SELECT count(*) FROM boards WHERE id >= {from_board}
                    AND 'NaN' IN (started_unix_s, ended_unix_s))
              + (SELECT count(*) FROM pad_stats
                    WHERE 'NaN' IN (sum_volume_pct, sum_sq_volume_pct))
              + (SELECT count(*) FROM stencil_cleans WHERE cleaned_unix_s = 'NaN')
              + (SELECT count(*) FROM pad_images WHERE board_id >= {from_board}
                    AND 'NaN' IN (x0_mm, y0_mm, pitch_mm, lsb_um))
              + (SELECT count(*) FROM reviews WHERE board_id >= {from_board}
                    AND reviewed_unix_s = 'NaN')
              + (SELECT count(*) FROM prints WHERE board_id >= {from_board} AND 'NaN' IN (x_um, y_um, rotation_mdeg,
                    stretch_ppm, u_x_um, u_y_um, u_rotation_mdeg, u_stretch_ppm, scale_um,
                    centre_x_mm, centre_y_mm, correction_x_um, correction_y_um,
                    correction_rotation_mdeg, change_x_um, change_y_um, change_rotation_mdeg,
                    estimate_x_um, estimate_y_um, estimate_rotation_mdeg, u_estimate_x_um,
                    u_estimate_y_um, u_estimate_rotation_mdeg))",
    ),
    (
        "triggers switched off (foreign keys not kept)",
        "SELECT count(*) FROM pg_trigger AS t JOIN pg_class AS c ON c.oid = t.tgrelid
            WHERE c.relnamespace = current_schema()::regnamespace AND t.tgenabled = 'D'",
    ),
    (
        "of the 4 triggers that keep pads' foreign key missing",
        "SELECT 4 - count(*) FROM pg_trigger AS t JOIN pg_class AS c ON c.oid = t.tgrelid
            WHERE c.relnamespace = current_schema()::regnamespace
            AND (c.relname, t.tgname) IN (('pads', 'pads_board_exists_on_insert'),
                ('pads', 'pads_board_exists_on_update'), ('boards', 'boards_delete_pads'),
                ('boards', 'boards_id_fixed'))",
    ),
    (
        "constraints not validated on the rows there",
        "SELECT count(*) FROM pg_constraint
            WHERE connamespace = current_schema()::regnamespace AND NOT convalidated",
    ),
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn v1_for_sqlite_is_the_text_that_shipped() {
        assert_eq!(
            render(V1, Dialect::Sqlite),
            include_str!("v1_as_shipped.sql")
        );
    }

    #[test]
    fn every_word_is_known_and_spelled_for_both() {
        for step in MIGRATIONS {
            for d in [Dialect::Sqlite, Dialect::Postgres] {
                let sql = step.sql(d);
                // The only braces left: PostgreSQL's `{16}` in a regular expression.
                assert!(
                    !sql.replace("{16}", "").contains(['{', '}']),
                    "{d:?}: {sql}"
                );
            }
        }
        for (_, sql) in INVARIANTS.iter().chain(POSTGRES_INVARIANTS) {
            for d in [Dialect::Sqlite, Dialect::Postgres] {
                for from in [None, Some(7)] {
                    let r = rule(sql, d, from);
                    assert!(!r.replace("{16}", "").contains(['{', '}']), "{r}");
                }
            }
        }
        assert_eq!(render("a {unknown} b", Dialect::Sqlite), "a {unknown} b");
        assert_eq!(render("{real}{", Dialect::Postgres), "DOUBLE PRECISION{");
    }

    #[test]
    fn the_default_line_of_version_2_is_the_programs() {
        assert!(V2_SQLITE.contains(&format!("'{}'", crate::store::DEFAULT_LINE)));
        assert!(V2_POSTGRES.contains(&format!("'{}'", crate::store::DEFAULT_LINE)));
    }
}
