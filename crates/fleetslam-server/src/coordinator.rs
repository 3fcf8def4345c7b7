//! One coordinator task per run owns the run's filter.
//!
//! Handlers send it commands over a bounded queue (full: the client gets 503 with
//! Retry-After, nothing stored). The task drains what is queued, checks every record
//! (repeat, too old, out of time order), stores the accepted ones in ONE append (group
//! commit: acknowledged means committed), answers each request, feeds the records to the
//! deterministic [`Merger`], and applies what the merger releases on a blocking thread, which
//! steps each batch on a worker of rayon's pool, off the async runtime. The two overlap: while the filter
//! steps through one batch, the task goes on taking requests and storing them, and the next
//! batch starts as soon as the filter is back, so a commit's fsync and the clients' round
//! trips do not leave the filter idle. The state it publishes is the latest estimate in a
//! `watch` channel: readers always see the newest, and a slow reader never slows the filter
//! or makes memory grow.
//!
//! A record the filter fails or panics on is quarantined ([`crate::poison`]): marked in the
//! store with the reason, counted in its robot's status, announced as a `record_quarantined`
//! event, and the filter is rebuilt without it; the run goes on. A run whose filter cannot be
//! rebuilt becomes `failed` in the store with the reason; it stays readable and deletable.

use crate::error::ApiError;
use crate::history::{self, RunMetrics, RunSnapshot, Trajectories};
use crate::merge::{MergeError, Merger, OrderKey};
use crate::poison;
use crate::track::TrajectoryLog;
use fleetslam_core::filter::StepReport;
use fleetslam_core::log::Record;
use fleetslam_core::pose::{Pose2, PoseGaussian};
use fleetslam_localize::LateJoinSlam;
use fleetslam_store::{NewObservation, NewRobot, NewSnapshot, Store};
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, mpsc, oneshot, watch};

/// Limits and rates of a coordinator.
#[derive(Debug, Clone)]
pub struct CoordinatorConfig {
    /// Requests queued per run before the server answers 503.
    pub queue_capacity: usize,
    /// Records acknowledged but not yet stepped through by the filter (in the merge or
    /// waiting for the filter) above which the coordinator takes no more requests while the
    /// filter steps, until it catches up: the requests wait in the queue (beyond
    /// `queue_capacity` they get 503). Acknowledgements do not wait for the filter, so this
    /// is what holds back clients that post faster than the filter runs. Default
    /// [`DEFAULT_MAX_BACKLOG`] (about 0.7 s of filter work with 1,000 particles on MRCLAM);
    /// lower holds clients back sooner, higher lets more memory and lag build up.
    pub max_backlog: usize,
    /// How long a silent robot holds the others back in the merge.
    pub reorder_window: Duration,
    /// Most state publications per second.
    pub state_rate_hz: f64,
    /// Particles per robot in the published state.
    pub particle_sample: usize,
    /// Records applied between two stored snapshots at most (recovery replays at most this
    /// many; scrubbing through a finished run replays at most this many per position).
    pub snapshot_every: u64,
    /// The filter's own stepping time (the steps' time, not the wall clock's) after which a
    /// snapshot falls due, when that comes before `snapshot_every` records: a recovery or a
    /// scrub then replays about this much filter work at most, and snapshots, whose cost
    /// grows with the particles as a step's does, take a bounded share of the filter's time
    /// however many records a step takes. Default [`DEFAULT_SNAPSHOT_EVERY_WORK`].
    pub snapshot_every_work: Duration,
    /// How far a record's time may lie ahead of the run's clock [s] (see
    /// [`Coordinator::clock`]).
    pub max_future_s: f64,
    /// Websocket clients (`GET live`) of one run at a time; more get a 503. Default
    /// [`crate::ws_limit::DEFAULT_WS_MAX_PER_RUN`] (32). Each costs a task and a state
    /// serialization per publication.
    pub ws_max_per_run: usize,
    /// Websocket clients of all runs together; more get a 503. Default
    /// [`crate::ws_limit::DEFAULT_WS_MAX_TOTAL`] (256).
    pub ws_max_total: usize,
    /// How often a live websocket is pinged and sent a heartbeat message (see
    /// [`crate::ws_limit::Heartbeat`]). Default
    /// [`crate::ws_limit::DEFAULT_WS_HEARTBEAT`] (5 s).
    pub ws_heartbeat: Duration,
}

impl Default for CoordinatorConfig {
    fn default() -> Self {
        Self {
            queue_capacity: 256,
            max_backlog: DEFAULT_MAX_BACKLOG,
            reorder_window: Duration::from_secs(2),
            state_rate_hz: 10.0,
            particle_sample: 100,
            snapshot_every: DEFAULT_SNAPSHOT_EVERY,
            snapshot_every_work: DEFAULT_SNAPSHOT_EVERY_WORK,
            max_future_s: crate::limits::Limits::default().max_future_s,
            ws_max_per_run: crate::ws_limit::DEFAULT_WS_MAX_PER_RUN,
            ws_max_total: crate::ws_limit::DEFAULT_WS_MAX_TOTAL,
            ws_heartbeat: crate::ws_limit::DEFAULT_WS_HEARTBEAT,
        }
    }
}

/// The merge's clock: when a silent robot stops holding the others back.
///
/// A single server uses the wall clock. A cluster replica that owns a run reads the run's
/// records from its JetStream stream and uses the stream's own clock instead (the time
/// JetStream stored each message, [`Clock::advance`]d by [`crate::cluster`] before each
/// message is handed over): which robot counts as silent is then a function of the stream,
/// so a replica that takes the run over replays it to the same decisions.
#[derive(Debug, Clone, Default)]
pub enum Clock {
    #[default]
    Wall,
    Stream(Arc<Mutex<Instant>>),
}

impl Clock {
    /// A stream clock that starts at `at`.
    pub fn stream(at: Instant) -> Self {
        Clock::Stream(Arc::new(Mutex::new(at)))
    }

    pub fn now(&self) -> Instant {
        match self {
            Clock::Wall => Instant::now(),
            Clock::Stream(t) => *t.lock().unwrap_or_else(|p| p.into_inner()),
        }
    }

    /// Moves a stream clock forward to `to` (never back); the wall clock ignores it.
    pub fn advance(&self, to: Instant) {
        if let Clock::Stream(t) = self {
            let mut t = t.lock().unwrap_or_else(|p| p.into_inner());
            if to > *t {
                *t = to;
            }
        }
    }

    /// Whether the coordinator wakes up by itself for a silent robot (the wall clock), or
    /// only when the stream moves its clock.
    fn wakes(&self) -> bool {
        matches!(self, Clock::Wall)
    }
}

/// What became of one posted record.
#[derive(Debug, Clone, Serialize, PartialEq, utoipa::ToSchema)]
pub struct RecordAck {
    pub seq: u64,
    /// `stored` (new, durable), `duplicate` (stored before; acknowledged again, applied once)
    /// or `rejected` (not stored; see `error`).
    pub status: &'static str,
    /// Arrival number in the run's stored log (stored and duplicate records).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub arrival: Option<i64>,
    /// Why a record was rejected, for programs: `too_old`, `time_regression`,
    /// `out_of_order`, `too_far_ahead`, `seq_conflict`, `unknown_robot`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub code: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// A robot's live status.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct RobotStatus {
    pub id: String,
    /// `mapping` (part of the SLAM filter), or, for a robot that joined at an unknown pose,
    /// `localizing` (localized against the run's best map; its records do not change the
    /// map) and then `converged` (waiting for its convergence to hold before it joins).
    pub mode: &'static str,
    #[schema(value_type = Option<Object>)]
    pub best: Option<Pose2>,
    #[schema(value_type = Option<Object>)]
    pub mean: Option<Pose2>,
    pub cov: Option<[[f64; 3]; 3]>,
    /// Highest sequence number acknowledged.
    pub last_seq: Option<u64>,
    /// Time of its latest acknowledged record [s].
    pub last_t: Option<f64>,
    /// Records acknowledged.
    pub records: u64,
    /// Missing sequence numbers below `last_seq` (gaps are accepted and reported).
    pub gaps: u64,
    /// Records refused because their seq was stored before with other content (a robot
    /// that restarted its numbering, or two robots sharing a token).
    pub seq_conflicts: u64,
    /// Its records buffered in the merge, waiting for the other robots.
    pub queue_depth: usize,
    /// How far (in data time) the filter is behind this robot's latest record [s].
    pub lag_s: f64,
    /// Its stored records the filter failed or panicked on (or whose stored body could not
    /// be read back): quarantined, skipped by the filter, recovery, scrubbing, re-runs and
    /// exports. Their seqs stay taken.
    pub quarantined: u64,
    /// Why the latest of them was quarantined.
    pub quarantine_reason: Option<String>,
}

/// A landmark of the best particle.
#[derive(Debug, Clone, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct LandmarkState {
    pub slot: usize,
    pub id: Option<u32>,
    pub mean: [f64; 3],
    /// Upper triangle (xx, xy, xz, yy, yz, zz).
    pub cov: [f64; 6],
}

/// The published state of a run.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct RunState {
    pub run: String,
    pub status: String,
    /// Records applied to the filter.
    pub applied: u64,
    /// Data time of the last applied record [s].
    pub t: Option<f64>,
    /// Data time of the run's start: its earliest trajectory point [s] (a page that opens a
    /// live run mid-way counts data time from it). Absent from a state replayed at a time.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub t_start: Option<f64>,
    pub ess: f64,
    pub particles: usize,
    pub resamples: u64,
    pub robots: Vec<RobotStatus>,
    pub landmarks: Vec<LandmarkState>,
    /// A subsample of particles per robot: `[x, y, theta, weight]`.
    pub particle_sample: BTreeMap<String, Vec<[f64; 4]>>,
    /// Median filter step time over the last publication interval [ms].
    pub step_ms: f64,
    /// Why the run failed (status `failed`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// Events streamed to websocket clients besides the state.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    RobotJoined {
        robot: String,
        mode: String,
    },
    Resampled {
        applied: u64,
        ess: f64,
    },
    LandmarkAdded {
        applied: u64,
        count: usize,
    },
    LandmarkRemoved {
        applied: u64,
        count: usize,
    },
    /// A record the filter failed or panicked on: it is skipped, the run goes on.
    RecordQuarantined {
        robot: String,
        seq: u64,
        reason: String,
    },
    /// The run could not go on: it is `failed` (readable, deletable).
    RunFailed {
        reason: String,
    },
    RunEnded,
}

/// An ingest request waiting for its answer.
type PendingIngest = (
    Vec<Record>,
    oneshot::Sender<Result<Vec<RecordAck>, ApiError>>,
);

/// A request to the coordinator.
#[derive(Debug)]
pub enum Command {
    Ingest {
        records: Vec<Record>,
        reply: oneshot::Sender<Result<Vec<RecordAck>, ApiError>>,
    },
    AddRobot {
        row: NewRobot,
        start: Option<PoseGaussian>,
        t0: Option<f64>,
        /// The robot's row is already in the store (a cluster replica stored it before it
        /// published the registration).
        stored: bool,
        reply: oneshot::Sender<Result<(), ApiError>>,
    },
    End {
        reply: oneshot::Sender<Result<(), ApiError>>,
    },
    /// Store a snapshot now (on shutdown) and answer once it is stored.
    Checkpoint {
        reply: oneshot::Sender<Result<(), ApiError>>,
    },
}

/// The handle the HTTP layer keeps for a running run.
#[derive(Debug, Clone)]
pub struct RunHandle {
    pub id: String,
    tx: mpsc::Sender<Command>,
    /// The latest published state; [`RunHandle::current_state`] reads it.
    pub state: watch::Receiver<Arc<PublishedState>>,
    /// The trajectories, published with each state (just before it): readers never ask the
    /// coordinator, and a publication shares the trajectories' sealed chunks (see
    /// [`TrajectoryLog`]).
    pub trajectories: watch::Receiver<Arc<TrajectoryLog>>,
    pub events: broadcast::Sender<Event>,
}

impl RunHandle {
    async fn call<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<Result<T, ApiError>>) -> Command,
    ) -> Result<T, ApiError> {
        let (reply, rx) = oneshot::channel();
        self.tx.try_send(make(reply)).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => ApiError::Busy {
                message: format!(
                    "run {} is busy: its queue is full; nothing was stored, retry later",
                    self.id
                ),
                retry_after_s: 1,
            },
            mpsc::error::TrySendError::Closed(_) => self.gone(),
        })?;
        rx.await.map_err(|_| self.gone())?
    }

    /// The latest published state (built now if nobody has read it yet, outside the
    /// channel's lock: the coordinator never waits for a reader).
    pub fn current_state(&self) -> Arc<RunState> {
        let published = self.state.borrow().clone();
        published.get()
    }

    /// The answer to a request the coordinator can no longer take.
    fn gone(&self) -> ApiError {
        let state = self.current_state();
        match (&*state.status, &state.reason) {
            ("failed", Some(reason)) => ApiError::Conflict(format!(
                "run {} failed ({reason}): it takes no more data; its state, trajectories and \
                 export can still be read, and DELETE /v1/runs/{} removes it",
                self.id, self.id
            )),
            _ => ApiError::Conflict(format!("run {} has ended", self.id)),
        }
    }

    /// True once the coordinator has stopped (the run ended or failed).
    pub fn is_closed(&self) -> bool {
        self.tx.is_closed()
    }

    pub async fn ingest(&self, records: Vec<Record>) -> Result<Vec<RecordAck>, ApiError> {
        self.call(|reply| Command::Ingest { records, reply }).await
    }

    /// Registers a robot: the coordinator checks its id is free, stores `row`, and adds it
    /// to the filter (a start pose checked by [`crate::limits::check_start`]).
    pub async fn add_robot(
        &self,
        row: NewRobot,
        start: Option<PoseGaussian>,
        t0: Option<f64>,
    ) -> Result<(), ApiError> {
        self.add_robot_row(row, start, t0, false).await
    }

    /// Adds a robot whose row a cluster replica has already stored (see
    /// [`crate::cluster`]); otherwise as [`RunHandle::add_robot`].
    pub async fn add_stored_robot(
        &self,
        row: NewRobot,
        start: Option<PoseGaussian>,
        t0: Option<f64>,
    ) -> Result<(), ApiError> {
        self.add_robot_row(row, start, t0, true).await
    }

    async fn add_robot_row(
        &self,
        row: NewRobot,
        start: Option<PoseGaussian>,
        t0: Option<f64>,
        stored: bool,
    ) -> Result<(), ApiError> {
        self.call(|reply| Command::AddRobot {
            row,
            start,
            t0,
            stored,
            reply,
        })
        .await
    }

    pub async fn end(&self) -> Result<(), ApiError> {
        self.call(|reply| Command::End { reply }).await
    }

    /// Stores a snapshot of the run as it is now.
    pub async fn checkpoint(&self) -> Result<(), ApiError> {
        let (reply, rx) = oneshot::channel();
        // Waits for room: on shutdown nothing else is sent.
        self.tx
            .send(Command::Checkpoint { reply })
            .await
            .map_err(|_| ApiError::Conflict(format!("run {} has ended", self.id)))?;
        rx.await
            .map_err(|_| ApiError::Conflict(format!("run {} has ended", self.id)))?
    }

    /// The latest published trajectories, copied out on the caller's side (never through
    /// the command queue). Read after the state, they are at least as new as it.
    pub fn trajectories(&self) -> Trajectories {
        self.trajectories.borrow().to_map()
    }

    /// The filter's series, published with the trajectories.
    pub fn filter_series(&self) -> Vec<crate::track::FilterPoint> {
        self.trajectories.borrow().filter_series()
    }

    /// Requests waiting in the queue.
    pub fn queue_depth(&self) -> usize {
        self.tx.max_capacity() - self.tx.capacity()
    }
}

/// Per-robot bookkeeping of acknowledged sequence numbers.
#[derive(Debug, Default)]
struct Acked {
    /// Every seq below this is acknowledged.
    contiguous: u64,
    above: BTreeSet<u64>,
    max: Option<u64>,
    last_t: Option<f64>,
    records: u64,
    /// Repeats of a stored seq with other content.
    seq_conflicts: u64,
    /// Quarantined records and the latest one's reason.
    quarantined: u64,
    quarantine_reason: Option<String>,
}

impl Acked {
    fn contains(&self, seq: u64) -> bool {
        seq < self.contiguous || self.above.contains(&seq)
    }

    fn insert(&mut self, seq: u64, t: f64) {
        self.records += 1;
        self.max = Some(self.max.map_or(seq, |m| m.max(seq)));
        self.last_t = Some(self.last_t.map_or(t, |l| l.max(t)));
        if seq == self.contiguous {
            self.contiguous += 1;
            while self.above.remove(&self.contiguous) {
                self.contiguous += 1;
            }
        } else {
            self.above.insert(seq);
        }
    }

    /// The bookkeeping of a robot whose stored records have these seqs (seq -> t).
    fn restore(seqs: &BTreeMap<u64, f64>) -> Self {
        let mut a = Acked::default();
        for (&seq, &t) in seqs {
            a.insert(seq, t);
        }
        a
    }

    fn gaps(&self) -> u64 {
        match self.max {
            Some(m) => m + 1 - self.contiguous - self.above.len() as u64,
            None => 0,
        }
    }
}

/// What a restarted server knows of a run it recovers.
#[derive(Debug)]
pub struct Recovered {
    /// The latest snapshot's filter position (its filter is the one passed to [`spawn`]).
    pub applied: u64,
    pub last: Option<OrderKey>,
    pub trajectories: TrajectoryLog,
    /// How many points of each robot's trajectory the store's pieces already hold.
    pub trajectories_stored: BTreeMap<String, usize>,
    /// Every registered robot: its start time and its stored records' seq -> t.
    pub robots: Vec<(String, f64, BTreeMap<u64, f64>)>,
    /// Stored records not in the snapshot, to apply again (in any order).
    pub pending: Vec<Record>,
    /// Per robot: how many of its stored records are quarantined, and the latest reason.
    pub quarantined: BTreeMap<String, (u64, String)>,
}

/// Starts the coordinator of a new run (`recovered: None`; its filter has no robots yet) or
/// of a run recovered after a restart.
pub fn spawn(
    id: String,
    filter: LateJoinSlam,
    store: Store,
    cfg: CoordinatorConfig,
    recovered: Option<Recovered>,
    training: Option<history::Training>,
    clock: Clock,
) -> RunHandle {
    let (tx, rx) = mpsc::channel(cfg.queue_capacity.max(1));
    let (events, _) = broadcast::channel(256);
    let snapshots = spawn_snapshot_writer(id.clone(), store.clone());
    let (traj_tx, traj_rx) = watch::channel(Arc::new(TrajectoryLog::new()));
    let mut task = Coordinator {
        id: id.clone(),
        filter: None,
        store,
        merger: Merger::new(cfg.reorder_window),
        acked: HashMap::new(),
        start_t: None,
        first_t: None,
        applied: 0,
        last_snapshot: 0,
        work_since_snapshot: Duration::ZERO,
        base: Arc::new(filter.clone()),
        since: Vec::new(),
        failed: None,
        traj_sent: BTreeMap::new(),
        trajectories: TrajectoryLog::new(),
        all_step_ns: Vec::new(),
        observations_at_start: 0,
        snapshots,
        training,
        status: "active".into(),
        step_ns: Vec::new(),
        last_publish: None,
        dirty: false,
        events: events.clone(),
        state_tx: None,
        traj_tx,
        cfg,
        stepping: None,
        queued: VecDeque::new(),
        handed: 0,
        last_applied: None,
        clock,
    };
    if let Some(r) = recovered {
        let now = task.clock.now();
        task.applied = r.applied;
        task.last_snapshot = r.applied;
        task.trajectories = r.trajectories;
        task.traj_sent = r.trajectories_stored;
        task.last_applied = r.last.clone();
        task.merger.restore_applied(r.last);
        for (robot, t0, seqs) in &r.robots {
            task.merger.restore_robot(robot, *t0, seqs, now);
            task.acked.insert(robot.clone(), Acked::restore(seqs));
            if let Some(t) = seqs.values().copied().reduce(f64::min) {
                task.first_t = Some(task.first_t.map_or(t, |f| f.min(t)));
            }
        }
        for rec in r.pending {
            task.merger.restore_pending(rec);
        }
        for (robot, (n, reason)) in r.quarantined {
            if let Some(a) = task.acked.get_mut(&robot) {
                a.quarantined = n;
                a.quarantine_reason = Some(reason);
            }
        }
    }
    task.observations_at_start = filter.slam().stats().observations;
    task.filter = Some(filter);
    let (state_tx, state_rx) = watch::channel(Arc::new(PublishedState::built(task.build_state())));
    task.traj_tx
        .send_replace(Arc::new(task.trajectories.clone()));
    task.state_tx = Some(state_tx);
    tokio::spawn(task.run(rx));
    RunHandle {
        id,
        tx,
        state: state_rx,
        trajectories: traj_rx,
        events,
    }
}

/// A snapshot to write with the training rows recorded since the previous one, and who
/// waits for it.
struct SnapshotJob {
    snap: RunSnapshot,
    rows: Vec<String>,
    /// The trajectory points added since the previous snapshot, and the index each robot's
    /// new points start at.
    points: (Trajectories, BTreeMap<String, usize>),
    reply: Option<oneshot::Sender<Result<(), ApiError>>>,
}

/// Writes a run's snapshots one after another (so that a later one is never overwritten by
/// an earlier one), encoding them off the async runtime. Each snapshot's new trajectory
/// points are stored first (pieces that failed to store are tried again with the next
/// snapshot, so the pieces never have a hole), then the snapshot that covers them.
fn spawn_snapshot_writer(run: String, store: Store) -> mpsc::UnboundedSender<SnapshotJob> {
    let (tx, mut rx) = mpsc::unbounded_channel::<SnapshotJob>();
    tokio::spawn(async move {
        let mut unstored: Vec<fleetslam_store::TrajectoryChunk> = Vec::new();
        // The last snapshot's buffer, encoded into again (it is back here once stored, and
        // lost only when a snapshot fails before that).
        let mut buffer: Vec<u8> = Vec::new();
        while let Some(job) = rx.recv().await {
            let SnapshotJob {
                snap,
                rows,
                points,
                reply,
            } = job;
            let applied = snap.applied;
            let t = snap.filed_t();
            let res = async {
                store.append_training(&run, &rows).await?;
                let mut data = std::mem::take(&mut buffer);
                let (data, chunks) = tokio::task::spawn_blocking(move || {
                    snap.encode_into(&mut data)?;
                    Ok::<_, ApiError>((data, history::trajectory_chunks(&points.0, &points.1)?))
                })
                .await
                .map_err(ApiError::internal)??;
                unstored.extend(chunks);
                let snapshot = NewSnapshot {
                    applied: applied as i64,
                    t,
                    data,
                };
                let stored = async {
                    store.put_trajectory_chunks(&run, &unstored).await?;
                    unstored.clear();
                    store.put_snapshot(&run, &snapshot).await
                }
                .await;
                buffer = snapshot.data;
                stored?;
                Ok(())
            }
            .await;
            if let Err(e) = &res {
                tracing::error!(run = %run, applied, error = %e, "storing a snapshot failed");
            }
            if let Some(reply) = reply {
                let _ = reply.send(res);
            }
        }
    });
    tx
}

struct Coordinator {
    id: String,
    /// Taken while a blocking thread steps it.
    filter: Option<LateJoinSlam>,
    store: Store,
    merger: Merger,
    acked: HashMap<String, Acked>,
    /// The latest start time given at a registration (`t0`).
    start_t: Option<f64>,
    /// The earliest time of a record stored in the run.
    first_t: Option<f64>,
    applied: u64,
    /// `applied` at the last snapshot.
    last_snapshot: u64,
    /// The filter's stepping time since the last snapshot (see
    /// [`CoordinatorConfig::snapshot_every_work`]).
    work_since_snapshot: Duration,
    /// The filter as of the last snapshot (or the start), and the records applied since:
    /// what the filter is rebuilt from after a poison record, as a restart would.
    base: Arc<LateJoinSlam>,
    since: Vec<Record>,
    /// Why the run failed, once it has.
    failed: Option<String>,
    /// How many trajectory points of each robot went to the snapshot writer.
    traj_sent: BTreeMap<String, usize>,
    trajectories: TrajectoryLog,
    /// Every step time of this process's life of the run [ns].
    all_step_ns: Vec<u64>,
    /// The filter's landmark observation count when this process took the run (after a
    /// recovery, what the snapshot's filter had applied), so that the metrics divide the
    /// step times by the observations of those steps.
    observations_at_start: u64,
    snapshots: mpsc::UnboundedSender<SnapshotJob>,
    /// The run logs a sample of its landmark updates as training rows: they are stored with
    /// each snapshot, so a recovery re-records exactly those after the latest one.
    training: Option<history::Training>,
    status: String,
    step_ns: Vec<u64>,
    last_publish: Option<Instant>,
    /// Something changed since the last published state.
    dirty: bool,
    events: broadcast::Sender<Event>,
    state_tx: Option<watch::Sender<Arc<PublishedState>>>,
    traj_tx: watch::Sender<Arc<TrajectoryLog>>,
    cfg: CoordinatorConfig,
    /// The filter's steps under way on a blocking thread; while it is `Some`, `filter`,
    /// `trajectories` and `since` are away with it.
    stepping: Option<tokio::task::JoinHandle<Stepped>>,
    /// Records the merger released, in order, that the filter has not stepped through yet.
    queued: VecDeque<Record>,
    /// How many records the steps under way were given.
    handed: usize,
    /// The key of the last record the filter stepped through (or quarantined): what the
    /// filter holds, which snapshots record. The merger's own position is ahead of it by
    /// the records in `queued` and under way.
    last_applied: Option<OrderKey>,
    clock: Clock,
}

/// What a blocking thread hands back: the filter, trajectories and records since the last
/// snapshot it took, what its steps did, and the records it had no time for.
type Stepped = (
    LateJoinSlam,
    TrajectoryLog,
    Vec<Record>,
    Applied,
    VecDeque<Record>,
);

/// Waits for the steps under way (never resolves when there are none).
async fn stepped(
    stepping: &mut Option<tokio::task::JoinHandle<Stepped>>,
) -> Result<Stepped, tokio::task::JoinError> {
    match stepping {
        Some(h) => h.await,
        None => std::future::pending().await,
    }
}

/// The most requests drained into one group commit.
const MAX_DRAIN: usize = 64;

/// Default of [`CoordinatorConfig::max_backlog`].
pub const DEFAULT_MAX_BACKLOG: usize = 2048;

/// Default of [`CoordinatorConfig::snapshot_every`].
pub const DEFAULT_SNAPSHOT_EVERY: u64 = 20_000;

/// Default of [`CoordinatorConfig::snapshot_every_work`].
pub const DEFAULT_SNAPSHOT_EVERY_WORK: Duration = Duration::from_millis(500);

impl Coordinator {
    async fn run(mut self, mut rx: mpsc::Receiver<Command>) {
        let mut end_reply = None;
        loop {
            // Wake up for a silent robot's window, or to publish a state the throttle held;
            // both wait while the filter steps (its return wakes the task).
            let deadline = if self.stepping.is_some() {
                None
            } else {
                let silent = self.merger.next_deadline().filter(|_| self.clock.wakes());
                match (silent, self.publish_due()) {
                    (Some(a), Some(b)) => Some(a.min(b)),
                    (a, b) => a.or(b),
                }
            };
            let first = tokio::select! {
                cmd = rx.recv(), if self.stepping.is_none() || self.backlog() < self.cfg.max_backlog => {
                    match cmd { Some(c) => Some(c), None => break }
                }
                res = stepped(&mut self.stepping), if self.stepping.is_some() => {
                    self.stepping = None;
                    self.finish_apply(res).await;
                    self.between_steps();
                    None
                }
                _ = async {
                    match deadline {
                        Some(d) => tokio::time::sleep_until(d.into()).await,
                        None => std::future::pending().await,
                    }
                } => None,
            };
            let mut cmds: Vec<Command> = first.into_iter().collect();
            while cmds.len() < MAX_DRAIN {
                match rx.try_recv() {
                    Ok(c) => cmds.push(c),
                    Err(_) => break,
                }
            }
            let mut ingests = Vec::new();
            let mut checkpoints = Vec::new();
            let mut ended = false;
            for c in cmds {
                match c {
                    Command::Ingest { records, reply } => ingests.push((records, reply)),
                    Command::AddRobot {
                        row,
                        start,
                        t0,
                        stored,
                        reply,
                    } => {
                        // The filter and the trajectories must be home.
                        self.settle().await;
                        let r = match &self.failed {
                            Some(reason) => Err(ApiError::Conflict(format!(
                                "run {} failed ({reason}): it takes no more robots",
                                self.id
                            ))),
                            None => self.add_robot(row, start, t0, stored).await,
                        };
                        let _ = reply.send(r);
                    }
                    Command::End { reply } => {
                        ended = true;
                        end_reply = Some(reply);
                    }
                    Command::Checkpoint { reply } => checkpoints.push(reply),
                }
            }
            if !ingests.is_empty() {
                self.ingest(ingests).await;
            }
            if ended || !checkpoints.is_empty() {
                self.settle().await;
            }
            if ended {
                // Everything the merger holds, in order, with the snapshots that fall due on
                // the way (a run ended while a backlog was left still stores one every
                // `snapshot_every` records).
                while self.failed.is_none() && self.start_apply(true) {
                    self.settle().await;
                    self.snapshot_if_due();
                }
            }
            if let Some(reason) = &self.failed {
                if let Some(reply) = end_reply.take() {
                    let _ = reply.send(Err(ApiError::Conflict(format!(
                        "run {} failed while ending ({reason}); its state, trajectories and \
                         export can still be read, and DELETE /v1/runs/{} removes it",
                        self.id, self.id
                    ))));
                }
                break;
            }
            if ended {
                self.status = "ended".into();
                let _ = self.events.send(Event::RunEnded);
                self.publish(true);
                let stored = self.finish().await;
                // Answered only now, so that the caller sees the final state.
                if let Some(reply) = end_reply.take() {
                    let _ = reply.send(stored);
                }
                break;
            }
            for reply in checkpoints {
                let (tx, rx) = oneshot::channel();
                self.snapshot(Some(tx));
                let stored = rx.await.map_err(ApiError::internal).and_then(|r| r);
                let _ = reply.send(stored);
            }
            self.between_steps();
        }
        // The steps under way end with the task; their records are stored, and a restart
        // applies them again.
        self.settle().await;
    }

    /// Records acknowledged that the filter has not stepped through: in the merge, waiting
    /// for the filter, and under way.
    fn backlog(&self) -> usize {
        self.merger.pending() + self.queued.len() + self.handed
    }

    /// While the filter is home: stores a snapshot when one is due, publishes the state
    /// (throttled), and starts stepping through what the merger releases.
    fn between_steps(&mut self) {
        if self.stepping.is_some() || self.filter.is_none() || self.failed.is_some() {
            return;
        }
        self.snapshot_if_due();
        self.publish(false);
        self.start_apply(false);
    }

    /// Queues a snapshot when `snapshot_every` records have been applied since the last
    /// one, or the filter has stepped for `snapshot_every_work` through at least one record
    /// since (the filter must be home).
    fn snapshot_if_due(&mut self) {
        if self.filter.is_some()
            && self.failed.is_none()
            && (self.applied >= self.last_snapshot + self.cfg.snapshot_every.max(1)
                || (self.applied > self.last_snapshot
                    && self.work_since_snapshot >= self.cfg.snapshot_every_work))
        {
            self.snapshot(None);
        }
    }

    /// Queues a snapshot of the current filter; `reply` hears when it is stored.
    fn snapshot(&mut self, reply: Option<oneshot::Sender<Result<(), ApiError>>>) {
        let filter = self
            .filter
            .as_ref()
            .expect("the filter is home between steps");
        let snap = RunSnapshot {
            filter: filter.snapshot(),
            applied: self.applied,
            // The records released by the merger but not stepped through yet are not in
            // the filter: a recovery applies them again.
            last: self
                .last_applied
                .as_ref()
                .map(|k| (k.t(), k.robot().to_string(), k.seq())),
            // The points are stored in pieces beside it: only those added since the
            // previous snapshot go with this one.
            trajectories: Trajectories::new(),
            trajectory_lens: Some(self.trajectories.lens()),
            training: self.training.as_ref().map(|(c, _)| *c),
        };
        let rows = self.training.as_ref().map_or_else(Vec::new, |(_, r)| {
            r.drain_rows().iter().map(|row| row.to_json()).collect()
        });
        let points = self.trajectories.since(&self.traj_sent);
        let from = std::mem::replace(&mut self.traj_sent, self.trajectories.lens());
        self.last_snapshot = self.applied;
        self.work_since_snapshot = Duration::ZERO;
        self.base = Arc::new(filter.clone());
        self.since.clear();
        let job = SnapshotJob {
            snap,
            rows,
            points: (points, from),
            reply,
        };
        if let Err(mpsc::error::SendError(job)) = self.snapshots.send(job)
            && let Some(reply) = job.reply
        {
            let _ = reply.send(Err(ApiError::internal(anyhow::anyhow!(
                "the snapshot writer has stopped"
            ))));
        }
    }

    /// Stores a final snapshot and the run's result; called when the run ends.
    async fn finish(&mut self) -> Result<(), ApiError> {
        let (tx, rx) = oneshot::channel();
        self.snapshot(Some(tx));
        rx.await.map_err(ApiError::internal)??;
        let state = self.build_state();
        let metrics = self.metrics(&state);
        let trajectories = self.trajectories.to_map();
        let body = serde_json::to_string(&history::RunResult {
            state: &state,
            trajectories: &trajectories,
            metrics: &metrics,
        })
        .map_err(ApiError::internal)?;
        self.store
            .put_artifact(&self.id, history::RESULT, &body)
            .await?;
        Ok(())
    }

    fn metrics(&self, state: &RunState) -> RunMetrics {
        let filter = self
            .filter
            .as_ref()
            .expect("the filter is home between steps");
        let mut ns = self.all_step_ns.clone();
        ns.sort_unstable();
        let pct = |p: f64| {
            ns.get(((ns.len().max(1) - 1) as f64 * p).round() as usize)
                .map_or(0.0, |v| *v as f64 / 1e6)
        };
        let stats = filter.slam().stats();
        let particles = filter.slam().config().particles;
        let total_s = ns.iter().sum::<u64>() as f64 / 1e9;
        RunMetrics {
            applied: self.applied,
            t_start: self.trajectories.first_t(),
            step_ms_p50: pct(0.5),
            step_ms_p95: pct(0.95),
            step_ms_mean: if ns.is_empty() {
                0.0
            } else {
                ns.iter().sum::<u64>() as f64 / ns.len() as f64 / 1e6
            },
            landmark_updates: stats.landmark_updates,
            ns_per_landmark_update: if stats.landmark_updates > 0 {
                stats.update_nanos as f64 / stats.landmark_updates as f64
            } else {
                0.0
            },
            updater: filter.slam().config().updater.clone(),
            particles: filter.slam().config().particles,
            seed: filter.slam().config().seed,
            resamples: stats.resamples,
            landmarks: state.landmarks.len(),
            final_ess: state.ess,
            ns_per_particle_record: fleetslam_data::run::per_particle_ns(
                total_s,
                particles,
                ns.len() as u64,
            ),
            ns_per_particle_observation: fleetslam_data::run::per_particle_ns(
                total_s,
                particles,
                stats
                    .observations
                    .saturating_sub(self.observations_at_start),
            ),
        }
    }

    async fn add_robot(
        &mut self,
        row: NewRobot,
        start: Option<PoseGaussian>,
        t0: Option<f64>,
        stored: bool,
    ) -> Result<(), ApiError> {
        let robot = row.robot_id.clone();
        if self.acked.contains_key(&robot) {
            return Err(ApiError::Conflict(format!(
                "robot {robot:?} is already registered in this run"
            )));
        }
        // The handler checked the id, t0 and start pose as the filter does, so the filter
        // cannot refuse the robot once it is stored.
        if !stored {
            self.store.add_robot(&self.id, &row).await?;
        }
        if let Some(t) = t0 {
            self.start_t = Some(self.start_t.map_or(t, |s| s.max(t)));
        }
        let t0 = t0.unwrap_or(0.0);
        let filter = self
            .filter
            .as_mut()
            .expect("the filter is home between steps");
        let added = match &start {
            Some(s) => filter.add_robot(&robot, s, t0).map(|i| {
                self.trajectories.insert(
                    robot.clone(),
                    vec![history::trajectory_point(filter.slam(), i, t0)],
                );
            }),
            // Localized against the run's map first, then inserted into every particle.
            None => filter.add_unknown_robot(&robot),
        };
        if let Err(e) = added {
            return Err(ApiError::internal(anyhow::anyhow!(
                "robot {robot:?} was stored but the filter refused it: {e}"
            )));
        }
        let mode = filter.phase(&robot).map_or("mapping", |p| p.as_str());
        // Every robot's records go through the merge, in the one deterministic order.
        self.merger.add_robot(&robot, t0, 0, self.clock.now());
        self.acked.insert(robot.clone(), Acked::default());
        // A recovery restores robots from snapshots: store one that has this robot before
        // the registration is answered.
        let (tx, rx) = oneshot::channel();
        self.snapshot(Some(tx));
        rx.await.map_err(ApiError::internal)??;
        let _ = self.events.send(Event::RobotJoined {
            robot,
            mode: mode.into(),
        });
        self.publish(true);
        Ok(())
    }

    /// The run's clock, against which `max_future_s` bounds a record's time: the time of the
    /// last applied record; before any, the latest start time given at a registration; before
    /// that, the earliest stored record's time; before any record, `fallback`.
    fn clock(&self, fallback: Option<f64>) -> Option<f64> {
        self.merger
            .applied_t()
            .or(self.start_t)
            .or(self.first_t)
            .or(fallback)
    }

    /// Checks, stores (one append for all requests) and acknowledges records.
    async fn ingest(&mut self, ingests: Vec<PendingIngest>) {
        /// What becomes of one record.
        enum Plan {
            Ack(RecordAck),
            /// Index into the batch to store.
            Store(usize),
            /// Index into `repeats`: a seq stored before, to compare with.
            Repeat(usize),
        }
        let mut plans: Vec<Vec<Plan>> = Vec::with_capacity(ingests.len());
        let mut batch: Vec<(Record, String)> = Vec::new();
        let mut in_batch: HashMap<(String, u64), usize> = HashMap::new();
        let mut repeats: Vec<(String, u64, String)> = Vec::new();
        // Times of the records accepted so far in this batch, per robot, by seq: a robot's
        // time must not go back as its seq goes up, within the batch as against the merge.
        let mut batch_times: HashMap<String, BTreeMap<u64, f64>> = HashMap::new();
        let earliest = ingests
            .iter()
            .flat_map(|(rs, _)| rs.iter().map(|r| r.t))
            .reduce(f64::min);
        let clock = self.clock(earliest);
        let max_future = self.cfg.max_future_s;
        for (records, _) in &ingests {
            let mut plan = Vec::with_capacity(records.len());
            for r in records {
                let body = match serde_json::to_string(r) {
                    Ok(b) => b,
                    Err(e) => {
                        plan.push(Plan::Ack(reject(
                            r.seq,
                            "invalid",
                            format!("cannot encode: {e}"),
                        )));
                        continue;
                    }
                };
                let Some(acked) = self.acked.get_mut(&r.robot) else {
                    plan.push(Plan::Ack(reject(
                        r.seq,
                        "unknown_robot",
                        format!("robot {:?} is not registered in this run", r.robot),
                    )));
                    continue;
                };
                if let Some(&i) = in_batch.get(&(r.robot.clone(), r.seq)) {
                    if batch[i].1 == body {
                        plan.push(Plan::Store(i));
                    } else {
                        acked.seq_conflicts += 1;
                        plan.push(Plan::Ack(seq_conflict(&r.robot, r.seq)));
                    }
                    continue;
                }
                if acked.contains(r.seq) {
                    plan.push(Plan::Repeat(repeats.len()));
                    repeats.push((r.robot.clone(), r.seq, body));
                    continue;
                }
                if let Some(c) = clock
                    && r.t > c + max_future
                {
                    plan.push(Plan::Ack(reject(
                        r.seq,
                        "too_far_ahead",
                        format!(
                            "t={} is {:.0} s ahead of the run's clock (t={c}); at most \
                             max_future_s = {max_future} s ahead is accepted",
                            r.t,
                            r.t - c
                        ),
                    )));
                    continue;
                }
                if let Err(e) = self.merger.check(r) {
                    let (code, msg) = match e {
                        MergeError::TooOld { .. } => (
                            "too_old",
                            format!(
                                "{e} (reorder window {} ms)",
                                self.cfg.reorder_window.as_millis()
                            ),
                        ),
                        MergeError::TimeRegression { .. } => ("time_regression", e.to_string()),
                        MergeError::UnknownRobot(_) => ("unknown_robot", e.to_string()),
                    };
                    plan.push(Plan::Ack(reject(r.seq, code, msg)));
                    continue;
                }
                let times = batch_times.entry(r.robot.clone()).or_default();
                let before = times.range(..r.seq).next_back().map(|(s, t)| (*s, *t));
                let after = times.range(r.seq + 1..).next().map(|(s, t)| (*s, *t));
                if let Some((s, t)) = before
                    .filter(|(_, t)| r.t < *t)
                    .or(after.filter(|(_, t)| r.t > *t))
                {
                    plan.push(Plan::Ack(reject(
                        r.seq,
                        "out_of_order",
                        format!(
                            "record {} of robot {:?} at t={} is out of time order with its record {s} at t={t}",
                            r.seq, r.robot, r.t
                        ),
                    )));
                    continue;
                }
                times.insert(r.seq, r.t);
                in_batch.insert((r.robot.clone(), r.seq), batch.len());
                plan.push(Plan::Store(batch.len()));
                batch.push((r.clone(), body));
            }
            plans.push(plan);
        }
        // A repeated seq is a duplicate only if its content is what was stored.
        let mut repeat_acks: Vec<RecordAck> = Vec::with_capacity(repeats.len());
        for (robot, seq, body) in &repeats {
            let stored = match self.store.record_body(&self.id, robot, *seq as i64).await {
                Ok(b) => b,
                Err(e) => {
                    let e = Arc::new(e);
                    for (_, reply) in ingests {
                        let _ = reply.send(Err(ApiError::internal(anyhow::anyhow!(
                            "reading a stored record: {e}"
                        ))));
                    }
                    return;
                }
            };
            // A quarantined record's fate is decided: a repeat of its seq is acknowledged
            // (its stored body may be what could not be read back).
            let same = match &stored {
                Some((_, Some(_))) => true,
                Some((b, None)) => b == body,
                None => false,
            };
            repeat_acks.push(if same {
                RecordAck {
                    seq: *seq,
                    status: "duplicate",
                    arrival: None,
                    code: None,
                    error: None,
                }
            } else {
                if let Some(a) = self.acked.get_mut(robot) {
                    a.seq_conflicts += 1;
                }
                seq_conflict(robot, *seq)
            });
        }
        let (batch, bodies): (Vec<Record>, Vec<String>) = batch.into_iter().unzip();
        let stored = if batch.is_empty() {
            Ok(Vec::new())
        } else {
            let obs = batch
                .iter()
                .zip(bodies)
                .map(|(r, body)| NewObservation {
                    robot_id: r.robot.clone(),
                    seq: r.seq as i64,
                    t: r.t,
                    body,
                })
                .collect();
            let (store, id) = (self.store.clone(), self.id.clone());
            let append = async move { store.append(&id, obs).await.map(|o| o.items) };
            tokio::pin!(append);
            // The filter keeps stepping while the commit flushes; steps that end meanwhile
            // are taken in, but the next batch waits for these records to be in the merge
            // (they were checked against it as it is now).
            loop {
                tokio::select! {
                    stored = &mut append => break stored,
                    res = stepped(&mut self.stepping), if self.stepping.is_some() => {
                        self.stepping = None;
                        self.finish_apply(res).await;
                    }
                }
            }
        };
        let stored = match stored {
            Ok(items) => items,
            Err(e) => {
                let e = Arc::new(e);
                for (_, reply) in ingests {
                    let _ = reply.send(Err(ApiError::internal(anyhow::anyhow!(
                        "storing records: {e}"
                    ))));
                }
                return;
            }
        };
        // Durable now: update bookkeeping, feed the merger, answer.
        let now = self.clock.now();
        for (rec, item) in batch.iter().zip(&stored) {
            let acked = self.acked.get_mut(&rec.robot).expect("checked above");
            if !item.duplicate {
                acked.insert(rec.seq, rec.t);
                self.first_t = Some(self.first_t.map_or(rec.t, |f| f.min(rec.t)));
                // Checked above; the only failure left would be a bug.
                if let Err(e) = self.merger.push(rec.clone(), now) {
                    tracing::error!(run = %self.id, error = %e, "merge refused a checked record");
                }
            }
        }
        // A record posted twice in one batch is stored once; the second is a duplicate.
        let mut answered: BTreeSet<usize> = BTreeSet::new();
        for ((_, reply), plan) in ingests.into_iter().zip(plans) {
            let acks = plan
                .into_iter()
                .map(|p| match p {
                    Plan::Ack(a) => a,
                    Plan::Repeat(i) => repeat_acks[i].clone(),
                    Plan::Store(i) => RecordAck {
                        seq: batch[i].seq,
                        status: if stored[i].duplicate || !answered.insert(i) {
                            "duplicate"
                        } else {
                            "stored"
                        },
                        arrival: Some(stored[i].arrival),
                        code: None,
                        error: None,
                    },
                })
                .collect();
            let _ = reply.send(Ok(acks));
        }
    }

    /// Starts stepping the filter through the records the merger releases (all it holds
    /// when `flush`) on a blocking thread, unless the filter is away or nothing is ready;
    /// says whether it started. A record the filter fails or panics on is quarantined and
    /// the filter rebuilt without it (see [`poison`]); a filter that cannot be rebuilt
    /// fails the run ([`Coordinator::finish_apply`]).
    fn start_apply(&mut self, flush: bool) -> bool {
        if self.stepping.is_some() || self.failed.is_some() {
            return false;
        }
        let Some(mut filter) = self.filter.take() else {
            return false;
        };
        self.queued
            .extend(self.merger.ready(self.clock.now(), flush));
        if self.queued.is_empty() {
            self.filter = Some(filter);
            return false;
        }
        let mut records = std::mem::take(&mut self.queued);
        self.handed = records.len();
        // The thread comes back after about one publication interval, so that states go
        // out while a backlog is worked off, and when a snapshot is due, so that snapshots
        // fall every `snapshot_every` records or `snapshot_every_work` of stepping however
        // fast the filter runs.
        let budget = self.min_gap();
        let due =
            (self.last_snapshot + self.cfg.snapshot_every.max(1)).saturating_sub(self.applied);
        let due_work = self
            .cfg
            .snapshot_every_work
            .saturating_sub(self.work_since_snapshot);
        let mut trajectories = std::mem::take(&mut self.trajectories);
        let base = self.base.clone();
        let mut since = std::mem::take(&mut self.since);
        let recorder = self.training.as_ref().map(|(_, r)| r.clone());
        self.stepping = Some(tokio::task::spawn_blocking(move || {
            let mut out = Applied::default();
            let started = Instant::now();
            let mut work = Duration::ZERO;
            // The batch runs on a worker of rayon's pool, as `run_log` steps: each step's
            // parallel parts (its work items, the weights' exps, the resample) are then
            // joins inside the pool, where from this blocking thread each was a job sent to
            // the pool and waited for (MRCLAM's steps in `server_overhead`, session 23: 7.2-7.5
            // s from the blocking thread, 4.7-4.8 s inside the pool).
            rayon::scope(|_| {
                while let Some(r) = records.pop_front() {
                    if !out.reports.is_empty()
                        && (started.elapsed() >= budget
                            || out.reports.len() as u64 >= due
                            || work >= due_work)
                    {
                        records.push_front(r);
                        break;
                    }
                    let t0 = Instant::now();
                    out.last = Some(OrderKey::of(&r));
                    match poison::try_step(&mut filter, &r) {
                        Ok(rep) => {
                            let took = t0.elapsed();
                            work += took;
                            let ns = took.as_nanos() as u64;
                            if rep.joined {
                                out.joins.push(r.robot.clone());
                            }
                            trajectories.push_filter(history::filter_point(
                                filter.slam(),
                                rep.slam.as_ref(),
                                trajectories.last_filter(),
                                r.t,
                                ns,
                            ));
                            out.reports.push((rep.slam, ns));
                            if let Some(i) = filter.slam().robot_index(&r.robot) {
                                trajectories.push(
                                    &r.robot,
                                    history::trajectory_point(filter.slam(), i, r.t),
                                );
                            }
                            since.push(r);
                        }
                        Err(why) => {
                            out.quarantined.push((r.robot.clone(), r.seq, why));
                            match poison::rebuild(&base, &since, recorder.as_deref()) {
                                Ok(f) => filter = f,
                                Err(e) => {
                                    out.fatal = Some(e);
                                    break;
                                }
                            }
                        }
                    }
                }
            });
            (filter, trajectories, since, out, records)
        }));
        true
    }

    /// Waits for the steps under way, if any, and takes in what they did.
    async fn settle(&mut self) {
        if let Some(h) = self.stepping.take() {
            let res = h.await;
            self.finish_apply(res).await;
        }
    }

    /// Takes in what a batch of steps did: the filter comes home, events go out, quarantined
    /// records are marked; a filter lost fails the run.
    async fn finish_apply(&mut self, res: Result<Stepped, tokio::task::JoinError>) {
        let (filter, trajectories, since, out, rest) = match res {
            Ok(v) => v,
            Err(e) => {
                // Only a bug outside the guarded steps gets here; the filter is lost.
                self.fail(format!("the coordinator's step thread failed: {e}"))
                    .await;
                return;
            }
        };
        self.trajectories = trajectories;
        self.since = since;
        // Nothing is released while the filter is away: these come first.
        debug_assert!(self.queued.is_empty());
        self.queued = rest;
        self.handed = 0;
        if out.last.is_some() {
            self.last_applied = out.last.clone();
        }
        if out.fatal.is_none() {
            self.filter = Some(filter);
        }
        for robot in out.joins {
            let _ = self.events.send(Event::RobotJoined {
                robot,
                mode: "mapping".into(),
            });
        }
        for (rep, ns) in out.reports {
            self.applied += 1;
            self.work_since_snapshot += Duration::from_nanos(ns);
            self.step_ns.push(ns);
            self.all_step_ns.push(ns);
            let Some(rep) = rep else { continue };
            if rep.resampled {
                let _ = self.events.send(Event::Resampled {
                    applied: self.applied,
                    ess: rep.ess,
                });
            }
            if rep.landmarks_added > 0 {
                let _ = self.events.send(Event::LandmarkAdded {
                    applied: self.applied,
                    count: rep.landmarks_added,
                });
            }
            if rep.landmarks_removed > 0 {
                let _ = self.events.send(Event::LandmarkRemoved {
                    applied: self.applied,
                    count: rep.landmarks_removed,
                });
            }
        }
        for (robot, seq, reason) in out.quarantined {
            self.quarantine(robot, seq, reason).await;
        }
        if let Some(e) = out.fatal {
            self.fail(e).await;
        }
    }

    /// Records a quarantined record: in the store (so that a restart skips it), in its
    /// robot's status and as an event.
    async fn quarantine(&mut self, robot: String, seq: u64, reason: String) {
        tracing::warn!(run = %self.id, robot = %robot, seq, reason = %reason, "record quarantined");
        match self
            .store
            .quarantine(&self.id, &robot, seq as i64, &reason)
            .await
        {
            Ok(true) => {}
            Ok(false) => {
                tracing::error!(run = %self.id, robot = %robot, seq, "a quarantined record is not in the store")
            }
            // A restart applies it again, fails again and quarantines it then.
            Err(e) => {
                tracing::error!(run = %self.id, robot = %robot, seq, error = %e, "marking a quarantined record failed")
            }
        }
        if let Some(a) = self.acked.get_mut(&robot) {
            a.quarantined += 1;
            a.quarantine_reason = Some(reason.clone());
        }
        let _ = self
            .events
            .send(Event::RecordQuarantined { robot, seq, reason });
        self.dirty = true;
    }

    /// The run cannot go on: it becomes `failed` in the store with the reason, its last
    /// state is published with that status, and the coordinator stops (the caller breaks
    /// out of its loop).
    async fn fail(&mut self, reason: String) {
        tracing::error!(run = %self.id, reason = %reason, "the run failed");
        self.status = "failed".into();
        if let Err(e) = self.store.set_run_failed(&self.id, &reason).await {
            tracing::error!(run = %self.id, error = %e, "marking the run failed in the store failed");
        }
        if let Some(tx) = &self.state_tx {
            let mut s = match &self.filter {
                Some(_) => self.build_state(),
                None => {
                    let last = tx.borrow().clone();
                    (*last.get()).clone()
                }
            };
            s.status = "failed".into();
            s.reason = Some(reason.clone());
            tx.send_replace(Arc::new(PublishedState::built(s)));
        }
        let _ = self.events.send(Event::RunFailed {
            reason: reason.clone(),
        });
        self.failed = Some(reason);
    }

    fn min_gap(&self) -> Duration {
        Duration::from_secs_f64(1.0 / self.cfg.state_rate_hz.max(0.1))
    }

    /// When a state held back by the throttle is due.
    fn publish_due(&self) -> Option<Instant> {
        match (self.dirty, self.last_publish) {
            (true, Some(l)) => Some(l + self.min_gap()),
            (true, None) => Some(Instant::now()),
            _ => None,
        }
    }

    fn publish(&mut self, force: bool) {
        if self.filter.is_none() {
            // Away stepping (or lost): published once it is home.
            self.dirty = true;
            return;
        }
        if !force
            && self
                .last_publish
                .is_some_and(|l| l.elapsed() < self.min_gap())
        {
            self.dirty = true;
            return;
        }
        self.dirty = false;
        self.last_publish = Some(Instant::now());
        let filter = self.filter.as_ref().expect("checked above").clone();
        let state = Arc::new(PublishedState::lazy(self.capture(), filter));
        self.step_ns.clear();
        // The trajectories first: a reader that reads the state, then the trajectories, gets
        // trajectories at least as new as the state.
        self.traj_tx
            .send_replace(Arc::new(self.trajectories.clone()));
        if let Some(tx) = &self.state_tx {
            tx.send_replace(state);
        }
    }

    /// The state now, built here (the final state, a failed run's).
    fn build_state(&self) -> RunState {
        let filter = self
            .filter
            .as_ref()
            .expect("the filter is home between steps");
        self.capture().build(filter)
    }

    /// The coordinator's part of the state now; [`StateParts::build`] adds the filter's.
    fn capture(&self) -> StateParts {
        let applied_t = self.last_applied.as_ref().map(OrderKey::t);
        let books = self
            .acked
            .iter()
            .map(|(id, a)| {
                let book = RobotBook {
                    last_seq: a.max,
                    last_t: a.last_t,
                    records: a.records,
                    gaps: a.gaps(),
                    seq_conflicts: a.seq_conflicts,
                    queue_depth: self.merger.pending_of(id),
                    lag_s: match (a.last_t, applied_t) {
                        (Some(l), Some(t)) => (l - t).max(0.0),
                        _ => 0.0,
                    },
                    quarantined: a.quarantined,
                    quarantine_reason: a.quarantine_reason.clone(),
                };
                (id.clone(), book)
            })
            .collect();
        let mut step_ns = self.step_ns.clone();
        step_ns.sort_unstable();
        StateParts {
            run: self.id.clone(),
            status: self.status.clone(),
            applied: self.applied,
            applied_t,
            t_start: self.trajectories.first_t(),
            particle_sample: self.cfg.particle_sample,
            books,
            step_ms: step_ns
                .get(step_ns.len() / 2)
                .map_or(0.0, |n| *n as f64 / 1e6),
        }
    }
}

/// The coordinator's figures of a robot, laid over the filter's in a state.
#[derive(Debug, Clone)]
struct RobotBook {
    last_seq: Option<u64>,
    last_t: Option<f64>,
    records: u64,
    gaps: u64,
    seq_conflicts: u64,
    queue_depth: usize,
    lag_s: f64,
    quarantined: u64,
    quarantine_reason: Option<String>,
}

/// What a state holds besides what it reads from the filter.
#[derive(Debug, Clone)]
struct StateParts {
    run: String,
    status: String,
    applied: u64,
    applied_t: Option<f64>,
    t_start: Option<f64>,
    particle_sample: usize,
    books: HashMap<String, RobotBook>,
    step_ms: f64,
}

impl StateParts {
    /// The state of `filter` with these figures.
    fn build(&self, filter: &LateJoinSlam) -> RunState {
        let mut state = history::base_state(
            &self.run,
            &self.status,
            filter,
            self.applied,
            self.applied_t,
            self.particle_sample,
        );
        for r in &mut state.robots {
            if let Some(b) = self.books.get(&r.id) {
                r.last_seq = b.last_seq;
                r.last_t = b.last_t;
                r.records = b.records;
                r.gaps = b.gaps;
                r.seq_conflicts = b.seq_conflicts;
                r.queue_depth = b.queue_depth;
                r.lag_s = b.lag_s;
                r.quarantined = b.quarantined;
                r.quarantine_reason = b.quarantine_reason.clone();
            }
        }
        state.step_ms = self.step_ms;
        state.t_start = self.t_start;
        state
    }
}

/// A published state of a run. The coordinator publishes a copy of the filter (particles
/// share their maps: a few small vectors per particle) with its own figures; the state
/// (estimate, landmarks, particle sample) is built on the first read, on the reader's
/// thread, once for all readers of this publication. States that nobody reads are never
/// built, and building one never holds the filter back.
pub struct PublishedState {
    /// What the state is built from, until it is.
    parts: Mutex<Option<(StateParts, LateJoinSlam)>>,
    built: OnceLock<Arc<RunState>>,
}

impl PublishedState {
    /// A state built already.
    fn built(state: RunState) -> Self {
        Self {
            parts: Mutex::new(None),
            built: OnceLock::from(Arc::new(state)),
        }
    }

    /// A state to build from `filter` when first read.
    fn lazy(parts: StateParts, filter: LateJoinSlam) -> Self {
        Self {
            parts: Mutex::new(Some((parts, filter))),
            built: OnceLock::new(),
        }
    }

    /// The state (built now if nobody has read it yet).
    pub fn get(&self) -> Arc<RunState> {
        self.built
            .get_or_init(|| {
                let (parts, filter) = self
                    .parts
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .take()
                    .expect("an unbuilt state keeps its parts until it is built");
                Arc::new(parts.build(&filter))
            })
            .clone()
    }

    /// True once the state has been built (read, or published built).
    pub fn is_built(&self) -> bool {
        self.built.get().is_some()
    }
}

impl std::fmt::Debug for PublishedState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PublishedState")
            .field("built", &self.built.get())
            .finish_non_exhaustive()
    }
}

/// What a batch of steps did, handed back from the blocking thread.
#[derive(Default)]
struct Applied {
    /// Per applied record: the filter's report and the step time [ns].
    reports: Vec<(Option<StepReport>, u64)>,
    /// (robot, seq, reason) of the quarantined records.
    quarantined: Vec<(String, u64, String)>,
    /// Robots that joined the filter.
    joins: Vec<String>,
    /// Why the filter could not be rebuilt, when it could not: the run fails.
    fatal: Option<String>,
    /// The key of the last record stepped through or quarantined.
    last: Option<OrderKey>,
}

fn reject(seq: u64, code: &'static str, error: String) -> RecordAck {
    RecordAck {
        seq,
        status: "rejected",
        arrival: None,
        code: Some(code),
        error: Some(error),
    }
}

fn seq_conflict(robot: &str, seq: u64) -> RecordAck {
    reject(
        seq,
        "seq_conflict",
        format!(
            "seq {seq} of robot {robot:?} was stored before with other content; a robot that \
             restarts must go on from its last seq (see last_seq in the run's state), not \
             number its records from 0 again"
        ),
    )
}
