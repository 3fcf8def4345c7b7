//! Durable storage of fleetslam runs: every run, its robots, its append-only observation
//! log, filter snapshots, evaluation results, training records and learned models.
//!
//! # Backends
//!
//! [`Store::open`] takes a URL: `sqlite://...` for the embedded SQLite database (the default:
//! [`Store::open_default`] puts it at `DATA_DIR/fleetslam.db`, creating the directory and the
//! file on first start, no set-up) or `postgres://...` for a PostgreSQL server. The schema
//! lives in the workspace's top-level `migrations/sqlite/` and `migrations/postgres/` (the
//! two differ in BLOB/BYTEA and in how ids are generated), is embedded in the binary and is
//! applied on every open. Both backends pass the same test suite.
//!
//! [`Store`] is an enum over a native `SqlitePool` and a native `PgPool` rather than
//! sqlx's `AnyPool`: each backend keeps its own types (BLOB vs BYTEA, 64-bit integers and
//! doubles without the Any driver's conversions) and its own tuning (SQLite's WAL mode,
//! `synchronous=FULL`, `BEGIN IMMEDIATE`), and nothing is decided at run time from strings.
//! The price, one `match` per query, is paid once by an internal macro that expands each
//! query for both pools; the SQL text itself is shared, since both accept `$1` placeholders.
//!
//! # Durability and group commit
//!
//! A call that returns `Ok` has committed: SQLite runs in WAL mode with `synchronous=FULL`
//! (an fsync per commit) and PostgreSQL with its default `synchronous_commit`. So that this
//! does not cost throughput, appends to the observation log go through ONE writer task per
//! store, which gathers what concurrent callers have queued into one transaction, commits
//! once, and answers each caller (see [`Store::append`]). The writer also owns the per-run
//! arrival counters, so arrival numbers are 1, 2, 3, ... without gaps; for that reason one
//! database is written by one `Store` (one process) at a time.
//!
//! # Recovery
//!
//! On start, [`Store::active_runs`] lists the runs that were still active; for each,
//! [`Store::latest_snapshot`] gives the filter state and the watermark it was taken at, and
//! [`Store::records_after`] pages through the records that came after it, in arrival order.
//!
//! # Export and retention
//!
//! A run is exported by [`Store::get_run`], [`Store::robots`], [`Store::records_after`]
//! (paged), [`Store::evaluations`] and the snapshots; [`Store::delete_run`] removes a run and
//! everything it owns in one transaction.

#![warn(missing_docs)]

pub mod admin;
mod error;
mod pool;
mod types;
mod writer;

use std::collections::BTreeMap;
use std::path::Path;
use std::str::FromStr;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde_json::Value;
use sqlx::migrate::Migrator;
use sqlx::postgres::PgPoolOptions;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{FromRow, Row};
use tokio::sync::{mpsc, oneshot};

pub use error::StoreError;
pub use types::*;

use pool::{Pool, with_pool};
use writer::{AppendJob, Job, Stats};

/// The SQLite schema, embedded from `migrations/sqlite/`.
static SQLITE_MIGRATOR: Migrator = sqlx::migrate!("../../migrations/sqlite");
/// The PostgreSQL schema, embedded from `migrations/postgres/`.
static POSTGRES_MIGRATOR: Migrator = sqlx::migrate!("../../migrations/postgres");

/// The file name of the default SQLite database inside the data directory.
pub const DEFAULT_DB_FILE: &str = "fleetslam.db";
/// The largest page [`Store::records_after`] returns.
pub const MAX_RECORDS_PAGE: i64 = 100_000;

/// The handle to the store: cheap to clone (all clones share one pool and one writer).
///
/// Must be opened inside a tokio runtime, whose lifetime bounds the writer task's: once that
/// runtime shuts down, appends fail with [`StoreError::Closed`].
#[derive(Debug, Clone)]
pub struct Store {
    inner: Arc<Inner>,
}

#[derive(Debug)]
struct Inner {
    pool: Pool,
    jobs: mpsc::Sender<Job>,
    stats: Arc<Stats>,
}

/// A run as read from the database, JSON still as text.
#[derive(FromRow)]
struct RawRun {
    id: String,
    name: Option<String>,
    status: String,
    config: String,
    header: Option<String>,
    summary: Option<String>,
    created_at: i64,
    ended_at: Option<i64>,
    reason: Option<String>,
    robots: i64,
    records: i64,
}

impl RawRun {
    fn parse(self) -> Result<RunRow, StoreError> {
        Ok(RunRow {
            id: self.id,
            name: self.name,
            status: self.status,
            config: serde_json::from_str(&self.config)?,
            header: parse_opt(self.header.as_deref())?,
            summary: parse_opt(self.summary.as_deref())?,
            created_at: self.created_at,
            ended_at: self.ended_at,
            reason: self.reason,
            robots: self.robots,
            records: self.records,
        })
    }
}

#[derive(FromRow)]
struct RawRobot {
    run_id: String,
    robot_id: String,
    start: Option<String>,
    token_hash: String,
    t0: Option<f64>,
    added_at: i64,
}

#[derive(FromRow)]
struct RawSnapshot {
    run_id: String,
    applied: i64,
    t: f64,
    data: Vec<u8>,
    created_at: i64,
}

impl From<RawSnapshot> for SnapshotRow {
    fn from(r: RawSnapshot) -> Self {
        SnapshotRow {
            run_id: r.run_id,
            applied: r.applied,
            t: r.t,
            data: r.data,
            created_at: r.created_at,
        }
    }
}

#[derive(FromRow)]
struct RawObservation {
    arrival: i64,
    robot_id: String,
    seq: i64,
    t: f64,
    body: String,
    rejected: Option<String>,
}

impl From<RawObservation> for StoredObservation {
    fn from(r: RawObservation) -> Self {
        StoredObservation {
            arrival: r.arrival,
            robot_id: r.robot_id,
            seq: r.seq,
            t: r.t,
            body: r.body,
            rejected: r.rejected,
        }
    }
}

#[derive(FromRow)]
struct RawModel {
    id: String,
    kind: String,
    config: String,
    metrics: String,
    weights: Vec<u8>,
    created_at: i64,
}

#[derive(FromRow)]
struct RawModelInfo {
    id: String,
    kind: String,
    config: String,
    metrics: String,
    weights_len: i64,
    created_at: i64,
}

/// The columns of a [`RunRow`], counts included; `r` is `runs`.
const RUN_COLUMNS: &str = "r.id, r.name, r.status, r.config, r.header, r.summary, r.created_at, r.ended_at, r.reason, \
     (SELECT COUNT(*) FROM robots b WHERE b.run_id = r.id) AS robots, \
     (SELECT COALESCE(MAX(o.arrival), 0) FROM observations o WHERE o.run_id = r.id) AS records";

const SNAPSHOT_COLUMNS: &str = "run_id, applied, t, data, created_at";

fn parse_opt(text: Option<&str>) -> Result<Option<Value>, StoreError> {
    text.map(serde_json::from_str)
        .transpose()
        .map_err(StoreError::from)
}

fn to_text(value: &Value) -> Result<String, StoreError> {
    Ok(serde_json::to_string(value)?)
}

/// Now, in unix milliseconds.
fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

fn check_status(status: &str) -> Result<(), StoreError> {
    if STATUSES.contains(&status) {
        Ok(())
    } else {
        Err(StoreError::Invalid(format!(
            "unknown run status {status:?} (expected one of {STATUSES:?})"
        )))
    }
}

fn check_id(kind: &str, id: &str) -> Result<(), StoreError> {
    if id.is_empty() {
        Err(StoreError::Invalid(format!("empty {kind} id")))
    } else {
        Ok(())
    }
}

/// The `WHERE` clause of a run filter, its placeholders numbered from `$1`, and the number of
/// placeholders used.
fn run_where(f: &RunFilter) -> (String, usize) {
    let mut conds = Vec::new();
    if f.status.is_some() {
        conds.push(format!("r.status = ${}", conds.len() + 1));
    }
    if f.created_after.is_some() {
        conds.push(format!("r.created_at >= ${}", conds.len() + 1));
    }
    if f.created_before.is_some() {
        conds.push(format!("r.created_at < ${}", conds.len() + 1));
    }
    let n = conds.len();
    if conds.is_empty() {
        (String::new(), 0)
    } else {
        (format!(" WHERE {}", conds.join(" AND ")), n)
    }
}

/// Binds the values of [`run_where`]'s placeholders, in order.
macro_rules! bind_run_filter {
    ($q:expr, $f:expr) => {{
        let mut q = $q;
        if let Some(s) = &$f.status {
            q = q.bind(s.as_str());
        }
        if let Some(t) = $f.created_after {
            q = q.bind(t);
        }
        if let Some(t) = $f.created_before {
            q = q.bind(t);
        }
        q
    }};
}

impl Store {
    /// Opens (creating if needed) the store at `url` and applies the migrations.
    ///
    /// - `sqlite:///abs/path.db`, `sqlite://relative.db` or `sqlite:relative.db`: the
    ///   embedded database; missing directories and the file are created. WAL mode,
    ///   `synchronous=FULL`, foreign keys on.
    /// - `postgres://user@host:port/db` (or `postgresql://`): a PostgreSQL server (without
    ///   TLS: meant for a server on the same host or a private network).
    pub async fn open(url: &str) -> Result<Store, StoreError> {
        let pool = if url.starts_with("sqlite:") {
            Pool::Sqlite(open_sqlite(SqliteConnectOptions::from_str(url)?).await?)
        } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            let pool = PgPoolOptions::new()
                .max_connections(8)
                .acquire_timeout(Duration::from_secs(30))
                .connect(url)
                .await?;
            POSTGRES_MIGRATOR.run(&pool).await?;
            Pool::Postgres(pool)
        } else {
            return Err(StoreError::Invalid(format!(
                "unsupported database URL {:?}: expected sqlite:... or postgres://...",
                redact(url)
            )));
        };
        Ok(Store::start(pool))
    }

    /// Starts the writer task of a migrated pool.
    fn start(pool: Pool) -> Store {
        let stats = Arc::new(Stats::default());
        let jobs = writer::spawn(pool.clone(), stats.clone());
        Store {
            inner: Arc::new(Inner { pool, jobs, stats }),
        }
    }

    /// Opens the default embedded store, the SQLite file `data_dir/fleetslam.db`, creating
    /// the directory and the file if missing.
    pub async fn open_default(data_dir: &Path) -> Result<Store, StoreError> {
        std::fs::create_dir_all(data_dir)?;
        // Options rather than a URL, so that any file name works (`?`, `#`, spaces, ...).
        let options = SqliteConnectOptions::new().filename(data_dir.join(DEFAULT_DB_FILE));
        Ok(Store::start(Pool::Sqlite(open_sqlite(options).await?)))
    }

    /// `"sqlite"` or `"postgres"`.
    pub fn backend(&self) -> &'static str {
        self.inner.pool.backend()
    }

    /// The group-commit writer's counters so far.
    pub fn writer_stats(&self) -> WriterStats {
        self.inner.stats.snapshot()
    }

    /// Closes the connection pool: every later call fails. Everything acknowledged before is
    /// already durable; this only releases the connections (and SQLite's WAL) early.
    pub async fn close(&self) {
        with_pool!(&self.inner.pool, pool => pool.close().await)
    }

    // ---------------------------------------------------------------- runs

    /// Creates a run with status `"active"`, created now. A used id is a
    /// [`StoreError::Conflict`].
    pub async fn create_run(&self, r: &NewRun) -> Result<RunRow, StoreError> {
        check_id("run", &r.id)?;
        let config = to_text(&r.config)?;
        let header = r.header.as_ref().map(to_text).transpose()?;
        let created_at = now_ms();
        let sql = "INSERT INTO runs (id, name, status, config, header, created_at) \
                   VALUES ($1, $2, $3, $4, $5, $6)";
        with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(&r.id)
                .bind(r.name.as_deref())
                .bind(STATUS_ACTIVE)
                .bind(&config)
                .bind(header.as_deref())
                .bind(created_at)
                .execute(pool)
                .await
                .map_err(|e| StoreError::from_db(e, || format!("run {}", r.id)))?;
        });
        Ok(RunRow {
            id: r.id.clone(),
            name: r.name.clone(),
            status: STATUS_ACTIVE.to_owned(),
            config: r.config.clone(),
            header: r.header.clone(),
            summary: None,
            created_at,
            ended_at: None,
            reason: None,
            robots: 0,
            records: 0,
        })
    }

    /// The run `id`, with its counts, if it exists.
    pub async fn get_run(&self, id: &str) -> Result<Option<RunRow>, StoreError> {
        let sql = format!("SELECT {RUN_COLUMNS} FROM runs r WHERE r.id = $1");
        let raw = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawRun>(&sql).bind(id).fetch_optional(pool).await?
        });
        raw.map(RawRun::parse).transpose()
    }

    /// One page of the runs matching `f`, newest first, each with its counts.
    pub async fn list_runs(&self, f: &RunFilter) -> Result<Vec<RunRow>, StoreError> {
        if let Some(s) = &f.status {
            check_status(s)?;
        }
        if !(1..=RunFilter::MAX_LIMIT).contains(&f.limit) || f.offset < 0 {
            return Err(StoreError::Invalid(format!(
                "page limit {} must be in 1..={} and offset {} not negative",
                f.limit,
                RunFilter::MAX_LIMIT,
                f.offset
            )));
        }
        let (cond, n) = run_where(f);
        let sql = format!(
            "SELECT {RUN_COLUMNS} FROM runs r{cond} ORDER BY r.created_at DESC, r.id DESC LIMIT ${} OFFSET ${}",
            n + 1,
            n + 2
        );
        let raws = with_pool!(&self.inner.pool, pool => {
            bind_run_filter!(sqlx::query_as::<_, RawRun>(&sql), f)
                .bind(f.limit)
                .bind(f.offset)
                .fetch_all(pool)
                .await?
        });
        raws.into_iter().map(RawRun::parse).collect()
    }

    /// How many runs match `f` in all (its `limit` and `offset` are ignored), for paging.
    pub async fn count_runs(&self, f: &RunFilter) -> Result<i64, StoreError> {
        if let Some(s) = &f.status {
            check_status(s)?;
        }
        let (cond, _) = run_where(f);
        let sql = format!("SELECT COUNT(*) AS n FROM runs r{cond}");
        let n = with_pool!(&self.inner.pool, pool => {
            bind_run_filter!(sqlx::query(&sql), f)
                .fetch_one(pool)
                .await?
                .try_get::<i64, _>("n")?
        });
        Ok(n)
    }

    /// Sets a run's status (`"active"`, `"ended"` or `"failed"`) and, when given, its
    /// summary (otherwise the summary is kept). Ending or failing sets `ended_at` (the first
    /// time only); going back to active clears it.
    pub async fn set_run_status(
        &self,
        id: &str,
        status: &str,
        summary: Option<&Value>,
    ) -> Result<(), StoreError> {
        check_status(status)?;
        let summary = summary.map(to_text).transpose()?;
        let sql = if status == STATUS_ACTIVE {
            "UPDATE runs SET status = $2, summary = COALESCE($3, summary), ended_at = NULL WHERE id = $1"
        } else {
            "UPDATE runs SET status = $2, summary = COALESCE($3, summary), \
             ended_at = COALESCE(ended_at, $4) WHERE id = $1"
        };
        let now = now_ms();
        let updated = with_pool!(&self.inner.pool, pool => {
            let mut q = sqlx::query(sql).bind(id).bind(status).bind(summary.as_deref());
            if status != STATUS_ACTIVE {
                q = q.bind(now);
            }
            q.execute(pool).await?.rows_affected()
        });
        if updated == 0 {
            return Err(StoreError::NotFound(format!("run {id}")));
        }
        Ok(())
    }

    /// Marks a run `"failed"` with the reason (its coordinator or its recovery failed):
    /// it is no longer recovered on start, and its reason is shown with it.
    pub async fn set_run_failed(&self, id: &str, reason: &str) -> Result<(), StoreError> {
        let sql = "UPDATE runs SET status = $2, reason = $3, ended_at = COALESCE(ended_at, $4) \
                   WHERE id = $1";
        let updated = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(id)
                .bind(STATUS_FAILED)
                .bind(reason)
                .bind(now_ms())
                .execute(pool)
                .await?
                .rows_affected()
        });
        if updated == 0 {
            return Err(StoreError::NotFound(format!("run {id}")));
        }
        Ok(())
    }

    /// Every run still `"active"`, oldest first: the runs to recover on start.
    pub async fn active_runs(&self) -> Result<Vec<RunRow>, StoreError> {
        let sql = format!(
            "SELECT {RUN_COLUMNS} FROM runs r WHERE r.status = $1 ORDER BY r.created_at, r.id"
        );
        let raws = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawRun>(&sql).bind(STATUS_ACTIVE).fetch_all(pool).await?
        });
        raws.into_iter().map(RawRun::parse).collect()
    }

    /// The ids of every run still `"active"`, oldest first, without their counts (what a
    /// cluster replica polls for runs without an owner).
    pub async fn active_run_ids(&self) -> Result<Vec<String>, StoreError> {
        let sql = "SELECT id FROM runs WHERE status = $1 ORDER BY created_at, id";
        let ids = with_pool!(&self.inner.pool, pool => {
            sqlx::query_scalar::<_, String>(sql).bind(STATUS_ACTIVE).fetch_all(pool).await?
        });
        Ok(ids)
    }

    /// A run's status (`active`, `ended`, `failed`), or None when there is no such run.
    pub async fn run_status(&self, id: &str) -> Result<Option<String>, StoreError> {
        let sql = "SELECT status FROM runs WHERE id = $1";
        let status = with_pool!(&self.inner.pool, pool => {
            sqlx::query_scalar::<_, String>(sql).bind(id).fetch_optional(pool).await?
        });
        Ok(status)
    }

    /// Deletes a run and everything it owns (robots, records, snapshots, evaluations,
    /// training rows) in one transaction; false when there was no such run. Ordered after
    /// every append queued before it.
    pub async fn delete_run(&self, id: &str) -> Result<bool, StoreError> {
        let (reply, answer) = oneshot::channel();
        self.inner
            .jobs
            .send(Job::DeleteRun {
                run_id: id.to_owned(),
                reply,
            })
            .await
            .map_err(|_| StoreError::Closed)?;
        answer.await.map_err(|_| StoreError::Closed)?
    }

    // ---------------------------------------------------------------- robots

    /// Adds a robot to a run: [`StoreError::Conflict`] when the run already has it,
    /// [`StoreError::NotFound`] when there is no such run.
    pub async fn add_robot(&self, run_id: &str, r: &NewRobot) -> Result<(), StoreError> {
        check_id("robot", &r.robot_id)?;
        if r.t0.is_some_and(|t| !t.is_finite()) {
            return Err(StoreError::Invalid(format!(
                "robot {} has a non-finite t0",
                r.robot_id
            )));
        }
        let start = r.start.as_ref().map(to_text).transpose()?;
        let sql = "INSERT INTO robots (run_id, robot_id, start, token_hash, t0, added_at) \
                   VALUES ($1, $2, $3, $4, $5, $6)";
        with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .bind(&r.robot_id)
                .bind(start.as_deref())
                .bind(&r.token_hash)
                .bind(r.t0)
                .bind(now_ms())
                .execute(pool)
                .await
                .map_err(|e| StoreError::from_db(e, || format!("robot {} in run {run_id}", r.robot_id)))?;
        });
        Ok(())
    }

    /// The robots of a run, in the order they joined.
    pub async fn robots(&self, run_id: &str) -> Result<Vec<RobotRow>, StoreError> {
        let sql = "SELECT run_id, robot_id, start, token_hash, t0, added_at FROM robots \
                   WHERE run_id = $1 ORDER BY added_at, robot_id";
        let raws = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawRobot>(sql).bind(run_id).fetch_all(pool).await?
        });
        raws.into_iter()
            .map(|r| {
                Ok(RobotRow {
                    run_id: r.run_id,
                    robot_id: r.robot_id,
                    start: parse_opt(r.start.as_deref())?,
                    token_hash: r.token_hash,
                    t0: r.t0,
                    added_at: r.added_at,
                })
            })
            .collect()
    }

    // ---------------------------------------------------------------- observation log

    /// Appends records to a run's log, durably: when this returns `Ok`, every record is
    /// committed.
    ///
    /// Idempotent per `(run, robot, seq)`: a record already stored is not inserted again
    /// and comes back with `duplicate: true` and its stored arrival number, so a retried
    /// request can be acknowledged again. Each new record gets the run's next arrival number
    /// (1, 2, 3, ...), in input order. The answer has one item per record, in input order.
    ///
    /// Concurrent calls are committed together by the store's writer task (group commit).
    /// Errors: [`StoreError::NotFound`] (no such run), [`StoreError::Invalid`] (empty robot
    /// id, negative seq, non-finite time; nothing of the call is written),
    /// [`StoreError::Closed`]. The store does not check that the robot was added to the run.
    /// A call dropped while waiting may still have been committed.
    pub async fn append(
        &self,
        run_id: &str,
        recs: Vec<NewObservation>,
    ) -> Result<AppendOutcome, StoreError> {
        writer::validate(&recs)?;
        if recs.is_empty() {
            return Ok(AppendOutcome::default());
        }
        let (reply, answer) = oneshot::channel();
        self.inner
            .jobs
            .send(Job::Append(AppendJob {
                run_id: run_id.to_owned(),
                recs,
                reply,
            }))
            .await
            .map_err(|_| StoreError::Closed)?;
        answer.await.map_err(|_| StoreError::Closed)?
    }

    /// Up to `limit` (1..=[`MAX_RECORDS_PAGE`]) records with an arrival number greater than
    /// `after_arrival`, in arrival order. Page on with the last arrival returned.
    pub async fn records_after(
        &self,
        run_id: &str,
        after_arrival: i64,
        limit: i64,
    ) -> Result<Vec<StoredObservation>, StoreError> {
        if !(1..=MAX_RECORDS_PAGE).contains(&limit) {
            return Err(StoreError::Invalid(format!(
                "page limit {limit} must be in 1..={MAX_RECORDS_PAGE}"
            )));
        }
        let sql = "SELECT arrival, robot_id, seq, t, body, rejected FROM observations \
                   WHERE run_id = $1 AND arrival > $2 ORDER BY arrival LIMIT $3";
        let raws = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawObservation>(sql)
                .bind(run_id)
                .bind(after_arrival)
                .bind(limit)
                .fetch_all(pool)
                .await?
        });
        Ok(raws.into_iter().map(StoredObservation::from).collect())
    }

    /// Up to `limit` (1..=[`MAX_RECORDS_PAGE`]) records with a time in `from_t..=until_t`
    /// and an arrival number greater than `after_arrival`, in arrival order (page on with
    /// the last arrival returned). Served by the index on `(run_id, t)`: reading the records
    /// after a snapshot costs those records, not the whole log.
    pub async fn records_in_time(
        &self,
        run_id: &str,
        from_t: f64,
        until_t: f64,
        after_arrival: i64,
        limit: i64,
    ) -> Result<Vec<StoredObservation>, StoreError> {
        if !(1..=MAX_RECORDS_PAGE).contains(&limit) {
            return Err(StoreError::Invalid(format!(
                "page limit {limit} must be in 1..={MAX_RECORDS_PAGE}"
            )));
        }
        if from_t.is_nan() || until_t.is_nan() {
            return Err(StoreError::Invalid("a time bound is NaN".into()));
        }
        // The store keeps finite times only; clamping keeps infinite bounds portable.
        let (from_t, until_t) = (from_t.max(f64::MIN), until_t.min(f64::MAX));
        let sql = "SELECT arrival, robot_id, seq, t, body, rejected FROM observations \
                   WHERE run_id = $1 AND t >= $2 AND t <= $3 AND arrival > $4 \
                   ORDER BY arrival LIMIT $5";
        let raws = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawObservation>(sql)
                .bind(run_id)
                .bind(from_t)
                .bind(until_t)
                .bind(after_arrival)
                .bind(limit)
                .fetch_all(pool)
                .await?
        });
        Ok(raws.into_iter().map(StoredObservation::from).collect())
    }

    /// Quarantines the stored record `(run, robot, seq)`: it stays in the log (its seq stays
    /// taken) but is marked rejected with `reason`, and recovery, scrubbing, re-runs and
    /// exports skip it. Marking it again keeps the first reason. False when no such record.
    pub async fn quarantine(
        &self,
        run_id: &str,
        robot_id: &str,
        seq: i64,
        reason: &str,
    ) -> Result<bool, StoreError> {
        let reason = if reason.is_empty() {
            "rejected"
        } else {
            reason
        };
        let sql = "UPDATE observations SET rejected = COALESCE(rejected, $4) \
                   WHERE run_id = $1 AND robot_id = $2 AND seq = $3";
        let n = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .bind(robot_id)
                .bind(seq)
                .bind(reason)
                .execute(pool)
                .await?
                .rows_affected()
        });
        Ok(n > 0)
    }

    /// The stored body of record `seq` of `robot` in a run, and the reason it was
    /// quarantined if it was, when there is such a record: what a repeated seq is compared
    /// with.
    pub async fn record_body(
        &self,
        run_id: &str,
        robot_id: &str,
        seq: i64,
    ) -> Result<Option<(String, Option<String>)>, StoreError> {
        let sql = "SELECT body, rejected FROM observations WHERE run_id = $1 AND robot_id = $2 AND seq = $3";
        let found = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .bind(robot_id)
                .bind(seq)
                .fetch_optional(pool)
                .await?
                .map(|row| Ok::<_, sqlx::Error>((
                    row.try_get::<String, _>("body")?,
                    row.try_get::<Option<String>, _>("rejected")?,
                )))
                .transpose()?
        });
        Ok(found)
    }

    /// The highest stored seq of each robot of a run that has records.
    pub async fn last_seqs(&self, run_id: &str) -> Result<BTreeMap<String, i64>, StoreError> {
        let sql = "SELECT robot_id, MAX(seq) AS seq FROM observations WHERE run_id = $1 GROUP BY robot_id";
        let rows = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .fetch_all(pool)
                .await?
                .into_iter()
                .map(|row| Ok((row.try_get::<String, _>("robot_id")?, row.try_get::<i64, _>("seq")?)))
                .collect::<Result<BTreeMap<_, _>, sqlx::Error>>()?
        });
        Ok(rows)
    }

    /// How many records a run holds (0 for an unknown run). Arrival numbers are contiguous,
    /// so this is also the highest arrival number.
    pub async fn record_count(&self, run_id: &str) -> Result<i64, StoreError> {
        let sql = "SELECT COALESCE(MAX(arrival), 0) AS n FROM observations WHERE run_id = $1";
        let n = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql).bind(run_id).fetch_one(pool).await?.try_get::<i64, _>("n")?
        });
        Ok(n)
    }

    // ---------------------------------------------------------------- snapshots

    /// Stores a filter snapshot, replacing one of the run with the same `applied`.
    pub async fn put_snapshot(&self, run_id: &str, s: &NewSnapshot) -> Result<(), StoreError> {
        if !s.t.is_finite() {
            return Err(StoreError::Invalid("snapshot time is not finite".into()));
        }
        let sql = "INSERT INTO snapshots (run_id, applied, t, data, created_at) VALUES ($1, $2, $3, $4, $5) \
                   ON CONFLICT (run_id, applied) DO UPDATE SET t = excluded.t, data = excluded.data, \
                   created_at = excluded.created_at";
        with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .bind(s.applied)
                .bind(s.t)
                .bind(s.data.as_slice())
                .bind(now_ms())
                .execute(pool)
                .await
                .map_err(|e| StoreError::from_db(e, || format!("snapshot {} of run {run_id}", s.applied)))?;
        });
        Ok(())
    }

    /// The run's snapshot with the highest `applied`.
    pub async fn latest_snapshot(&self, run_id: &str) -> Result<Option<SnapshotRow>, StoreError> {
        let sql = format!(
            "SELECT {SNAPSHOT_COLUMNS} FROM snapshots WHERE run_id = $1 ORDER BY applied DESC LIMIT 1"
        );
        let raw = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawSnapshot>(&sql).bind(run_id).fetch_optional(pool).await?
        });
        Ok(raw.map(SnapshotRow::from))
    }

    /// The run's latest snapshot (highest `t`, then highest `applied`) taken at or before
    /// filter time `t`.
    pub async fn snapshot_at_or_before(
        &self,
        run_id: &str,
        t: f64,
    ) -> Result<Option<SnapshotRow>, StoreError> {
        let sql = format!(
            "SELECT {SNAPSHOT_COLUMNS} FROM snapshots WHERE run_id = $1 AND t <= $2 \
             ORDER BY t DESC, applied DESC LIMIT 1"
        );
        let raw = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawSnapshot>(&sql).bind(run_id).bind(t).fetch_optional(pool).await?
        });
        Ok(raw.map(SnapshotRow::from))
    }

    /// Every snapshot of a run as `(applied, t)`, in `applied` order, without their data: the
    /// points a replay of the run can start from.
    pub async fn snapshot_index(&self, run_id: &str) -> Result<Vec<(i64, f64)>, StoreError> {
        let sql = "SELECT applied, t FROM snapshots WHERE run_id = $1 ORDER BY applied";
        let rows = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .fetch_all(pool)
                .await?
                .into_iter()
                .map(|row| Ok((row.try_get::<i64, _>("applied")?, row.try_get::<f64, _>("t")?)))
                .collect::<Result<Vec<_>, sqlx::Error>>()?
        });
        Ok(rows)
    }

    /// The run's snapshot with the highest `applied` not above `applied`.
    pub async fn snapshot_at_or_before_applied(
        &self,
        run_id: &str,
        applied: i64,
    ) -> Result<Option<SnapshotRow>, StoreError> {
        let sql = format!(
            "SELECT {SNAPSHOT_COLUMNS} FROM snapshots WHERE run_id = $1 AND applied <= $2 \
             ORDER BY applied DESC LIMIT 1"
        );
        let raw = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawSnapshot>(&sql).bind(run_id).bind(applied).fetch_optional(pool).await?
        });
        Ok(raw.map(SnapshotRow::from))
    }

    /// Stores pieces of a run's trajectories in one transaction, each replacing a piece of
    /// the same robot starting at the same index.
    pub async fn put_trajectory_chunks(
        &self,
        run_id: &str,
        chunks: &[TrajectoryChunk],
    ) -> Result<(), StoreError> {
        if chunks.is_empty() {
            return Ok(());
        }
        if let Some(c) = chunks.iter().find(|c| c.first < 0 || c.robot_id.is_empty()) {
            return Err(StoreError::Invalid(format!(
                "trajectory piece of robot {:?} at {}: empty robot id or negative index",
                c.robot_id, c.first
            )));
        }
        let sql = "INSERT INTO trajectory_chunks (run_id, robot_id, first_index, points) VALUES ($1, $2, $3, $4) \
                   ON CONFLICT (run_id, robot_id, first_index) DO UPDATE SET points = excluded.points";
        with_pool!(&self.inner.pool, pool => {
            let mut tx = pool.begin().await?;
            for c in chunks {
                sqlx::query(sql)
                    .bind(run_id)
                    .bind(&c.robot_id)
                    .bind(c.first)
                    .bind(&c.points)
                    .execute(&mut *tx)
                    .await
                    .map_err(|e| StoreError::from_db(e, || format!("trajectory pieces of run {run_id}")))?;
            }
            tx.commit().await?;
        });
        Ok(())
    }

    /// The stored pieces of one track of a run (a robot's trajectory, or a series its
    /// caller stores beside them under a name no robot id takes), by first index.
    pub async fn track_chunks(
        &self,
        run_id: &str,
        track: &str,
    ) -> Result<Vec<TrajectoryChunk>, StoreError> {
        self.chunks(
            "SELECT robot_id, first_index, points FROM trajectory_chunks \
             WHERE run_id = $1 AND robot_id = $2 ORDER BY first_index",
            run_id,
            Some(track),
        )
        .await
    }

    /// Every stored piece of a run's trajectories, by robot, then by first index.
    pub async fn trajectory_chunks(
        &self,
        run_id: &str,
    ) -> Result<Vec<TrajectoryChunk>, StoreError> {
        self.chunks(
            "SELECT robot_id, first_index, points FROM trajectory_chunks WHERE run_id = $1 \
             ORDER BY robot_id, first_index",
            run_id,
            None,
        )
        .await
    }

    /// The pieces `sql` selects for the run (`$1`) and, when given, the track (`$2`).
    async fn chunks(
        &self,
        sql: &str,
        run_id: &str,
        track: Option<&str>,
    ) -> Result<Vec<TrajectoryChunk>, StoreError> {
        let rows = with_pool!(&self.inner.pool, pool => {
            let mut q = sqlx::query(sql).bind(run_id);
            if let Some(t) = track {
                q = q.bind(t);
            }
            q.fetch_all(pool)
                .await?
                .into_iter()
                .map(|row| {
                    Ok(TrajectoryChunk {
                        robot_id: row.try_get("robot_id")?,
                        first: row.try_get("first_index")?,
                        points: row.try_get("points")?,
                    })
                })
                .collect::<Result<Vec<_>, sqlx::Error>>()?
        });
        Ok(rows)
    }

    // ---------------------------------------------------------------- artifacts

    /// Stores a named JSON document of a run (its final result, its ground truth, ...),
    /// replacing one of the same name.
    pub async fn put_artifact(
        &self,
        run_id: &str,
        name: &str,
        body: &str,
    ) -> Result<(), StoreError> {
        check_id("artifact name", name)?;
        let sql = "INSERT INTO run_artifacts (run_id, name, body, created_at) VALUES ($1, $2, $3, $4) \
                   ON CONFLICT (run_id, name) DO UPDATE SET body = excluded.body, \
                   created_at = excluded.created_at";
        with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .bind(name)
                .bind(body)
                .bind(now_ms())
                .execute(pool)
                .await
                .map_err(|e| StoreError::from_db(e, || format!("artifact {name} of run {run_id}")))?;
        });
        Ok(())
    }

    /// A named JSON document of a run, as stored.
    pub async fn get_artifact(
        &self,
        run_id: &str,
        name: &str,
    ) -> Result<Option<String>, StoreError> {
        let sql = "SELECT body FROM run_artifacts WHERE run_id = $1 AND name = $2";
        let body = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .bind(name)
                .fetch_optional(pool)
                .await?
                .map(|row| row.try_get::<String, _>("body"))
                .transpose()?
        });
        Ok(body)
    }

    // ---------------------------------------------------------------- evaluations

    /// Stores an evaluation result of a run.
    pub async fn put_evaluation(&self, run_id: &str, eval: &Value) -> Result<(), StoreError> {
        let body = to_text(eval)?;
        let sql = "INSERT INTO evaluations (run_id, body, created_at) VALUES ($1, $2, $3)";
        with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .bind(&body)
                .bind(now_ms())
                .execute(pool)
                .await
                .map_err(|e| StoreError::from_db(e, || format!("evaluation of run {run_id}")))?;
        });
        Ok(())
    }

    /// A run's evaluation results, oldest first.
    pub async fn evaluations(&self, run_id: &str) -> Result<Vec<Value>, StoreError> {
        let sql = "SELECT body FROM evaluations WHERE run_id = $1 ORDER BY id";
        let bodies = with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(run_id)
                .fetch_all(pool)
                .await?
                .into_iter()
                .map(|row| row.try_get::<String, _>("body"))
                .collect::<Result<Vec<_>, _>>()?
        });
        bodies
            .iter()
            .map(|b| serde_json::from_str(b).map_err(StoreError::from))
            .collect()
    }

    // ---------------------------------------------------------------- training data, models

    /// Appends training rows (the JSON text of one landmark update's input and output each,
    /// stored as given) to a run, in one transaction.
    pub async fn append_training(&self, run_id: &str, rows: &[String]) -> Result<(), StoreError> {
        if rows.is_empty() {
            return Ok(());
        }
        let sql = "INSERT INTO training_rows (run_id, body) VALUES ($1, $2)";
        with_pool!(&self.inner.pool, pool => {
            let mut tx = pool.begin().await?;
            for row in rows {
                sqlx::query(sql)
                    .bind(run_id)
                    .bind(row)
                    .execute(&mut *tx)
                    .await
                    .map_err(|e| StoreError::from_db(e, || format!("training rows of run {run_id}")))?;
            }
            tx.commit().await?;
        });
        Ok(())
    }

    /// Up to `limit` training rows of the given runs (of every run when `run_ids` is empty),
    /// in the order they were stored.
    pub async fn training_rows(
        &self,
        run_ids: &[String],
        limit: i64,
    ) -> Result<Vec<String>, StoreError> {
        if limit < 1 {
            return Err(StoreError::Invalid(format!(
                "limit {limit} must be positive"
            )));
        }
        let cond = if run_ids.is_empty() {
            String::new()
        } else {
            let marks: Vec<String> = (1..=run_ids.len()).map(|i| format!("${i}")).collect();
            format!(" WHERE run_id IN ({})", marks.join(", "))
        };
        let sql = format!(
            "SELECT body FROM training_rows{cond} ORDER BY id LIMIT ${}",
            run_ids.len() + 1
        );
        let rows = with_pool!(&self.inner.pool, pool => {
            let mut q = sqlx::query(&sql);
            for id in run_ids {
                q = q.bind(id.as_str());
            }
            q.bind(limit)
                .fetch_all(pool)
                .await?
                .into_iter()
                .map(|row| row.try_get::<String, _>("body"))
                .collect::<Result<Vec<_>, _>>()?
        });
        Ok(rows)
    }

    /// Stores a learned model, replacing one with the same id.
    pub async fn put_model(&self, m: &NewModel) -> Result<(), StoreError> {
        check_id("model", &m.id)?;
        let config = to_text(&m.config)?;
        let metrics = to_text(&m.metrics)?;
        let sql = "INSERT INTO models (id, kind, config, metrics, weights, created_at) \
                   VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT (id) DO UPDATE SET kind = excluded.kind, \
                   config = excluded.config, metrics = excluded.metrics, weights = excluded.weights, \
                   created_at = excluded.created_at";
        with_pool!(&self.inner.pool, pool => {
            sqlx::query(sql)
                .bind(&m.id)
                .bind(&m.kind)
                .bind(&config)
                .bind(&metrics)
                .bind(m.weights.as_slice())
                .bind(now_ms())
                .execute(pool)
                .await?;
        });
        Ok(())
    }

    /// The model `id` with its weights, if stored.
    pub async fn get_model(&self, id: &str) -> Result<Option<ModelRow>, StoreError> {
        let sql = "SELECT id, kind, config, metrics, weights, created_at FROM models WHERE id = $1";
        let raw = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawModel>(sql).bind(id).fetch_optional(pool).await?
        });
        raw.map(|r| {
            Ok(ModelRow {
                id: r.id,
                kind: r.kind,
                config: serde_json::from_str(&r.config)?,
                metrics: serde_json::from_str(&r.metrics)?,
                weights: r.weights,
                created_at: r.created_at,
            })
        })
        .transpose()
    }

    /// Every stored model without its weights, newest first.
    pub async fn list_models(&self) -> Result<Vec<ModelInfo>, StoreError> {
        let sql = "SELECT id, kind, config, metrics, CAST(LENGTH(weights) AS BIGINT) AS weights_len, created_at \
                   FROM models ORDER BY created_at DESC, id";
        let raws = with_pool!(&self.inner.pool, pool => {
            sqlx::query_as::<_, RawModelInfo>(sql).fetch_all(pool).await?
        });
        raws.into_iter()
            .map(|r| {
                Ok(ModelInfo {
                    id: r.id,
                    kind: r.kind,
                    config: serde_json::from_str(&r.config)?,
                    metrics: serde_json::from_str(&r.metrics)?,
                    weights_len: r.weights_len,
                    created_at: r.created_at,
                })
            })
            .collect()
    }
}

/// Opens and migrates the SQLite pool, creating the database's directory and file if
/// missing, in WAL mode with `synchronous=FULL` and foreign keys on.
async fn open_sqlite(options: SqliteConnectOptions) -> Result<sqlx::SqlitePool, StoreError> {
    let options = options
        .create_if_missing(true)
        .journal_mode(SqliteJournalMode::Wal)
        .synchronous(SqliteSynchronous::Full)
        .foreign_keys(true)
        .busy_timeout(Duration::from_secs(30));
    let file = options.get_filename();
    if let Some(dir) = file.parent()
        && !dir.as_os_str().is_empty()
        && file.as_os_str() != ":memory:"
    {
        std::fs::create_dir_all(dir)?;
    }
    let pool = SqlitePoolOptions::new()
        .max_connections(4)
        .acquire_timeout(Duration::from_secs(30))
        .connect_with(options)
        .await?;
    SQLITE_MIGRATOR.run(&pool).await?;
    Ok(pool)
}

/// The URL without its password, for messages.
fn redact(url: &str) -> String {
    match (url.find("://"), url.find('@')) {
        (Some(scheme), Some(at)) if at > scheme => {
            let userinfo = &url[scheme + 3..at];
            match userinfo.find(':') {
                Some(colon) => format!("{}:***{}", &url[..scheme + 3 + colon], &url[at..]),
                None => url.to_owned(),
            }
        }
        _ => url.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn redacts_passwords() {
        assert_eq!(redact("postgres://u:secret@h/db"), "postgres://u:***@h/db");
        assert_eq!(redact("postgres://u@h/db"), "postgres://u@h/db");
        assert_eq!(redact("mysql://h/db"), "mysql://h/db");
    }

    #[test]
    fn filter_placeholders_are_numbered_in_bind_order() {
        let f = RunFilter {
            status: Some("ended".into()),
            created_before: Some(5),
            ..RunFilter::default()
        };
        let (cond, n) = run_where(&f);
        assert_eq!(cond, " WHERE r.status = $1 AND r.created_at < $2");
        assert_eq!(n, 2);
        assert_eq!(run_where(&RunFilter::default()), (String::new(), 0));
    }
}
