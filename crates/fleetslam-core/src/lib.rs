//! fleetslam-core: multi-robot, shared-map FastSLAM.
//!
//! Each particle holds the pose of every robot of a run and ONE landmark map shared by the
//! robots, with a small Gaussian filter per landmark (Montemerlo et al. 2002/2003; the
//! multi-robot form of Gil et al. 2010 used by Vidal et al. 2015). An observation by robot
//! `i` moves and weighs only robot `i`'s pose in each particle; a particle's log-weight is
//! the sum over robots (the product of the paper).
//!
//! Main types:
//! - [`log::Record`] and [`log::LogHeader`]: the observation format (HTTP and log files).
//! - [`updater::LandmarkUpdater`]: the swappable per-landmark update, batched;
//!   [`ekf::EkfUpdater`] is the reference implementation.
//! - [`filter::FastSlam`]: the filter; [`config::FilterConfig`] its configuration.
//! - [`map::LandmarkMap`]: the persistent per-particle map (O(log M) copies per update).
//!
//! This crate knows nothing of async runtimes, HTTP, databases or burn.
//!
//! ```
//! use fleetslam_core::{config::FilterConfig, filter::FastSlam, log::Record, pose::*};
//! let mut cfg = FilterConfig::default();
//! cfg.particles = 50;
//! let mut slam = FastSlam::new(cfg).unwrap();
//! slam.add_robot("r1", &PoseGaussian::exact(Pose2::default()), 0.0).unwrap();
//! let rec: Record = serde_json::from_str(
//!     r#"{"robot":"r1","seq":0,"t":1.0,"motion":{"velocity":[[0.5,0.0,1.0]]},
//!         "landmarks":[{"id":3,"z":[2.0,0.1]}]}"#).unwrap();
//! slam.step(&rec).unwrap();
//! assert_eq!(slam.estimate().landmarks.len(), 1);
//! ```

pub mod config;
pub mod ekf;
pub(crate) mod ekf_lanes;
pub mod filter;
pub mod linalg;
pub mod log;
pub mod map;
pub mod math;
pub mod motion;
pub mod pose;
pub mod resample;
pub mod rng;
pub mod sensor;
pub mod stats;
pub mod updater;

pub use config::FilterConfig;
pub use filter::FastSlam;
pub use pose::{Pose2, PoseGaussian};
