//! File formats robotics tools read: TUM trajectories (`timestamp x y z qx qy qz qw`, as read
//! by `evo`) and a landmarks CSV (`id,x,y,z,cxx,cxy,cxz,cyy,cyz,czz`).
//!
//! Estimates and ground truth use the same names in their directory:
//! `trajectory_<robot>.tum` per robot and `landmarks.csv`.

use fleetslam_core::math;
use fleetslam_core::pose::{Pose2, wrap_angle};
use std::io::{BufRead, BufWriter, Write};
use std::path::{Path, PathBuf};

/// One timestamped planar pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrajectoryPoint {
    pub t: f64,
    pub pose: Pose2,
}

/// A landmark estimate or truth. `cov` is the upper triangle of the 3x3 covariance
/// (xx, xy, xz, yy, yz, zz); zero when unknown.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LandmarkRow {
    pub id: Option<u32>,
    pub mean: [f64; 3],
    pub cov: [f64; 6],
}

/// The file name of a robot's trajectory in an estimate or truth directory.
pub fn trajectory_file(dir: &Path, robot: &str) -> PathBuf {
    dir.join(format!("trajectory_{robot}.tum"))
}

/// The landmarks file in an estimate or truth directory.
pub fn landmarks_file(dir: &Path) -> PathBuf {
    dir.join("landmarks.csv")
}

/// Robots that have a trajectory file in `dir`, sorted.
pub fn robots_in(dir: &Path) -> std::io::Result<Vec<String>> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir)? {
        let name = e?.file_name().to_string_lossy().into_owned();
        if let Some(r) = name
            .strip_prefix("trajectory_")
            .and_then(|s| s.strip_suffix(".tum"))
        {
            out.push(r.to_string());
        }
    }
    out.sort();
    Ok(out)
}

fn invalid(msg: String) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::InvalidData, msg)
}

/// Writes a TUM trajectory: planar poses as z = 0 and a yaw-only quaternion.
pub fn write_tum(w: impl Write, points: &[TrajectoryPoint]) -> std::io::Result<()> {
    let mut w = BufWriter::new(w);
    for p in points {
        let h = 0.5 * p.pose.theta;
        writeln!(
            w,
            "{:.6} {:.6} {:.6} 0 0 0 {:.9} {:.9}",
            p.t,
            p.pose.x,
            p.pose.y,
            math::sin(h),
            math::cos(h)
        )?;
    }
    w.flush()
}

pub fn write_tum_path(path: &Path, points: &[TrajectoryPoint]) -> std::io::Result<()> {
    write_tum(std::fs::File::create(path)?, points)
}

/// Reads a TUM trajectory; the heading is the yaw of the quaternion. `#` lines are comments.
pub fn read_tum(r: impl BufRead) -> std::io::Result<Vec<TrajectoryPoint>> {
    let mut out = Vec::new();
    for (i, line) in r.lines().enumerate() {
        let line = line?;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|s| s.parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| invalid(format!("TUM line {}: {e}", i + 1)))?;
        if v.len() != 8 {
            return Err(invalid(format!(
                "TUM line {}: expected 8 numbers, got {}",
                i + 1,
                v.len()
            )));
        }
        let (qx, qy, qz, qw) = (v[4], v[5], v[6], v[7]);
        let yaw = math::atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz));
        out.push(TrajectoryPoint {
            t: v[0],
            pose: Pose2::new(v[1], v[2], wrap_angle(yaw)),
        });
    }
    Ok(out)
}

pub fn read_tum_path(path: &Path) -> std::io::Result<Vec<TrajectoryPoint>> {
    read_tum(std::io::BufReader::new(std::fs::File::open(path)?))
}

const LANDMARK_HEADER: &str = "id,x,y,z,cxx,cxy,cxz,cyy,cyz,czz";

/// Writes landmarks as CSV; an unknown id is an empty field.
pub fn write_landmarks_csv(w: impl Write, rows: &[LandmarkRow]) -> std::io::Result<()> {
    let mut w = BufWriter::new(w);
    writeln!(w, "{LANDMARK_HEADER}")?;
    for r in rows {
        let id = r.id.map(|i| i.to_string()).unwrap_or_default();
        write!(w, "{id}")?;
        for v in r.mean.iter().chain(r.cov.iter()) {
            write!(w, ",{v:.9}")?;
        }
        writeln!(w)?;
    }
    w.flush()
}

pub fn write_landmarks_csv_path(path: &Path, rows: &[LandmarkRow]) -> std::io::Result<()> {
    write_landmarks_csv(std::fs::File::create(path)?, rows)
}

/// Reads a landmarks CSV written by [`write_landmarks_csv`] (missing covariance columns read
/// as zero, so `id,x,y` files work too).
pub fn read_landmarks_csv(r: impl BufRead) -> std::io::Result<Vec<LandmarkRow>> {
    let mut out = Vec::new();
    for (i, line) in r.lines().enumerate() {
        let line = line?;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || (i == 0 && line.starts_with("id")) {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() < 3 {
            return Err(invalid(format!(
                "landmarks line {}: expected id,x,y[,z,...]",
                i + 1
            )));
        }
        let id = if f[0].trim().is_empty() {
            None
        } else {
            Some(
                f[0].trim()
                    .parse::<u32>()
                    .map_err(|e| invalid(format!("landmarks line {}: id: {e}", i + 1)))?,
            )
        };
        let mut nums = [0.0; 9];
        for (k, s) in f[1..].iter().take(9).enumerate() {
            nums[k] = s
                .trim()
                .parse::<f64>()
                .map_err(|e| invalid(format!("landmarks line {}: column {}: {e}", i + 1, k + 2)))?;
        }
        out.push(LandmarkRow {
            id,
            mean: [nums[0], nums[1], nums[2]],
            cov: [nums[3], nums[4], nums[5], nums[6], nums[7], nums[8]],
        });
    }
    Ok(out)
}

pub fn read_landmarks_csv_path(path: &Path) -> std::io::Result<Vec<LandmarkRow>> {
    read_landmarks_csv(std::io::BufReader::new(std::fs::File::open(path)?))
}

/// Ground truth (or an estimate) as files: one trajectory per robot and the landmarks.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Truth {
    pub trajectories: std::collections::BTreeMap<String, Vec<TrajectoryPoint>>,
    /// Empty when the data set has no landmark truth (Victoria Park).
    pub landmarks: Vec<LandmarkRow>,
}

impl Truth {
    /// Writes `trajectory_<robot>.tum` per robot and, when there are landmarks,
    /// `landmarks.csv` into `dir` (created if missing).
    pub fn write_dir(&self, dir: &Path) -> std::io::Result<()> {
        std::fs::create_dir_all(dir)?;
        for (robot, pts) in &self.trajectories {
            write_tum_path(&trajectory_file(dir, robot), pts)?;
        }
        if !self.landmarks.is_empty() {
            write_landmarks_csv_path(&landmarks_file(dir), &self.landmarks)?;
        }
        Ok(())
    }

    /// Reads what [`Truth::write_dir`] wrote; a missing landmarks file reads as none.
    pub fn read_dir(dir: &Path) -> std::io::Result<Truth> {
        let mut t = Truth::default();
        for robot in robots_in(dir)? {
            let pts = read_tum_path(&trajectory_file(dir, &robot))?;
            t.trajectories.insert(robot, pts);
        }
        let lm = landmarks_file(dir);
        if lm.exists() {
            t.landmarks = read_landmarks_csv_path(&lm)?;
        }
        Ok(t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tum_round_trip() {
        let pts = vec![
            TrajectoryPoint {
                t: 1.5,
                pose: Pose2::new(1.0, -2.0, 3.0),
            },
            TrajectoryPoint {
                t: 2.0,
                pose: Pose2::new(0.0, 0.5, -3.0),
            },
        ];
        let mut buf = Vec::new();
        write_tum(&mut buf, &pts).unwrap();
        let back = read_tum(&buf[..]).unwrap();
        for (a, b) in pts.iter().zip(&back) {
            assert!((a.t - b.t).abs() < 1e-6 && a.pose.distance(&b.pose) < 1e-6);
            assert!(wrap_angle(a.pose.theta - b.pose.theta).abs() < 1e-8);
        }
    }

    #[test]
    fn landmarks_round_trip() {
        let rows = vec![
            LandmarkRow {
                id: Some(6),
                mean: [1.0, 2.0, 0.0],
                cov: [0.1, 0.0, 0.0, 0.2, 0.0, 0.0],
            },
            LandmarkRow {
                id: None,
                mean: [-1.0, 2.5, 0.3],
                cov: [0.0; 6],
            },
        ];
        let mut buf = Vec::new();
        write_landmarks_csv(&mut buf, &rows).unwrap();
        assert_eq!(read_landmarks_csv(&buf[..]).unwrap(), rows);
        assert!(read_landmarks_csv(&b"id,x,y\n1,2\n"[..]).is_err());
    }
}
