//! Bounds on what a client may send, so that no request can make a run hang, grow without
//! bound or poison it. Each bound is a server setting (`ServerConfig`); a request over one
//! gets a 400 (or 409, 413) whose message names the field, the value and the bound.

use fleetslam_core::log::Record;
use fleetslam_core::motion::Motion;
use fleetslam_core::pose::PoseGaussian;
use nalgebra::Matrix3;

/// The input bounds of a server.
#[derive(Debug, Clone, PartialEq)]
pub struct Limits {
    /// How far a record's time may lie ahead of the run's clock [s].
    pub max_future_s: f64,
    /// Longest motion (sum of segment durations) in one record [s].
    pub max_motion_s: f64,
    /// Most motion segments in one record.
    pub max_motion_segments: usize,
    /// Most records in one request.
    pub max_records_per_request: usize,
    /// Most landmark observations in one record.
    pub max_landmarks_per_record: usize,
    /// Most robot sightings in one record.
    pub max_sightings_per_record: usize,
    /// Most robots in one run.
    pub max_robots_per_run: usize,
    /// Most runs running at once.
    pub max_active_runs: usize,
    /// Longest run name, robot id or model id [bytes].
    pub max_name_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_future_s: 3600.0,
            max_motion_s: 600.0,
            max_motion_segments: 10_000,
            max_records_per_request: 10_000,
            max_landmarks_per_record: 1_000,
            max_sightings_per_record: 64,
            max_robots_per_run: 256,
            max_active_runs: 64,
            max_name_bytes: 128,
        }
    }
}

impl Limits {
    /// Checks the bounds themselves.
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [
            ("max_future_s", self.max_future_s),
            ("max_motion_s", self.max_motion_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be a finite number > 0, got {v}"));
            }
        }
        for (name, v) in [
            ("max_motion_segments", self.max_motion_segments),
            ("max_records_per_request", self.max_records_per_request),
            ("max_landmarks_per_record", self.max_landmarks_per_record),
            ("max_sightings_per_record", self.max_sightings_per_record),
            ("max_robots_per_run", self.max_robots_per_run),
            ("max_active_runs", self.max_active_runs),
            ("max_name_bytes", self.max_name_bytes),
        ] {
            if v == 0 {
                return Err(format!("{name} must be at least 1"));
            }
        }
        Ok(())
    }

    /// Checks the shape of one record against the bounds that do not depend on the run's
    /// state (the time window is the coordinator's). The message names the field.
    pub fn check_record(&self, r: &Record) -> Result<(), String> {
        if r.seq > i64::MAX as u64 {
            return Err(format!(
                "seq {} is too large: sequence numbers go up to {} (2^63 - 1)",
                r.seq,
                i64::MAX
            ));
        }
        if r.landmarks.len() > self.max_landmarks_per_record {
            return Err(format!(
                "landmarks: {} observations, at most {} per record (max_landmarks_per_record)",
                r.landmarks.len(),
                self.max_landmarks_per_record
            ));
        }
        if r.robots.len() > self.max_sightings_per_record {
            return Err(format!(
                "robots: {} sightings, at most {} per record (max_sightings_per_record)",
                r.robots.len(),
                self.max_sightings_per_record
            ));
        }
        if let Some(m) = &r.motion {
            let segments = match m {
                Motion::Velocity(s) | Motion::Ackermann(s) => s.len(),
                Motion::Odometry(_) => 1,
            };
            if segments > self.max_motion_segments {
                return Err(format!(
                    "motion: {segments} segments, at most {} per record (max_motion_segments)",
                    self.max_motion_segments
                ));
            }
            // Durations are checked non-negative and finite by `Record::validate`; this
            // bounds the integration work (Ackermann: one RK4 step per 50 ms).
            let d = m.duration();
            if d > self.max_motion_s {
                return Err(format!(
                    "motion: segments last {d} s in all, at most {} s per record (max_motion_s)",
                    self.max_motion_s
                ));
            }
        }
        Ok(())
    }

    /// Checks a name or id: 1 to `max_name_bytes` bytes, no control characters, no '/'.
    pub fn check_name(&self, what: &str, name: &str) -> Result<(), String> {
        if name.is_empty()
            || name.len() > self.max_name_bytes
            || name.chars().any(|c| c.is_control() || c == '/')
        {
            return Err(format!(
                "{what} must be 1-{} bytes of printable characters without '/', got {:?}",
                self.max_name_bytes,
                truncate(name, 80)
            ));
        }
        Ok(())
    }
}

/// Checks a start pose as the filter will use it: finite numbers, a symmetric covariance
/// that is zero (the pose is exact) or positive semi-definite (Cholesky, with the filter's
/// jitter of 1e-12 (1 + |trace|) for semi-definite ones).
pub fn check_start(start: &PoseGaussian) -> Result<(), String> {
    let m = &start.mean;
    if !(m.x.is_finite() && m.y.is_finite() && m.theta.is_finite()) {
        return Err(format!("mean has a non-finite number: {m:?}"));
    }
    let c = &start.cov;
    if c.iter().flatten().any(|v| !v.is_finite()) {
        return Err(format!("cov has a non-finite number: {c:?}"));
    }
    let scale = c.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    for (i, row) in c.iter().enumerate() {
        for (j, &cij) in row.iter().enumerate().take(i) {
            if (cij - c[j][i]).abs() > 1e-9 * (1.0 + scale) {
                return Err(format!(
                    "cov is not symmetric: cov[{i}][{j}] = {cij} but cov[{j}][{i}] = {}",
                    c[j][i]
                ));
            }
        }
    }
    if scale == 0.0 {
        return Ok(());
    }
    let cov = Matrix3::from_fn(|i, j| 0.5 * (c[i][j] + c[j][i]));
    let jitter = 1e-12 * (1.0 + cov.trace().abs());
    if cov.cholesky().is_some() || (cov + Matrix3::identity() * jitter).cholesky().is_some() {
        Ok(())
    } else {
        Err(format!(
            "cov is not positive semi-definite: {c:?} (variances must be >= 0 and each \
             correlation within [-1, 1])"
        ))
    }
}

/// At most `n` characters of `s`, marked when cut, for error messages.
pub fn truncate(s: &str, n: usize) -> String {
    match s.char_indices().nth(n) {
        Some((i, _)) => format!("{}...", &s[..i]),
        None => s.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record() -> Record {
        serde_json::from_str(r#"{"robot":"1","seq":0,"t":1.0}"#).unwrap()
    }

    #[test]
    fn bounds_name_the_field() {
        let l = Limits::default();
        let mut r = record();
        r.seq = 1 << 63;
        assert!(l.check_record(&r).unwrap_err().contains("seq"));
        r.seq = i64::MAX as u64;
        l.check_record(&r).unwrap();
        r.motion = Some(Motion::Ackermann(vec![[1.0, 0.0, 1e9]]));
        let e = l.check_record(&r).unwrap_err();
        assert!(e.contains("max_motion_s"), "{e}");
        r.motion = Some(Motion::Velocity(vec![[0.0, 0.0, 0.01]; 10_001]));
        assert!(
            l.check_record(&r)
                .unwrap_err()
                .contains("max_motion_segments")
        );
        r.motion = Some(Motion::Velocity(vec![[0.0, 0.0, 0.01]; 10_000]));
        l.check_record(&r).unwrap();
        r.landmarks = vec![
            fleetslam_core::log::LandmarkObservation {
                id: None,
                z: vec![1.0, 0.0]
            };
            1001
        ];
        assert!(l.check_record(&r).unwrap_err().contains("landmarks"));
    }

    #[test]
    fn start_poses() {
        use fleetslam_core::pose::Pose2;
        let mut g = PoseGaussian::exact(Pose2::new(1.0, 2.0, 0.0));
        check_start(&g).unwrap();
        g.cov = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.0]];
        check_start(&g).unwrap();
        g.cov = [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(
            check_start(&g)
                .unwrap_err()
                .contains("positive semi-definite")
        );
        g.cov = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(check_start(&g).is_err());
        g.cov = [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(check_start(&g).unwrap_err().contains("symmetric"));
        g.cov = [[f64::NAN, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(check_start(&g).is_err());
    }

    #[test]
    fn names() {
        let l = Limits::default();
        l.check_name("robot id", "r1").unwrap();
        assert!(l.check_name("robot id", "").is_err());
        assert!(l.check_name("robot id", "a/b").is_err());
        assert!(l.check_name("robot id", &"x".repeat(129)).is_err());
        assert!(l.check_name("robot id", "a\nb").is_err());
        assert_eq!(truncate("abcdef", 3), "abc...");
    }
}
