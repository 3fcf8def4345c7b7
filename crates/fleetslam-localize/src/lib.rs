//! fleetslam-localize: Monte Carlo localization against a fixed landmark map, the real-time
//! particle filter, and late joiners of a shared-map FastSLAM run.
//!
//! Main types:
//! - [`map::LandmarkSet`]: a fixed map (landmark means, covariances, ids), taken from a
//!   running filter's best particle or a finished run's estimate; [`map::Scorer`] the
//!   observation likelihood.
//! - [`localizer::Localizer`]: Monte Carlo localization of one robot with global
//!   initialisation, KLD-sampling, a convergence test and the real-time policies
//!   ([`config::Policy`]: skip, naive, uniform, rtpf) for windows of several records.
//! - [`rtpf`]: the mixture weights of the real-time particle filter (Kwok, Fox, Meila).
//! - [`joining::LateJoinSlam`]: a [`fleetslam_core::FastSlam`] plus one localizer per robot
//!   that joined at an unknown pose; [`joining::MapLocalization`]: localization only, in a
//!   stored map.
//! - [`experiment`]: the paper's experiment in simulation (`fleetslam experiment rtpf`).
//!
//! Depends on the core only (plus `plotters` for the experiment's plot): no async runtime,
//! web framework or database.
//!
//! ```
//! use fleetslam_core::config::FilterConfig;
//! use fleetslam_core::pose::{Pose2, PoseGaussian};
//! use fleetslam_localize::{LateJoinSlam, LocalizeConfig, Phase};
//! let mut cfg = FilterConfig::default();
//! cfg.particles = 20;
//! let mut run = LateJoinSlam::new(cfg, LocalizeConfig::default()).unwrap();
//! run.add_robot("a", &PoseGaussian::exact(Pose2::default()), 0.0).unwrap();
//! run.add_unknown_robot("late").unwrap();
//! assert_eq!(run.phase("late"), Some(Phase::Localizing));
//! assert_eq!(run.phase("a"), Some(Phase::Mapping));
//! ```

pub mod config;
pub mod error;
pub mod experiment;
pub mod joining;
pub mod localizer;
pub mod map;
pub mod rtpf;

pub use config::{LocalizeConfig, Models, Policy, Window};
pub use error::LocalizeError;
pub use joining::{LateJoinSlam, LateJoinSnapshot, MapLocalization, Phase};
pub use localizer::Localizer;
pub use map::LandmarkSet;
