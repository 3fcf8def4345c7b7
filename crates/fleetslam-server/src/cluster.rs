//! Cluster mode (issue 14): several server replicas share the runs through NATS JetStream
//! and PostgreSQL, with no protocol of our own.
//!
//! - **Records go through JetStream.** Any replica checks a robot's POST (token, models,
//!   limits) and publishes each record to the run's subject (`fleetslam.run.<run>`) of one
//!   replicated stream, with a message id made of (run, robot, seq, content hash): JetStream's
//!   deduplication is the first line of idempotency. The robot is acknowledged only after
//!   JetStream's publish acknowledgement, so acknowledged means stored in a replicated stream.
//!   Registrations and the end of a run go through the same subject, so the run's owner sees
//!   them in the same order as the records.
//! - **One owner per run, by lease.** A lease is a key in a JetStream key-value bucket whose
//!   entries expire after `lease_ttl`: a replica takes a run with a create (which fails when
//!   the key exists) and renews it with an update that names the revision it holds. A replica
//!   that stops renewing (killed, cut off) loses the key when it expires, and another takes
//!   the run. New and orphaned runs go to the least loaded replica (each replica announces its
//!   load in a second bucket), ties broken by rendezvous hashing.
//! - **The owner** recovers the run from PostgreSQL exactly as a restarted single server does
//!   (latest snapshot, then every archived record after it), then reads the run's subject
//!   with an ordered consumer from the position stored beside the run, feeding the
//!   coordinator as if the records came over HTTP: the coordinator archives them in
//!   PostgreSQL (its repeat check makes a message delivered twice a duplicate, applied once),
//!   merges and steps them, and writes snapshots and the result. The position is written
//!   after the records it covers are archived, so a new owner re-reads at most a batch.
//! - **The merge's clock is the stream's**: a robot counts as silent by the time JetStream
//!   stored the messages ([`Clock::Stream`]), and an owner that sees nothing for the reorder
//!   window publishes a tick into the subject, so silence is decided by the stream's
//!   content, the same for every owner that replays it.
//! - **Any replica serves any run**: history, state and exports from PostgreSQL; the live
//!   websocket from the owner's states and events, which it publishes on
//!   `fleetslam.state.<run>` and `fleetslam.event.<run>` (plain NATS).

use crate::app::{AppState, LiveRun};
use crate::coordinator::{Clock, RecordAck};
use crate::error::ApiError;
use async_nats::jetstream::{self, consumer, kv, message::PublishMessage, stream};
use bytes::Bytes;
use fleetslam_core::log::Record;
use fleetslam_core::pose::PoseGaussian;
use futures::{FutureExt, StreamExt};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::Mutex;

/// Settings of a replica in cluster mode.
#[derive(Debug, Clone)]
pub struct ClusterConfig {
    /// NATS servers to connect to (any of the cluster's nodes; the client moves between them).
    pub nats_urls: Vec<String>,
    /// This replica's name, unique in the cluster (default: a random one per start).
    pub replica_id: String,
    /// The JetStream stream that carries every run's records. Default `FLEETSLAM`.
    pub stream: String,
    /// Replicas of the stream and of the lease buckets (R3 on a 3-node NATS cluster; 1 on a
    /// single node). Default 3.
    pub stream_replicas: usize,
    /// How long a lease lasts unless renewed; the owner renews it every third of it. A
    /// killed owner's runs move after at most this long (plus `claim_every`). Default 3 s.
    pub lease_ttl: Duration,
    /// How often a replica looks for runs without an owner. Default 250 ms.
    pub claim_every: Duration,
    /// How long a POST waits for JetStream's publish acknowledgements before answering 503
    /// (the robot retries; repeats are deduplicated). Default 10 s.
    pub ack_timeout: Duration,
    /// How long `POST /v1/runs/{run}/end` waits for the owner to end the run. Default 600 s.
    pub end_timeout: Duration,
    /// Most stream messages an owner hands to its coordinator in one ingest. Default 512.
    pub batch: usize,
    /// How long JetStream remembers message ids for deduplication. Default 10 min.
    pub duplicate_window: Duration,
    /// An owner that has read nothing of its run for this long publishes a tick (it moves
    /// the merge's clock); one whose tick has not come back after as long again reads the
    /// subject anew from its position (its consumer was lost with a NATS node). Default 1 s.
    pub idle_tick: Duration,
}

impl Default for ClusterConfig {
    fn default() -> Self {
        Self {
            nats_urls: vec!["nats://127.0.0.1:4222".into()],
            replica_id: format!(
                "replica-{}",
                &uuid::Uuid::new_v4().simple().to_string()[..8]
            ),
            stream: "FLEETSLAM".into(),
            stream_replicas: 3,
            lease_ttl: Duration::from_secs(3),
            claim_every: Duration::from_millis(250),
            ack_timeout: Duration::from_secs(10),
            end_timeout: Duration::from_secs(600),
            batch: 512,
            duplicate_window: Duration::from_secs(600),
            idle_tick: Duration::from_secs(1),
        }
    }
}

const LEASES: &str = "fleetslam_leases";
const MEMBERS: &str = "fleetslam_replicas";
const KIND: &str = "Fleetslam-Kind";
/// The run artifact holding the owner's position in the run's subject.
const POSITION: &str = "stream_position";

/// A registration as published to the run's subject.
#[derive(Debug, Serialize, Deserialize)]
struct Registration {
    robot: String,
    start: Option<PoseGaussian>,
    t0: Option<f64>,
    token_hash: String,
}

/// Where an owner is in a run's subject: the last message whose effects are archived.
#[derive(Debug, Default, Clone, Copy, Serialize, Deserialize)]
struct Position {
    seq: u64,
    /// When JetStream stored it [ns since the Unix epoch]: the merge's clock.
    published_ns: i128,
}

/// Counters of a replica (`GET /metrics`: `fleetslam_cluster{counter="..."}`).
#[derive(Debug, Default)]
pub struct ClusterStats {
    pub published: AtomicU64,
    pub duplicates: AtomicU64,
    pub takeovers: AtomicU64,
    /// Records a run's owner refused after JetStream had acknowledged them (too old, time
    /// going back, a seq stored with other content): logged with the reason.
    pub refused_after_ack: AtomicU64,
}

/// A replica's link to the cluster.
#[derive(Debug)]
pub struct Cluster {
    pub cfg: ClusterConfig,
    client: async_nats::Client,
    js: jetstream::Context,
    leases: kv::Store,
    members: kv::Store,
    /// The runs this replica owns, and the task that drives each.
    owned: Mutex<HashMap<String, tokio::task::AbortHandle>>,
    /// Runs seen without an owner, and since when (for the fallback claim).
    orphans: Mutex<HashMap<String, Instant>>,
    /// The stream clock's origin: stream time `ns` is `origin + ns`.
    origin: Instant,
    /// What this replica knows of the runs it checks requests for.
    pub(crate) runs: tokio::sync::RwLock<HashMap<String, Arc<crate::app::ClusterRun>>>,
    pub stats: ClusterStats,
}

fn nats_err(what: &str, e: impl std::fmt::Display) -> ApiError {
    ApiError::Busy {
        message: format!(
            "{what}: the record log (NATS JetStream) did not answer ({e}); nothing is acknowledged, retry"
        ),
        retry_after_s: 1,
    }
}

impl Cluster {
    /// Connects to NATS and makes sure the stream and the buckets exist.
    pub async fn connect(cfg: ClusterConfig) -> anyhow::Result<Arc<Cluster>> {
        use anyhow::Context as _;
        let client = async_nats::ConnectOptions::new()
            .name(format!("fleetslam {}", cfg.replica_id))
            .retry_on_initial_connect()
            .connection_timeout(Duration::from_secs(5))
            .connect(cfg.nats_urls.clone())
            .await
            .with_context(|| format!("connecting to NATS at {}", cfg.nats_urls.join(",")))?;
        let js = jetstream::new(client.clone());
        let replicas = cfg.stream_replicas.max(1);
        // Creating what exists is a no-op; replicas starting together may race, so retry.
        let mut tries = 0;
        let (leases, members) = loop {
            let made = async {
                js.get_or_create_stream(stream::Config {
                    name: cfg.stream.clone(),
                    subjects: vec!["fleetslam.run.*".into()],
                    num_replicas: replicas,
                    duplicate_window: cfg.duplicate_window,
                    storage: stream::StorageType::File,
                    ..Default::default()
                })
                .await
                .context("creating the record stream")?;
                // A key-value bucket is a stream of this form. It is created as a stream
                // because the client's bucket creation first reads the account's limits in
                // a form that NATS servers before 2.10 do not answer.
                let bucket = |bucket: &str| stream::Config {
                    name: format!("KV_{bucket}"),
                    subjects: vec![format!("$KV.{bucket}.>")],
                    max_messages_per_subject: 1,
                    max_age: cfg.lease_ttl,
                    storage: stream::StorageType::File,
                    allow_rollup: true,
                    deny_delete: true,
                    allow_direct: true,
                    num_replicas: replicas,
                    discard: stream::DiscardPolicy::New,
                    ..Default::default()
                };
                for name in [LEASES, MEMBERS] {
                    js.get_or_create_stream(bucket(name))
                        .await
                        .with_context(|| format!("creating the bucket {name}"))?;
                }
                let leases = js.get_key_value(LEASES).await.context("the lease bucket")?;
                let members = js
                    .get_key_value(MEMBERS)
                    .await
                    .context("the replica bucket")?;
                anyhow::Ok((leases, members))
            }
            .await;
            match made {
                Ok(v) => break v,
                Err(e) if tries < 20 => {
                    tries += 1;
                    tracing::warn!(error = %format!("{e:#}"), "setting up JetStream; retrying");
                    tokio::time::sleep(Duration::from_millis(500)).await;
                }
                Err(e) => return Err(e),
            }
        };
        Ok(Arc::new(Cluster {
            cfg,
            client,
            js,
            leases,
            members,
            owned: Mutex::default(),
            orphans: Mutex::default(),
            origin: Instant::now(),
            runs: Default::default(),
            stats: ClusterStats::default(),
        }))
    }

    fn subject(run: &str) -> String {
        format!("fleetslam.run.{run}")
    }

    /// The stream clock's instant of a message stored at `ns` (Unix epoch nanoseconds).
    fn instant(&self, ns: i128) -> Instant {
        self.origin + Duration::from_nanos(ns.clamp(0, u64::MAX as i128) as u64)
    }

    /// Publishes one message and waits for JetStream's acknowledgement.
    async fn publish(
        &self,
        run: &str,
        kind: &str,
        id: Option<String>,
        payload: Bytes,
    ) -> Result<jetstream::publish::PublishAck, ApiError> {
        let mut msg = PublishMessage::build().payload(payload).header(KIND, kind);
        if let Some(id) = id {
            msg = msg.message_id(id);
        }
        let ack = tokio::time::timeout(self.cfg.ack_timeout, async {
            self.js
                .send_publish(Self::subject(run), msg)
                .await
                .map_err(|e| nats_err("publishing", e))?
                .await
                .map_err(|e| nats_err("publishing", e))
        })
        .await
        .map_err(|_| nats_err("publishing", "timed out"))??;
        Ok(ack)
    }

    /// Publishes a robot's records (checked by the caller) and answers with one
    /// acknowledgement each, once JetStream has acknowledged every one.
    pub async fn publish_records(
        &self,
        run: &str,
        records: &[Record],
    ) -> Result<Vec<RecordAck>, ApiError> {
        let mut acks = Vec::with_capacity(records.len());
        let mut pending = Vec::with_capacity(records.len());
        for r in records {
            // The coordinator compares repeats by this canonical form.
            let body = serde_json::to_string(r).map_err(ApiError::internal)?;
            let id = message_id(run, r, &body);
            let msg = PublishMessage::build()
                .payload(Bytes::from(body))
                .header(KIND, "record")
                .message_id(id);
            let ack = tokio::time::timeout(
                self.cfg.ack_timeout,
                self.js.send_publish(Self::subject(run), msg),
            )
            .await
            .map_err(|_| nats_err("publishing", "timed out"))?
            .map_err(|e| nats_err("publishing", e))?;
            pending.push((r.seq, ack));
        }
        for (seq, ack) in pending {
            let ack = tokio::time::timeout(self.cfg.ack_timeout, ack)
                .await
                .map_err(|_| nats_err("publishing", "timed out"))?
                .map_err(|e| nats_err("publishing", e))?;
            if ack.duplicate {
                self.stats.duplicates.fetch_add(1, Ordering::Relaxed);
            } else {
                self.stats.published.fetch_add(1, Ordering::Relaxed);
            }
            acks.push(RecordAck {
                seq,
                status: if ack.duplicate { "duplicate" } else { "stored" },
                arrival: None,
                code: None,
                error: None,
            });
        }
        Ok(acks)
    }

    /// Publishes a registration (the robot's row is already stored).
    pub async fn publish_registration(
        &self,
        run: &str,
        robot: &str,
        start: Option<PoseGaussian>,
        t0: Option<f64>,
        token_hash: &str,
    ) -> Result<(), ApiError> {
        let body = serde_json::to_vec(&Registration {
            robot: robot.into(),
            start,
            t0,
            token_hash: token_hash.into(),
        })
        .map_err(ApiError::internal)?;
        let id = format!("{run}:robot:{}", hex::encode(Sha256::digest(robot)));
        self.publish(run, "robot", Some(id), body.into()).await?;
        Ok(())
    }

    /// Publishes the end of a run, then waits until its owner has ended it.
    pub async fn end_run(&self, state: &AppState, run: &str) -> Result<(), ApiError> {
        self.publish(run, "end", Some(format!("{run}:end")), Bytes::new())
            .await?;
        let deadline = Instant::now() + self.cfg.end_timeout;
        loop {
            let status = state
                .store
                .run_status(run)
                .await?
                .ok_or_else(|| ApiError::NotFound(format!("no run {run}")))?;
            match status.as_str() {
                "ended" => return Ok(()),
                "active" if Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(50)).await
                }
                "active" => {
                    return Err(ApiError::Busy {
                        message: format!(
                            "run {run}: its end is in the record log, but its owner has not \
                             ended it within {} s; it will, and GET /v1/runs/{run} shows when",
                            self.cfg.end_timeout.as_secs()
                        ),
                        retry_after_s: 5,
                    });
                }
                _ => {
                    let row = state
                        .store
                        .get_run(run)
                        .await?
                        .ok_or_else(|| ApiError::NotFound(format!("no run {run}")))?;
                    return Err(crate::api_history::not_running(&row));
                }
            }
        }
    }

    /// Runs the replica's side of the cluster until the process stops: announces its load,
    /// takes runs without an owner, and drives them.
    pub fn spawn(self: &Arc<Self>, state: AppState) -> tokio::task::JoinHandle<()> {
        let me = self.clone();
        tokio::spawn(async move {
            let mut last_beat: Option<Instant> = None;
            loop {
                if last_beat.is_none_or(|t| t.elapsed() >= me.cfg.lease_ttl / 3) {
                    me.heartbeat().await;
                    last_beat = Some(Instant::now());
                }
                if let Err(e) = me.claim(&state).await {
                    tracing::warn!(error = %e, "looking for runs without an owner");
                }
                tokio::time::sleep(me.cfg.claim_every).await;
            }
        })
    }

    async fn heartbeat(&self) {
        let load = self.owned.lock().await.len();
        let body = serde_json::json!({ "runs": load }).to_string();
        if let Err(e) = self.members.put(&self.cfg.replica_id, body.into()).await {
            tracing::warn!(error = %e, "announcing this replica");
        }
    }

    /// The live replicas and how many runs each owns.
    async fn loads(&self) -> HashMap<String, usize> {
        let mut out = HashMap::new();
        let Ok(keys) = self.members.keys().await else {
            return out;
        };
        let keys: Vec<String> = keys.filter_map(|k| async { k.ok() }).collect().await;
        for k in keys {
            if let Ok(Some(v)) = self.members.get(&k).await {
                let runs = serde_json::from_slice::<serde_json::Value>(&v)
                    .ok()
                    .and_then(|v| v["runs"].as_u64())
                    .unwrap_or(0) as usize;
                out.insert(k, runs);
            }
        }
        out
    }

    /// Whether this replica should take `run` now: it is the least loaded live replica
    /// (ties: rendezvous hashing of run and replica), or the run has waited for an owner
    /// longer than a lease.
    fn chosen(&self, run: &str, loads: &HashMap<String, usize>, mine: usize) -> bool {
        let score = |id: &str| {
            let h = Sha256::digest(format!("{run}/{id}"));
            u64::from_be_bytes(h[..8].try_into().expect("8 bytes"))
        };
        let me = (mine, std::cmp::Reverse(score(&self.cfg.replica_id)));
        loads
            .iter()
            .filter(|(id, _)| **id != self.cfg.replica_id)
            .all(|(id, load)| me < (*load, std::cmp::Reverse(score(id))))
    }

    async fn claim(self: &Arc<Self>, state: &AppState) -> Result<(), ApiError> {
        let active = state.store.active_run_ids().await?;
        let owned: Vec<String> = self.owned.lock().await.keys().cloned().collect();
        let mut loads = None;
        for id in active {
            if owned.contains(&id) {
                continue;
            }
            match self.leases.entry(&id).await {
                Ok(Some(e)) if e.operation == kv::Operation::Put => {
                    self.orphans.lock().await.remove(&id);
                    continue;
                }
                Ok(_) => {}
                Err(e) => {
                    tracing::warn!(run = %id, error = %e, "reading a lease");
                    continue;
                }
            }
            let waited = {
                let mut orphans = self.orphans.lock().await;
                orphans
                    .entry(id.clone())
                    .or_insert_with(Instant::now)
                    .elapsed()
            };
            if loads.is_none() {
                loads = Some(self.loads().await);
            }
            let mine = self.owned.lock().await.len();
            if waited < self.cfg.lease_ttl
                && !self.chosen(&id, loads.as_ref().expect("set above"), mine)
            {
                continue;
            }
            match self
                .leases
                .create(&id, self.cfg.replica_id.clone().into())
                .await
            {
                Ok(revision) => {
                    self.orphans.lock().await.remove(&id);
                    self.stats.takeovers.fetch_add(1, Ordering::Relaxed);
                    tracing::info!(run = %id, replica = %self.cfg.replica_id, "took the run");
                    let me = self.clone();
                    let (st, run) = (state.clone(), id.clone());
                    let mut owned = self.owned.lock().await;
                    let task = tokio::spawn(async move { me.own(st, run, revision).await });
                    owned.insert(id.clone(), task.abort_handle());
                    drop(owned);
                    self.heartbeat().await;
                    if let Some(l) = loads.as_mut() {
                        l.insert(self.cfg.replica_id.clone(), mine + 1);
                    }
                }
                Err(e) if e.kind() == kv::CreateErrorKind::AlreadyExists => {}
                Err(e) => tracing::warn!(run = %id, error = %e, "taking a lease"),
            }
        }
        Ok(())
    }

    /// Owns a run while the lease holds: recovers it, drives it from the stream, renews the
    /// lease; lets it go when the run ends or the lease is lost.
    async fn own(self: Arc<Self>, state: AppState, run: String, revision: u64) {
        let outcome = tokio::select! {
            r = self.drive(&state, &run) => r.map(|()| "ended"),
            lost = self.renew(&run, revision) => Err(lost),
        };
        // Whatever happened, this replica no longer runs the run: dropping its live entry
        // stops the coordinator (its stored state is what the next owner starts from).
        state.runs.write().await.remove(&run);
        self.owned.lock().await.remove(&run);
        match outcome {
            Ok(why) => {
                tracing::info!(run = %run, why, "run released");
                let _ = self.leases.delete(&run).await;
            }
            Err(e) => tracing::warn!(run = %run, error = %e, "gave the run up"),
        }
        self.heartbeat().await;
    }

    /// Renews the lease every third of its life; returns when it is lost.
    async fn renew(&self, run: &str, mut revision: u64) -> String {
        let mut renewed = Instant::now();
        loop {
            tokio::time::sleep(self.cfg.lease_ttl / 3).await;
            match self
                .leases
                .update(run, self.cfg.replica_id.clone().into(), revision)
                .await
            {
                Ok(r) => {
                    revision = r;
                    renewed = Instant::now();
                }
                Err(e) if renewed.elapsed() < self.cfg.lease_ttl => {
                    tracing::warn!(run, error = %e, "renewing the lease; retrying");
                }
                Err(e) => return format!("the lease could not be renewed: {e}"),
            }
        }
    }

    /// Recovers the run from the store and applies its subject from the stored position
    /// on; returns when the run has ended.
    async fn drive(&self, state: &AppState, run: &str) -> Result<(), String> {
        let store = &state.store;
        let row = store
            .get_run(run)
            .await
            .map_err(|e| e.to_string())?
            .ok_or("the run is gone")?;
        if row.status != "active" {
            return Ok(());
        }
        let mut pos: Position = store
            .get_artifact(run, POSITION)
            .await
            .map_err(|e| e.to_string())?
            .and_then(|b| serde_json::from_str(&b).ok())
            .unwrap_or_default();
        let clock = Clock::stream(self.instant(pos.published_ns));
        let started = Instant::now();
        crate::recovery::recover_run(state, &row, clock.clone())
            .await
            .map_err(|e| format!("recovering: {e}"))?;
        let live = state.running(run).await.ok_or("the run stopped at once")?;
        tracing::info!(
            run,
            from = pos.seq,
            ms = started.elapsed().as_millis() as u64,
            "run recovered; reading its subject"
        );
        let relay = tokio::spawn(relay(
            self.client.clone(),
            run.to_string(),
            live.handle.state.clone(),
            live.handle.events.subscribe(),
            state.config.coordinator.state_rate_hz,
        ));
        let _relay = AbortOnDrop(relay);
        let mut messages = self.read_from(run, pos.seq + 1).await?;
        // The sequence of the latest tick this owner published, until it has read it.
        let mut tick_out: Option<u64> = None;
        loop {
            let first = match tokio::time::timeout(self.cfg.idle_tick, messages.next()).await {
                Err(_) => {
                    if tick_out.is_some_and(|t| t > pos.seq) {
                        // Its own tick did not come back: the consumer was lost (with a
                        // NATS node); read again from the position.
                        tracing::warn!(
                            run,
                            from = pos.seq + 1,
                            "the run's subject stalled; reading it again"
                        );
                        match self.read_from(run, pos.seq + 1).await {
                            Ok(m) => messages = m,
                            Err(e) => {
                                tracing::warn!(run, error = %e, "reading the run's subject again")
                            }
                        }
                        tick_out = None;
                        continue;
                    }
                    // Nothing for a while: a tick moves the merge's clock through the
                    // stream, so that a replay decides silence alike.
                    match self.publish(run, "tick", None, Bytes::new()).await {
                        Ok(ack) => tick_out = Some(ack.sequence),
                        Err(e) => tracing::warn!(run, error = %e, "publishing a tick"),
                    }
                    continue;
                }
                Ok(None) => {
                    tracing::warn!(run, "the run's subscription ended; reading it again");
                    messages = self.read_from(run, pos.seq + 1).await?;
                    continue;
                }
                Ok(Some(Err(e))) => {
                    tracing::warn!(run, error = %e, "reading the run's subject");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
                Ok(Some(Ok(m))) => m,
            };
            let mut batch = vec![first];
            while batch.len() < self.cfg.batch {
                match messages.next().now_or_never() {
                    Some(Some(Ok(m))) => batch.push(m),
                    _ => break,
                }
            }
            let mut records: Vec<Record> = Vec::new();
            // When the last of `records` was stored: the clock their ingest runs at.
            let mut records_ns = pos.published_ns;
            let mut ended = false;
            for m in batch {
                let info = m.info().map_err(|e| e.to_string())?;
                let at = Position {
                    seq: info.stream_sequence,
                    published_ns: info.published.unix_timestamp_nanos(),
                };
                let kind = m
                    .headers
                    .as_ref()
                    .and_then(|h| h.get(KIND))
                    .map(|v| v.as_str().to_string())
                    .unwrap_or_default();
                if kind == "record" {
                    match serde_json::from_slice::<Record>(&m.payload) {
                        Ok(r) => {
                            records.push(r);
                            records_ns = at.published_ns;
                        }
                        Err(e) => {
                            tracing::error!(run, seq = at.seq, error = %e, "an unreadable record in the stream")
                        }
                    }
                    pos = at;
                    continue;
                }
                self.ingest(run, &live, &clock, &mut records, records_ns)
                    .await?;
                clock.advance(self.instant(at.published_ns));
                match kind.as_str() {
                    "robot" => {
                        let reg: Registration = serde_json::from_slice(&m.payload)
                            .map_err(|e| format!("an unreadable registration: {e}"))?;
                        let row = fleetslam_store::NewRobot {
                            robot_id: reg.robot.clone(),
                            start: reg
                                .start
                                .as_ref()
                                .map(serde_json::to_value)
                                .transpose()
                                .map_err(|e| e.to_string())?,
                            token_hash: reg.token_hash.clone(),
                            t0: reg.t0,
                        };
                        match live.handle.add_stored_robot(row, reg.start, reg.t0).await {
                            Ok(()) => {}
                            // Delivered again after a takeover: the recovery added it.
                            Err(ApiError::Conflict(m)) if m.contains("already registered") => {}
                            Err(e) => return Err(format!("adding robot {}: {e}", reg.robot)),
                        }
                    }
                    "end" => {
                        ended = true;
                        pos = at;
                        break;
                    }
                    // A tick: the clock moved; an empty ingest lets the merge see it.
                    _ => {
                        live.handle
                            .ingest(Vec::new())
                            .await
                            .map_err(|e| e.to_string())?;
                    }
                }
                pos = at;
            }
            self.ingest(run, &live, &clock, &mut records, records_ns)
                .await?;
            if ended {
                crate::app::finish_run(state, run, &live)
                    .await
                    .map_err(|e| format!("ending: {e}"))?;
            }
            store
                .put_artifact(
                    run,
                    POSITION,
                    &serde_json::to_string(&pos).map_err(|e| e.to_string())?,
                )
                .await
                .map_err(|e| format!("storing the position: {e}"))?;
            if ended {
                return Ok(());
            }
        }
    }

    /// An ordered consumer of the run's subject from stream sequence `from` on.
    async fn read_from(&self, run: &str, from: u64) -> Result<consumer::pull::Ordered, String> {
        let stream = self
            .js
            .get_stream(&self.cfg.stream)
            .await
            .map_err(|e| e.to_string())?;
        let consumer = stream
            .create_consumer(consumer::pull::OrderedConfig {
                filter_subject: Self::subject(run),
                deliver_policy: consumer::DeliverPolicy::ByStartSequence {
                    start_sequence: from,
                },
                ..Default::default()
            })
            .await
            .map_err(|e| e.to_string())?;
        consumer.messages().await.map_err(|e| e.to_string())
    }

    /// Hands records to the coordinator (it archives them; repeats are duplicates).
    async fn ingest(
        &self,
        run: &str,
        live: &LiveRun,
        clock: &Clock,
        records: &mut Vec<Record>,
        published_ns: i128,
    ) -> Result<(), String> {
        if records.is_empty() {
            return Ok(());
        }
        clock.advance(self.instant(published_ns));
        let batch = std::mem::take(records);
        let acks = loop {
            match live.handle.ingest(batch.clone()).await {
                Ok(a) => break a,
                Err(ApiError::Busy { .. }) => tokio::time::sleep(Duration::from_millis(20)).await,
                Err(e) => return Err(format!("applying records: {e}")),
            }
        };
        for a in acks.iter().filter(|a| a.status == "rejected") {
            self.stats.refused_after_ack.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(
                run,
                seq = a.seq,
                code = a.code.unwrap_or(""),
                error = a.error.as_deref().unwrap_or(""),
                "a record acknowledged by the stream was refused by the run"
            );
        }
        Ok(())
    }

    /// A websocket on a replica that does not own the run: the owner's states and events,
    /// relayed.
    pub async fn subscribe_live(
        &self,
        run: &str,
    ) -> Result<(async_nats::Subscriber, async_nats::Subscriber), ApiError> {
        let states = self
            .client
            .subscribe(format!("fleetslam.state.{run}"))
            .await
            .map_err(|e| nats_err("subscribing", e))?;
        let events = self
            .client
            .subscribe(format!("fleetslam.event.{run}"))
            .await
            .map_err(|e| nats_err("subscribing", e))?;
        Ok((states, events))
    }

    /// Lets every run go (on a graceful stop, after the snapshots): the other replicas take
    /// them at once instead of after the leases expire.
    pub async fn release_all(&self) {
        let owned: Vec<(String, tokio::task::AbortHandle)> =
            self.owned.lock().await.drain().collect();
        for (run, task) in owned {
            task.abort();
            let _ = self.leases.delete(&run).await;
        }
        let _ = self.members.delete(&self.cfg.replica_id).await;
    }

    /// Runs this replica owns now.
    pub async fn owned_runs(&self) -> usize {
        self.owned.lock().await.len()
    }
}

/// Aborts a task when dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// The id JetStream deduplicates a record by: run, robot, seq and a hash of its content (a
/// different record under the same seq is not a repeat, and reaches the owner's conflict
/// check).
pub fn message_id(run: &str, r: &Record, body: &str) -> String {
    let mut h = Sha256::new();
    h.update(r.robot.as_bytes());
    h.update([0]);
    h.update(body.as_bytes());
    format!("{run}:{}:{}", r.seq, hex::encode(&h.finalize()[..16]))
}

/// The owner's side of the live view: states (at most `rate` a second) and events, as the
/// websocket's own messages, on plain NATS subjects.
async fn relay(
    client: async_nats::Client,
    run: String,
    mut state: tokio::sync::watch::Receiver<Arc<crate::coordinator::PublishedState>>,
    mut events: tokio::sync::broadcast::Receiver<crate::coordinator::Event>,
    rate: f64,
) {
    let period = Duration::from_secs_f64(1.0 / rate.max(0.1));
    let (state_subject, event_subject) = (
        format!("fleetslam.state.{run}"),
        format!("fleetslam.event.{run}"),
    );
    let mut tick = tokio::time::interval(period);
    let mut dirty = true;
    loop {
        tokio::select! {
            changed = state.changed() => {
                if changed.is_err() { return; }
                dirty = true;
            }
            _ = tick.tick(), if dirty => {
                dirty = false;
                let s = state.borrow_and_update().clone();
                let text = serde_json::json!({ "type": "state", "state": &*s.get() }).to_string();
                let _ = client.publish(state_subject.clone(), text.into()).await;
            }
            ev = events.recv() => match ev {
                Ok(e) => {
                    let text = serde_json::json!({ "type": "event", "event": e }).to_string();
                    let _ = client.publish(event_subject.clone(), text.into()).await;
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
            },
        }
    }
}
