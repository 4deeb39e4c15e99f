
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
