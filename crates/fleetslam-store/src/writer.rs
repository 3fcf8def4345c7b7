//! The group-commit writer: ONE task per [`Store`](crate::Store) owns every write to the
//! observation log (and run deletion, so that its arrival counters never go stale).
//!
//! Callers send a [`Job`] through a bounded channel and wait on a oneshot. The writer takes
//! the first waiting job, drains whatever else is already queued (up to
//! [`MAX_BATCH_RECORDS`] records or [`MAX_BATCH_JOBS`] calls), writes all of it in ONE
//! transaction, commits once and answers every caller. While a commit is flushing, new
//! requests queue up and form the next group, so the cost of a durable commit (an fsync) is
//! shared by everyone who arrived during the previous one, without any added delay.
//!
//! Arrival numbers are assigned here from per-run counters, initialised from
//! `MAX(arrival)` on a run's first use. Only this task inserts observations, so the counters
//! stay exact; they are committed with the transaction and dropped if it fails. If a group
//! fails, each of its calls is retried alone so that one bad call cannot fail the others.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use sqlx::Row;
use tokio::sync::{mpsc, oneshot};

use crate::pool::{Pool, with_pool};
use crate::{AppendOutcome, Appended, NewObservation, StoreError, WriterStats};

/// The most records written in one group transaction.
pub(crate) const MAX_BATCH_RECORDS: usize = 4096;
/// The most calls answered by one group transaction.
pub(crate) const MAX_BATCH_JOBS: usize = 512;
/// How many calls may wait in the writer's queue before senders wait in turn.
pub(crate) const QUEUE_CAPACITY: usize = 4096;

/// A request to the writer.
#[derive(Debug)]
pub(crate) enum Job {
    /// Append records to a run's log.
    Append(AppendJob),
    /// Delete a run and everything it owns.
    DeleteRun {
        run_id: String,
        reply: oneshot::Sender<Result<bool, StoreError>>,
    },
}

/// One caller's append.
#[derive(Debug)]
pub(crate) struct AppendJob {
    pub(crate) run_id: String,
    pub(crate) recs: Vec<NewObservation>,
    pub(crate) reply: oneshot::Sender<Result<AppendOutcome, StoreError>>,
}

/// The writer's counters, shared with the store handles.
#[derive(Debug, Default)]
pub(crate) struct Stats {
    commits: AtomicU64,
    appends: AtomicU64,
    records: AtomicU64,
}

impl Stats {
    pub(crate) fn snapshot(&self) -> WriterStats {
        WriterStats {
            commits: self.commits.load(Ordering::Relaxed),
            appends: self.appends.load(Ordering::Relaxed),
            records: self.records.load(Ordering::Relaxed),
        }
    }
}

/// Starts the writer task for `pool`; it ends when every sender is dropped.
pub(crate) fn spawn(pool: Pool, stats: Arc<Stats>) -> mpsc::Sender<Job> {
    let (tx, rx) = mpsc::channel(QUEUE_CAPACITY);
    tokio::spawn(
        Writer {
            pool,
            stats,
            next: HashMap::new(),
        }
        .run(rx),
    );
    tx
}

/// Checks one call's records before anything is written.
pub(crate) fn validate(recs: &[NewObservation]) -> Result<(), StoreError> {
    for r in recs {
        if r.robot_id.is_empty() {
            return Err(StoreError::Invalid("a record has an empty robot id".into()));
        }
        if r.seq < 0 {
            return Err(StoreError::Invalid(format!(
                "robot {} record has a negative seq {}",
                r.robot_id, r.seq
            )));
        }
        if !r.t.is_finite() {
            return Err(StoreError::Invalid(format!(
                "robot {} record {} has a non-finite time",
                r.robot_id, r.seq
            )));
        }
    }
    Ok(())
}

struct Writer {
    pool: Pool,
    stats: Arc<Stats>,
    /// The next arrival number of each run seen so far.
    next: HashMap<String, i64>,
}

impl Writer {
    async fn run(mut self, mut rx: mpsc::Receiver<Job>) {
        let mut carried: Option<Job> = None;
        loop {
            let job = match carried.take() {
                Some(job) => job,
                None => match rx.recv().await {
                    Some(job) => job,
                    None => return,
                },
            };
            match job {
                Job::DeleteRun { run_id, reply } => {
                    let result = self.delete_run(&run_id).await;
                    // A caller that stopped waiting still had its run deleted.
                    let _ = reply.send(result);
                }
                Job::Append(first) => {
                    let mut records = first.recs.len();
                    let mut group = vec![first];
                    while records < MAX_BATCH_RECORDS && group.len() < MAX_BATCH_JOBS {
                        match rx.try_recv() {
                            Ok(Job::Append(job)) => {
                                records += job.recs.len();
                                group.push(job);
                            }
                            Ok(other) => {
                                carried = Some(other);
                                break;
                            }
                            Err(_) => break,
                        }
                    }
                    self.commit_group(group).await;
                }
            }
        }
    }

    /// Deletes a run's rows, children first, in one transaction.
    async fn delete_run(&mut self, run_id: &str) -> Result<bool, StoreError> {
        self.next.remove(run_id);
        let deleted = with_pool!(&self.pool, pool => {
            let mut tx = pool.begin().await?;
            for table in [
                "run_artifacts",
                "training_rows",
                "evaluations",
                "snapshots",
                "trajectory_chunks",
                "observations",
                "robots",
            ] {
                sqlx::query(&format!("DELETE FROM {table} WHERE run_id = $1"))
                    .bind(run_id)
                    .execute(&mut *tx)
                    .await?;
            }
            let runs = sqlx::query("DELETE FROM runs WHERE id = $1")
                .bind(run_id)
                .execute(&mut *tx)
                .await?;
            tx.commit().await?;
            runs.rows_affected() > 0
        });
        Ok(deleted)
    }

    /// Makes sure the counter of `run_id` is loaded; `NotFound` when the run does not exist.
    async fn load_counter(&mut self, run_id: &str) -> Result<(), StoreError> {
        if self.next.contains_key(run_id) {
            return Ok(());
        }
        let row = with_pool!(&self.pool, pool => {
            sqlx::query(
                "SELECT (SELECT COALESCE(MAX(arrival), 0) FROM observations WHERE run_id = $1) AS last \
                 FROM runs WHERE id = $1",
            )
            .bind(run_id)
            .fetch_optional(pool)
            .await?
            .map(|row| row.try_get::<i64, _>("last"))
            .transpose()?
        });
        match row {
            Some(last) => {
                self.next.insert(run_id.to_owned(), last + 1);
                Ok(())
            }
            None => Err(StoreError::NotFound(format!("run {run_id}"))),
        }
    }

    async fn commit_group(&mut self, group: Vec<AppendJob>) {
        // Answer the calls that cannot succeed before opening the transaction.
        let mut ready = Vec::with_capacity(group.len());
        for job in group {
            let check = match validate(&job.recs) {
                Ok(()) => self.load_counter(&job.run_id).await,
                Err(e) => Err(e),
            };
            match check {
                Ok(()) => ready.push(job),
                Err(e) => {
                    let _ = job.reply.send(Err(e));
                }
            }
        }
        if ready.is_empty() {
            return;
        }
        match self.write(&ready).await {
            Ok(outcomes) => {
                for (job, outcome) in ready.into_iter().zip(outcomes) {
                    self.answer(job, outcome);
                }
            }
            Err(e) if ready.len() == 1 => {
                if let Some(job) = ready.pop() {
                    let _ = job.reply.send(Err(e));
                }
            }
            Err(_) => {
                // Something in the group failed: retry each call alone, so the error goes to
                // the call that caused it and the others still succeed.
                for job in ready {
                    let result = match self.load_counter(&job.run_id).await {
                        Ok(()) => self.write(std::slice::from_ref(&job)).await,
                        Err(e) => Err(e),
                    };
                    match result {
                        Ok(mut outcomes) => {
                            let outcome = outcomes.pop().unwrap_or_default();
                            self.answer(job, outcome);
                        }
                        Err(e) => {
                            let _ = job.reply.send(Err(e));
                        }
                    }
                }
            }
        }
    }

    fn answer(&self, job: AppendJob, outcome: AppendOutcome) {
        self.stats.appends.fetch_add(1, Ordering::Relaxed);
        self.stats
            .records
            .fetch_add(outcome.inserted() as u64, Ordering::Relaxed);
        // The records are committed whether or not the caller is still waiting.
        let _ = job.reply.send(Ok(outcome));
    }

    /// Writes `jobs` in one transaction; on success the counters advance, on failure they are
    /// forgotten (reloaded from the database on next use) and nothing was written.
    async fn write(&mut self, jobs: &[AppendJob]) -> Result<Vec<AppendOutcome>, StoreError> {
        let mut next: HashMap<&str, i64> = HashMap::new();
        for job in jobs {
            let n = self
                .next
                .get(job.run_id.as_str())
                .copied()
                .ok_or_else(|| StoreError::NotFound(format!("run {}", job.run_id)))?;
            next.insert(job.run_id.as_str(), n);
        }
        let result = write_group(&self.pool, jobs, &mut next).await;
        match result {
            Ok(outcomes) => {
                self.stats.commits.fetch_add(1, Ordering::Relaxed);
                for (run, n) in next {
                    self.next.insert(run.to_owned(), n);
                }
                Ok(outcomes)
            }
            Err(e) => {
                for job in jobs {
                    self.next.remove(&job.run_id);
                }
                Err(e)
            }
        }
    }
}

const INSERT_OBSERVATION: &str = "INSERT INTO observations (run_id, arrival, robot_id, seq, t, body) \
     VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT (run_id, robot_id, seq) DO NOTHING";
const FIND_OBSERVATION: &str =
    "SELECT arrival FROM observations WHERE run_id = $1 AND robot_id = $2 AND seq = $3";

/// The group transaction itself.
async fn write_group<'a>(
    pool: &Pool,
    jobs: &'a [AppendJob],
    next: &mut HashMap<&'a str, i64>,
) -> Result<Vec<AppendOutcome>, StoreError> {
    let outcomes = with_pool!(pool, pool => {
        let mut tx = pool.begin_with(pool_begin(pool)).await?;
        let mut outcomes = Vec::with_capacity(jobs.len());
        for job in jobs {
            let mut items = Vec::with_capacity(job.recs.len());
            for rec in &job.recs {
                let arrival = next.get(job.run_id.as_str()).copied().unwrap_or(1);
                let inserted = sqlx::query(INSERT_OBSERVATION)
                    .bind(&job.run_id)
                    .bind(arrival)
                    .bind(&rec.robot_id)
                    .bind(rec.seq)
                    .bind(rec.t)
                    .bind(&rec.body)
                    .execute(&mut *tx)
                    .await?
                    .rows_affected()
                    == 1;
                let arrival = if inserted {
                    next.insert(job.run_id.as_str(), arrival + 1);
                    arrival
                } else {
                    sqlx::query(FIND_OBSERVATION)
                        .bind(&job.run_id)
                        .bind(&rec.robot_id)
                        .bind(rec.seq)
                        .fetch_one(&mut *tx)
                        .await?
                        .try_get::<i64, _>("arrival")?
                };
                items.push(Appended {
                    robot_id: rec.robot_id.clone(),
                    seq: rec.seq,
                    arrival,
                    duplicate: !inserted,
                });
            }
            outcomes.push(AppendOutcome { items });
        }
        tx.commit().await?;
        outcomes
    });
    Ok(outcomes)
}

/// The statement that opens a write transaction: SQLite takes its write lock up front
/// (`BEGIN IMMEDIATE`), so a transaction never fails to upgrade from reading to writing.
fn pool_begin<P: crate::pool::BeginStatement>(_: &P) -> &'static str {
    P::BEGIN
}
