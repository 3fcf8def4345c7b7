-- Poison isolation, failed runs and scrubbing by time (issue 11).
--
-- observations.rejected: NULL for a record the filter applied (or will apply); the reason
-- for a quarantined one (it made the filter fail or panic, or its body cannot be parsed
-- back). Quarantined records stay in the log (their (robot, seq) stays taken, so a retry is
-- a duplicate) but recovery, scrubbing, re-runs and exports skip them. Appends leave it NULL.
ALTER TABLE observations ADD COLUMN rejected TEXT;

-- runs.reason: why a run failed (its coordinator or its recovery failed).
ALTER TABLE runs ADD COLUMN reason TEXT;

-- Scrubbing (state at a time) reads the records after a snapshot by time, not the whole log.
CREATE INDEX observations_run_t ON observations (run_id, t);
