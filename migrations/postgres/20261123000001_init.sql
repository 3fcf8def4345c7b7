-- fleetslam store schema, PostgreSQL flavour (see migrations/sqlite/ for the same schema in
-- SQLite). JSON documents are kept as TEXT (stored and returned byte for byte, unlike JSONB);
-- times are unix milliseconds (BIGINT) except the robots' own clocks (t, t0: seconds).

CREATE TABLE runs (
    id          TEXT PRIMARY KEY NOT NULL,
    name        TEXT,
    status      TEXT NOT NULL CHECK (status IN ('active', 'ended', 'failed')),
    config      TEXT NOT NULL,
    header      TEXT,
    summary     TEXT,
    created_at  BIGINT NOT NULL,
    ended_at    BIGINT
);
CREATE INDEX runs_created_at ON runs (created_at);
CREATE INDEX runs_status_created_at ON runs (status, created_at);

CREATE TABLE robots (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    robot_id    TEXT NOT NULL,
    start       TEXT,
    token_hash  TEXT NOT NULL,
    t0          DOUBLE PRECISION,
    added_at    BIGINT NOT NULL,
    PRIMARY KEY (run_id, robot_id)
);

-- The append-only observation log: arrival numbers are 1, 2, 3, ... per run, contiguous.
CREATE TABLE observations (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    arrival     BIGINT NOT NULL,
    robot_id    TEXT NOT NULL,
    seq         BIGINT NOT NULL,
    t           DOUBLE PRECISION NOT NULL,
    body        TEXT NOT NULL,
    PRIMARY KEY (run_id, arrival),
    UNIQUE (run_id, robot_id, seq)
);

CREATE TABLE snapshots (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    applied     BIGINT NOT NULL,
    t           DOUBLE PRECISION NOT NULL,
    data        BYTEA NOT NULL,
    created_at  BIGINT NOT NULL,
    PRIMARY KEY (run_id, applied)
);
CREATE INDEX snapshots_run_t ON snapshots (run_id, t);

CREATE TABLE evaluations (
    id          BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    run_id      TEXT NOT NULL REFERENCES runs (id),
    body        TEXT NOT NULL,
    created_at  BIGINT NOT NULL
);
CREATE INDEX evaluations_run ON evaluations (run_id, id);

CREATE TABLE training_rows (
    id          BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    run_id      TEXT NOT NULL REFERENCES runs (id),
    body        TEXT NOT NULL
);
CREATE INDEX training_rows_run ON training_rows (run_id, id);

CREATE TABLE models (
    id          TEXT PRIMARY KEY NOT NULL,
    kind        TEXT NOT NULL,
    config      TEXT NOT NULL,
    metrics     TEXT NOT NULL,
    weights     BYTEA NOT NULL,
    created_at  BIGINT NOT NULL
);
