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

use std::collections::{HashMap, HashSet};
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
            highest: HashMap::new(),
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
    /// The highest seq stored of each robot of the runs in `next` (loaded with it): a record
    /// above it cannot repeat a stored one, so only the others are looked up.
    highest: HashMap<String, Highest>,
}

/// Robot -> the highest seq stored in one run's log.
type Highest = HashMap<String, i64>;

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
        self.highest.remove(run_id);
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

    /// Makes sure the counter and the robots' highest seqs of `run_id` are loaded;
    /// `NotFound` when the run does not exist.
    async fn load_counter(&mut self, run_id: &str) -> Result<(), StoreError> {
        if self.next.contains_key(run_id) && self.highest.contains_key(run_id) {
            return Ok(());
        }
        let loaded = with_pool!(&self.pool, pool => {
            let last = sqlx::query(
                "SELECT (SELECT COALESCE(MAX(arrival), 0) FROM observations WHERE run_id = $1) AS last \
                 FROM runs WHERE id = $1",
            )
            .bind(run_id)
            .fetch_optional(pool)
            .await?
            .map(|row| row.try_get::<i64, _>("last"))
            .transpose()?;
            match last {
                Some(last) => {
                    let mut highest = Highest::new();
                    for row in sqlx::query(
                        "SELECT robot_id, MAX(seq) AS seq FROM observations WHERE run_id = $1 \
                         GROUP BY robot_id",
                    )
                    .bind(run_id)
                    .fetch_all(pool)
                    .await?
                    {
                        highest.insert(row.try_get("robot_id")?, row.try_get("seq")?);
                    }
                    Some((last, highest))
                }
                None => None,
            }
        });
        match loaded {
            Some((last, highest)) => {
                self.next.insert(run_id.to_owned(), last + 1);
                self.highest.insert(run_id.to_owned(), highest);
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
        let result = write_group(&self.pool, jobs, &mut next, &self.highest).await;
        match result {
            Ok(outcomes) => {
                self.stats.commits.fetch_add(1, Ordering::Relaxed);
                for (run, n) in next {
                    self.next.insert(run.to_owned(), n);
                }
                for (job, outcome) in jobs.iter().zip(&outcomes) {
                    let Some(highest) = self.highest.get_mut(job.run_id.as_str()) else {
                        continue;
                    };
                    for item in outcome.items.iter().filter(|i| !i.duplicate) {
                        match highest.get_mut(&item.robot_id) {
                            Some(h) => *h = (*h).max(item.seq),
                            None => {
                                highest.insert(item.robot_id.clone(), item.seq);
                            }
                        }
                    }
                }
                Ok(outcomes)
            }
            Err(e) => {
                for job in jobs {
                    self.next.remove(&job.run_id);
                    self.highest.remove(&job.run_id);
                }
                Err(e)
            }
        }
    }
}

/// The most records one `INSERT` of a group writes (6 bound values each: within SQLite's
/// and PostgreSQL's limits on bound parameters, 32,766 and 65,535).
const ROWS_PER_INSERT: usize = 1000;
/// The most `(robot, seq)` keys one look-up of already stored records asks for (2 bound
/// values each).
const KEYS_PER_LOOKUP: usize = 1000;

/// The group transaction itself, in a few statements whatever the group's size: one look-up
/// of the group's records that may already be in the log (repeats of acknowledged ones:
/// those at or below their robot's highest stored seq, `highest`) per [`KEYS_PER_LOOKUP`]
/// keys, none when robots post rising seqs, then the new ones in multi-row `INSERT`s of at
/// most [`ROWS_PER_INSERT`]. A repeat (already stored, or earlier in the same group) keeps its
/// first arrival; every new record takes its run's next arrival number, in the order of the
/// calls and of their records. Only this task inserts observations and SQLite's transaction
/// holds the write lock from its start, so a look-up cannot miss a row that the insert then
/// meets; should another writer have inserted one anyway (a PostgreSQL run written from two
/// places), the unique key fails the whole transaction, nothing is acknowledged, and the
/// retry finds the row as a repeat.
async fn write_group<'a>(
    pool: &Pool,
    jobs: &'a [AppendJob],
    next: &mut HashMap<&'a str, i64>,
    highest: &HashMap<String, Highest>,
) -> Result<Vec<AppendOutcome>, StoreError> {
    // Each run's distinct (robot, seq) keys that may already be stored (at or below their
    // robot's highest stored seq), in first-seen order.
    let mut keys: Vec<(&str, Vec<(&str, i64)>)> = Vec::new();
    let mut distinct: HashSet<(&str, &str, i64)> = HashSet::new();
    for job in jobs {
        let run = job.run_id.as_str();
        let high = highest.get(run);
        for rec in &job.recs {
            let stored_above = high
                .and_then(|h| h.get(rec.robot_id.as_str()))
                .is_some_and(|&h| rec.seq <= h);
            if stored_above && distinct.insert((run, rec.robot_id.as_str(), rec.seq)) {
                let key = (rec.robot_id.as_str(), rec.seq);
                match keys.iter_mut().find(|(r, _)| *r == run) {
                    Some((_, list)) => list.push(key),
                    None => keys.push((run, vec![key])),
                }
            }
        }
    }
    let outcomes = with_pool!(pool, pool => {
        let mut tx = pool.begin_with(pool_begin(pool)).await?;
        // The arrivals of the group's records already in the log: run -> robot -> seq.
        let mut stored: HashMap<&str, HashMap<String, HashMap<i64, i64>>> = HashMap::new();
        for (run, list) in &keys {
            for chunk in list.chunks(KEYS_PER_LOOKUP) {
                let mut q = sqlx::QueryBuilder::new(
                    "SELECT robot_id, seq, arrival FROM observations WHERE run_id = ",
                );
                q.push_bind(*run);
                q.push(" AND (robot_id, seq) IN (VALUES ");
                let mut values = q.separated(", ");
                for (robot, seq) in chunk {
                    values.push("(");
                    values.push_bind_unseparated(*robot);
                    values.push_unseparated(", ");
                    values.push_bind_unseparated(*seq);
                    values.push_unseparated(")");
                }
                q.push(")");
                for row in q.build().fetch_all(&mut *tx).await? {
                    let robot: String = row.try_get("robot_id")?;
                    stored
                        .entry(*run)
                        .or_default()
                        .entry(robot)
                        .or_default()
                        .insert(row.try_get("seq")?, row.try_get("arrival")?);
                }
            }
        }
        let mut outcomes = Vec::with_capacity(jobs.len());
        let mut assigned: HashMap<(&str, &str, i64), i64> = HashMap::new();
        let mut fresh: Vec<(&str, i64, &NewObservation)> = Vec::new();
        for job in jobs {
            let run = job.run_id.as_str();
            let mut items = Vec::with_capacity(job.recs.len());
            for rec in &job.recs {
                let key = (run, rec.robot_id.as_str(), rec.seq);
                let before = stored
                    .get(run)
                    .and_then(|robots| robots.get(key.1))
                    .and_then(|seqs| seqs.get(&key.2))
                    .or_else(|| assigned.get(&key))
                    .copied();
                let (arrival, duplicate) = match before {
                    Some(arrival) => (arrival, true),
                    None => {
                        let counter = next.entry(run).or_insert(1);
                        let arrival = *counter;
                        *counter += 1;
                        assigned.insert(key, arrival);
                        fresh.push((run, arrival, rec));
                        (arrival, false)
                    }
                };
                items.push(Appended {
                    robot_id: rec.robot_id.clone(),
                    seq: rec.seq,
                    arrival,
                    duplicate,
                });
            }
            outcomes.push(AppendOutcome { items });
        }
        for chunk in fresh.chunks(ROWS_PER_INSERT) {
            let mut q = sqlx::QueryBuilder::new(
                "INSERT INTO observations (run_id, arrival, robot_id, seq, t, body) ",
            );
            q.push_values(chunk, |mut b, (run, arrival, rec)| {
                b.push_bind(*run)
                    .push_bind(*arrival)
                    .push_bind(rec.robot_id.as_str())
                    .push_bind(rec.seq)
                    .push_bind(rec.t)
                    .push_bind(rec.body.as_str());
            });
            q.build().execute(&mut *tx).await?;
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
