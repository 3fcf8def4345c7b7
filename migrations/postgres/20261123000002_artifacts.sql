-- Named JSON documents of a run: its final result (state and trajectories) and its ground
-- truth, when uploaded. One per (run, name); storing a name again replaces it.
CREATE TABLE run_artifacts (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    name        TEXT NOT NULL,
    body        TEXT NOT NULL,
    created_at  BIGINT NOT NULL,
    PRIMARY KEY (run_id, name)
);
