//! Live runs in Foxglove (`serve --foxglove-bind ADDR`): a Foxglove WebSocket server (the
//! official `foxglove` crate) beside the HTTP API, with one topic set per live run under
//! `/run/<id>`: the same messages as the MCAP export ([`fleetslam_data::mcap::RunChannels`]).
//!
//! | topic | schema | sent |
//! |---|---|---|
//! | `/run/<id>/tf` | `foxglove.FrameTransform` | `world` → `robot_<rid>`, one per applied record of the robot |
//! | `/run/<id>/robot/<rid>/pose` | `foxglove.PoseInFrame` | the robot's pose after each of its applied records |
//! | `/run/<id>/landmarks` | `foxglove.SceneUpdate` | the whole map (2-sigma ellipses and ids), each time the state changes |
//! | `/run/<id>/robot/<rid>/particles` | `foxglove.PosesInFrame` | the state's particle sample, each time the state changes |
//! | `/run/<id>/filter` | `fleetslam.FilterStats` (JSON) | ESS, step time and landmark count after each applied record |
//!
//! Each run's task wakes at the server's state rate (`state_rate_hz`) and sends what the run
//! published since it last woke. It builds messages only while a client subscribes to one of
//! the run's topics; with none, it only keeps the robots' topics advertised. Messages are
//! logged at the wall clock; their `timestamp` is the data time. A run's topics go when it
//! ends, [`ENDED_RUN_LINGER`] after its final state is sent. In cluster mode a replica shows the runs it owns.
//!
//! The Foxglove WebSocket protocol has no authentication: `serve` binds it to a loopback
//! address unless reads are open to anyone ([`crate::config::ServerConfig::check_exposure`]).

use crate::coordinator::RunHandle;
use crate::track::{FILTER_TRACK, TrajectoryLog};
use fleetslam_core::pose::Pose2;
use fleetslam_data::formats::LandmarkRow;
use fleetslam_data::mcap::{LogTime, McapError, RunChannels};
use foxglove::{Context, WebSocketServer, WebSocketServerHandle};
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

/// How long an ended run's topics stay advertised after its last messages are sent. The
/// Foxglove server delivers messages and (un)advertisements from separate queues per
/// client, so an unadvertisement sent at once could overtake the run's last messages.
pub const ENDED_RUN_LINGER: Duration = Duration::from_secs(2);

/// The Foxglove WebSocket server of a fleetslam server.
pub struct FoxgloveLive {
    ctx: Arc<Context>,
    /// Taken by [`FoxgloveLive::stop`].
    server: std::sync::Mutex<Option<WebSocketServerHandle>>,
    addr: SocketAddr,
}

impl std::fmt::Debug for FoxgloveLive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FoxgloveLive")
            .field("addr", &self.addr)
            .finish_non_exhaustive()
    }
}

impl FoxgloveLive {
    /// Starts the server on `bind` (`host:port`; port 0 picks a free one).
    pub async fn start(bind: SocketAddr) -> anyhow::Result<Self> {
        let ctx = Context::new();
        let server = WebSocketServer::new()
            .name("fleetslam")
            .context(&ctx)
            .bind(bind.ip().to_string(), bind.port())
            .start()
            .await
            .map_err(|e| anyhow::anyhow!("starting the Foxglove server on {bind}: {e}"))?;
        let addr = SocketAddr::new(bind.ip(), server.port());
        Ok(Self {
            ctx,
            server: std::sync::Mutex::new(Some(server)),
            addr,
        })
    }

    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Streams a live run's topics until the run ends (see the module's doc).
    pub(crate) fn watch(&self, handle: &RunHandle, state_rate_hz: f64) {
        let channels =
            match RunChannels::new(&self.ctx, &format!("/run/{}", handle.id), LogTime::Wall) {
                Ok(c) => c,
                Err(e) => {
                    tracing::warn!(run = %handle.id, error = %e, "Foxglove live: run not shown");
                    return;
                }
            };
        let period = Duration::from_secs_f64(1.0 / state_rate_hz.max(0.1));
        tokio::spawn(stream(channels, handle.clone(), period));
    }

    /// Stops the server (its clients are disconnected).
    pub fn stop(&self) {
        let server = self
            .server
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take();
        if let Some(s) = server {
            drop(s.stop());
        }
    }
}

async fn stream(mut channels: RunChannels, handle: RunHandle, period: Duration) {
    let (mut state, mut trajectories) = (handle.state.clone(), handle.trajectories.clone());
    // What was sent (or skipped, with nobody subscribed) of each track.
    let mut seen = BTreeMap::new();
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        // Closed: the run ended; its last state and points are sent, then its topics go.
        let (changed, ended) = match state.has_changed() {
            Ok(c) => (c, false),
            Err(_) => (true, true),
        };
        let log: Arc<TrajectoryLog> = trajectories.borrow_and_update().clone();
        let lens = log.lens();
        for robot in lens.keys().filter(|r| r.as_str() != FILTER_TRACK) {
            channels.add_robot(robot);
        }
        if channels.has_sinks() {
            let published = state.borrow_and_update().clone();
            let s = changed.then(|| published.get());
            if let Err(e) = send(&mut channels, &log, &seen, s.as_deref()) {
                tracing::warn!(run = %handle.id, error = %e, "Foxglove live: run not sent");
                break;
            }
        }
        seen = lens;
        if ended {
            break;
        }
    }
    tokio::time::sleep(ENDED_RUN_LINGER).await;
    channels.close();
}

/// Sends the points added since `seen`, and the map and particle samples of `state` when
/// it changed.
fn send(
    channels: &mut RunChannels,
    log: &TrajectoryLog,
    seen: &BTreeMap<String, usize>,
    state: Option<&crate::coordinator::RunState>,
) -> Result<(), McapError> {
    for (track, pts) in log.since(seen) {
        for p in pts {
            if track == FILTER_TRACK {
                channels.filter(p)?;
            } else {
                channels.pose(&track, p[0], &Pose2::new(p[1], p[2], p[3]))?;
            }
        }
    }
    if let Some(s) = state
        && let Some(t) = s.t
    {
        let rows: Vec<LandmarkRow> = s
            .landmarks
            .iter()
            .map(|l| LandmarkRow {
                id: l.id,
                mean: l.mean,
                cov: l.cov,
            })
            .collect();
        channels.landmarks(t, &rows)?;
        for (robot, sample) in &s.particle_sample {
            channels.particles(robot, t, sample)?;
        }
    }
    Ok(())
}
