-- Trajectory points of a run, stored in pieces with its snapshots (issue 11): each snapshot
-- stores the points added since the previous one, and names how many points of each robot
-- it covers, so that a snapshot's size does not grow with the length of the run. Recovery,
-- the state at a time and results reassemble the trajectories from the pieces.
--
-- `first_index` is the index of the piece's first point in the robot's trajectory; `points` is
-- the JSON array [[t, x, y, theta], ...]. Points are a deterministic function of the log,
-- so a piece written again (after a crash between a piece and its snapshot) agrees with the
-- one it replaces wherever they overlap.
CREATE TABLE trajectory_chunks (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    robot_id    TEXT NOT NULL,
    first_index INTEGER NOT NULL,
    points      TEXT NOT NULL,
    PRIMARY KEY (run_id, robot_id, first_index)
);
