-- fleetslam store schema, SQLite flavour (see migrations/postgres/ for the same schema in
-- PostgreSQL). JSON documents are kept as TEXT; times are unix milliseconds (INTEGER) except
-- the robots' own clocks (t, t0: seconds, REAL).

CREATE TABLE runs (
    id          TEXT PRIMARY KEY NOT NULL,
    name        TEXT,
    status      TEXT NOT NULL CHECK (status IN ('active', 'ended', 'failed')),
    config      TEXT NOT NULL,
    header      TEXT,
    summary     TEXT,
    created_at  INTEGER NOT NULL,
    ended_at    INTEGER
);
CREATE INDEX runs_created_at ON runs (created_at);
CREATE INDEX runs_status_created_at ON runs (status, created_at);

CREATE TABLE robots (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    robot_id    TEXT NOT NULL,
    start       TEXT,
    token_hash  TEXT NOT NULL,
    t0          REAL,
    added_at    INTEGER NOT NULL,
    PRIMARY KEY (run_id, robot_id)
);

-- The append-only observation log: arrival numbers are 1, 2, 3, ... per run, contiguous.
CREATE TABLE observations (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    arrival     INTEGER NOT NULL,
    robot_id    TEXT NOT NULL,
    seq         INTEGER NOT NULL,
    t           REAL NOT NULL,
    body        TEXT NOT NULL,
    PRIMARY KEY (run_id, arrival),
    UNIQUE (run_id, robot_id, seq)
);

CREATE TABLE snapshots (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    applied     INTEGER NOT NULL,
    t           REAL NOT NULL,
    data        BLOB NOT NULL,
    created_at  INTEGER NOT NULL,
    PRIMARY KEY (run_id, applied)
);
CREATE INDEX snapshots_run_t ON snapshots (run_id, t);

CREATE TABLE evaluations (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id      TEXT NOT NULL REFERENCES runs (id),
    body        TEXT NOT NULL,
    created_at  INTEGER NOT NULL
);
CREATE INDEX evaluations_run ON evaluations (run_id, id);

CREATE TABLE training_rows (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id      TEXT NOT NULL REFERENCES runs (id),
    body        TEXT NOT NULL
);
CREATE INDEX training_rows_run ON training_rows (run_id, id);

CREATE TABLE models (
    id          TEXT PRIMARY KEY NOT NULL,
    kind        TEXT NOT NULL,
    config      TEXT NOT NULL,
    metrics     TEXT NOT NULL,
    weights     BLOB NOT NULL,
    created_at  INTEGER NOT NULL
);
