//! `fleetslam replay`: plays a log into a server as k concurrent robot clients.
//!
//! Each robot posts its own records in order with its own token, in real time (scaled) or
//! as fast as the server accepts. A request that fails for a reason that may pass (no
//! connection, 5xx, 503/429 busy) is retried with jittered exponential backoff, never
//! sooner than the server's Retry-After, until the bound of [`RetryPolicy`]: records carry
//! sequence numbers and a repeat is acknowledged again and applied once, so a replay
//! survives a server restart.
//!
//! Given several servers (the replicas of a cluster), the robots are spread over them
//! (robot k posts to server k mod n) and a robot whose server fails moves on to the next.

use anyhow::{Context, Result};
use backon::{ExponentialBuilder, Retryable};
use fleetslam_core::log::{Log, Record};
use indicatif::{ProgressBar, ProgressStyle};
use reqwest::StatusCode;
use serde_json::{Value, json};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// How to pace the records.
#[derive(Debug, Clone, Copy)]
pub enum Pace {
    /// Data time divided by this factor (1.0 = real time).
    Scaled(f64),
    /// As fast as the server acknowledges.
    Fast,
}

#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// Base URLs: one server, or the replicas of a cluster.
    pub servers: Vec<String>,
    /// Join this run instead of creating one.
    pub run: Option<String>,
    /// FilterConfig overrides for a new run.
    pub config: Value,
    pub admin_token: Option<String>,
    pub pace: Pace,
    /// Most records per request.
    pub batch: usize,
    pub progress: bool,
    /// A new run logs this fraction of its landmark updates as training rows.
    pub training_rate: Option<f64>,
    /// How a robot retries a request of records that failed for a reason that may pass.
    pub retry: RetryPolicy,
}

/// How a robot retries a POST of its records that failed for a reason that may pass: no
/// answer, 5xx, or 503/429 (busy).
///
/// The waits grow exponentially (doubling) from `min_delay` to `max_delay`, each with a
/// random jitter of up to its own length added (so a wait lies in `[d, 2d)`), so robots
/// that failed together do not all come back at once. A `Retry-After` (seconds) on a
/// 503/429 answer is a floor: the next attempt waits at least that long. The robot gives up
/// on the request, and the replay fails, once the next attempt would start more than
/// `max_elapsed` after the first, or after `max_attempts` attempts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RetryPolicy {
    /// The first wait (before jitter). Default 50 ms.
    pub min_delay: Duration,
    /// The longest wait before jitter (Retry-After may ask for longer). Default 2 s.
    pub max_delay: Duration,
    /// No attempt starts later than this after the request's first one. Default 60 s: a
    /// server restart (or a replica's failover) of well over 10 s is survived.
    pub max_elapsed: Duration,
    /// Attempts per request, the first included (`None`: only `max_elapsed` bounds them).
    /// Default `None`.
    pub max_attempts: Option<usize>,
}

impl RetryPolicy {
    pub const DEFAULT: RetryPolicy = RetryPolicy {
        min_delay: Duration::from_millis(50),
        max_delay: Duration::from_secs(2),
        max_elapsed: Duration::from_secs(60),
        max_attempts: None,
    };

    /// The backoff (without the elapsed-time bound, which [`post_records`] applies).
    fn backoff(&self) -> ExponentialBuilder {
        let b = ExponentialBuilder::default()
            .with_min_delay(self.min_delay)
            .with_max_delay(self.max_delay.max(self.min_delay))
            .with_factor(2.0)
            .with_jitter();
        match self.max_attempts {
            Some(n) => b.with_max_times(n.saturating_sub(1)),
            None => b.without_max_times(),
        }
    }

    /// The bound, for the give-up message.
    fn bound(&self) -> String {
        let elapsed = self.max_elapsed.as_secs_f64();
        match self.max_attempts {
            Some(n) => format!("bound: {n} attempts or {elapsed} s"),
            None => format!("bound: {elapsed} s"),
        }
    }
}

impl Default for RetryPolicy {
    fn default() -> Self {
        Self::DEFAULT
    }
}

#[derive(Debug, Default, serde::Serialize)]
pub struct ReplaySummary {
    pub run: String,
    pub sent: u64,
    pub acknowledged: u64,
    pub duplicates: u64,
    pub rejected: u64,
    pub retried: u64,
    pub wall_time_s: f64,
    pub records_per_s: f64,
    pub latency_ms_p50: f64,
    pub latency_ms_p99: f64,
}

impl std::fmt::Display for ReplaySummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "run {}: {} records sent, {} acknowledged ({} repeats), {} rejected, {} requests retried; {:.0} records/s over {:.1} s; ack latency p50 {:.2} ms, p99 {:.2} ms",
            self.run,
            self.sent,
            self.acknowledged,
            self.duplicates,
            self.rejected,
            self.retried,
            self.records_per_s,
            self.wall_time_s,
            self.latency_ms_p50,
            self.latency_ms_p99
        )
    }
}

struct Counters {
    acked: AtomicU64,
    dups: AtomicU64,
    rejected: AtomicU64,
    retried: AtomicU64,
}

fn client() -> Result<reqwest::Client> {
    Ok(reqwest::Client::builder()
        .timeout(Duration::from_secs(30))
        .build()?)
}

impl ReplayOptions {
    /// The servers' base URLs, starting with the `k`-th (mod n).
    pub fn bases(&self, k: usize) -> Vec<String> {
        let n = self.servers.len().max(1);
        (0..self.servers.len())
            .map(|i| self.servers[(k + i) % n].trim_end_matches('/').to_string())
            .collect()
    }
}

/// POSTs to the first server that answers; a refusal (4xx) is final, a server that cannot
/// be reached or fails (5xx) passes the request to the next one.
async fn post_any(
    c: &reqwest::Client,
    bases: &[String],
    path: &str,
    token: Option<&str>,
    body: &Value,
) -> Result<Value> {
    let mut last = None;
    for base in bases {
        match post_json(c, &format!("{base}{path}"), token, body).await {
            Ok(v) => return Ok(v),
            Err(PostError::Refused(e)) => return Err(e),
            Err(PostError::Failed(e)) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| anyhow::anyhow!("no server given")))
}

enum PostError {
    /// The server answered 4xx.
    Refused(anyhow::Error),
    /// No answer, or 5xx.
    Failed(anyhow::Error),
}

async fn post_json(
    c: &reqwest::Client,
    url: &str,
    token: Option<&str>,
    body: &Value,
) -> Result<Value, PostError> {
    let mut req = c.post(url).json(body);
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    let resp = req
        .send()
        .await
        .with_context(|| format!("POST {url}"))
        .map_err(PostError::Failed)?;
    let status = resp.status();
    if !status.is_success() {
        let message = server_message(&resp.text().await.unwrap_or_default());
        let e = anyhow::anyhow!("POST {url}: {status}: {message}");
        return Err(if status.is_server_error() {
            PostError::Failed(e)
        } else {
            PostError::Refused(e)
        });
    }
    Ok(resp.json().await.unwrap_or(Value::Null))
}

/// Why one POST of a robot's records failed.
#[derive(Debug)]
enum Failure {
    /// 503 or 429: the server is busy; the same server is asked again, not before
    /// Retry-After.
    Busy {
        url: String,
        status: StatusCode,
        message: String,
        retry_after: Option<Duration>,
    },
    /// Another 5xx: the next server takes the robot.
    ServerError {
        url: String,
        status: StatusCode,
        message: String,
    },
    /// No answer (no connection, timeout, broken answer): this server may be gone; the next
    /// one takes the robot.
    NoAnswer { url: String, error: reqwest::Error },
    /// Another 4xx: final.
    Refused {
        url: String,
        status: StatusCode,
        message: String,
    },
}

impl Failure {
    /// Whether the robot moves on to the next server before it tries again.
    fn moves_on(&self) -> bool {
        matches!(self, Failure::ServerError { .. } | Failure::NoAnswer { .. })
    }
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Failure::Busy {
                url,
                status,
                message,
                retry_after,
            } => {
                write!(f, "POST {url}: {status}: {message}")?;
                if let Some(r) = retry_after {
                    write!(f, " (Retry-After: {} s)", r.as_secs())?;
                }
                Ok(())
            }
            Failure::ServerError {
                url,
                status,
                message,
            }
            | Failure::Refused {
                url,
                status,
                message,
            } => write!(f, "POST {url}: {status}: {message}"),
            Failure::NoAnswer { url, error } => {
                write!(f, "POST {url}: no answer: {error}")?;
                let mut source = std::error::Error::source(error);
                while let Some(e) = source {
                    write!(f, ": {e}")?;
                    source = e.source();
                }
                Ok(())
            }
        }
    }
}

/// The seconds form of a Retry-After header (the HTTP-date form is not used by the server).
fn retry_after(headers: &reqwest::header::HeaderMap) -> Option<Duration> {
    let v = headers.get(reqwest::header::RETRY_AFTER)?.to_str().ok()?;
    v.trim().parse::<u64>().ok().map(Duration::from_secs)
}

/// The `message` of an error body, else the body itself (shortened).
fn server_message(body: &str) -> String {
    match serde_json::from_str::<Value>(body) {
        Ok(v) if v["message"].is_string() => v["message"].as_str().unwrap_or_default().into(),
        _ if body.trim().is_empty() => "(no message)".into(),
        _ => body.trim().chars().take(300).collect(),
    }
}

/// POSTs one request of a robot's records to `urls[at]`, retrying under `policy`: 503/429
/// on the same server, another 5xx or no answer on the next one (`at` moves on); a 2xx or
/// 409 answer is returned with the answering attempt's latency [ms]; another 4xx fails at
/// once. Each retry counts in `retried`.
async fn post_records(
    c: &reqwest::Client,
    urls: &[String],
    token: &str,
    records: &[Record],
    policy: &RetryPolicy,
    at: &AtomicUsize,
    retried: &AtomicU64,
) -> Result<(Value, f64)> {
    let started = Instant::now();
    let attempts = AtomicUsize::new(0);
    let attempts_ref = &attempts;
    let attempt = move || async move {
        attempts_ref.fetch_add(1, Ordering::Relaxed);
        let url = &urls[at.load(Ordering::Relaxed) % urls.len()];
        let t0 = Instant::now();
        let no_answer = |error| Failure::NoAnswer {
            url: url.clone(),
            error,
        };
        let resp = c
            .post(url)
            .bearer_auth(token)
            .json(records)
            .send()
            .await
            .map_err(no_answer)?;
        let status = resp.status();
        if status.is_success() || status == StatusCode::CONFLICT {
            let v: Value = resp.json().await.unwrap_or(Value::Null);
            return Ok((v, t0.elapsed().as_secs_f64() * 1e3));
        }
        let retry_after = retry_after(resp.headers());
        let message = server_message(&resp.text().await.unwrap_or_default());
        let url = url.clone();
        Err(
            if status == StatusCode::SERVICE_UNAVAILABLE || status == StatusCode::TOO_MANY_REQUESTS
            {
                Failure::Busy {
                    url,
                    status,
                    message,
                    retry_after,
                }
            } else if status.is_server_error() {
                Failure::ServerError {
                    url,
                    status,
                    message,
                }
            } else {
                Failure::Refused {
                    url,
                    status,
                    message,
                }
            },
        )
    };
    let result = attempt
        .retry(policy.backoff())
        .when(|f: &Failure| !matches!(f, Failure::Refused { .. }))
        .adjust(|f: &Failure, wait: Option<Duration>| {
            // None: out of attempts.
            let wait = match f {
                Failure::Busy {
                    retry_after: Some(r),
                    ..
                } => wait?.max(*r),
                _ => wait?,
            };
            (started.elapsed() + wait <= policy.max_elapsed).then_some(wait)
        })
        .notify(|f: &Failure, _wait: Duration| {
            if f.moves_on() {
                at.fetch_add(1, Ordering::Relaxed);
            }
            retried.fetch_add(1, Ordering::Relaxed);
        })
        .await;
    result.map_err(|f| {
        let robot = records.first().map_or("?", |r| r.robot.as_str());
        let seqs = match (records.first(), records.last()) {
            (Some(a), Some(b)) if a.seq != b.seq => format!("records seq {}..={}", a.seq, b.seq),
            (Some(a), _) => format!("record seq {}", a.seq),
            _ => "no records".into(),
        };
        let n = attempts.load(Ordering::Relaxed);
        if let Failure::Refused { .. } = f {
            anyhow::anyhow!("robot {robot}: {seqs} refused: {f}")
        } else {
            anyhow::anyhow!(
                "robot {robot}: gave up on {seqs} after {n} attempts in {:.1} s ({}); last failure: {f}",
                started.elapsed().as_secs_f64(),
                policy.bound()
            )
        }
    })
}

/// Uploads a run's ground truth (`PUT /v1/runs/{run}/truth`).
pub async fn put_truth(
    o: &ReplayOptions,
    run: &str,
    truth: &fleetslam_data::formats::Truth,
) -> Result<()> {
    let c = client()?;
    let url = format!("{}/v1/runs/{run}/truth", o.bases(0)[0]);
    let mut req = c
        .put(&url)
        .json(&fleetslam_server::history::truth_to_json(truth));
    if let Some(t) = &o.admin_token {
        req = req.bearer_auth(t);
    }
    let resp = req.send().await.with_context(|| format!("PUT {url}"))?;
    if !resp.status().is_success() {
        let status = resp.status();
        let message = server_message(&resp.text().await.unwrap_or_default());
        anyhow::bail!("PUT {url}: {status}: {message}");
    }
    Ok(())
}

/// Creates (or joins) the run and registers the log's robots; returns run id and tokens.
pub async fn setup(log: &Log, o: &ReplayOptions) -> Result<(String, Vec<(String, String)>)> {
    let c = client()?;
    let run = match &o.run {
        Some(r) => r.clone(),
        None => {
            let v = post_any(
                &c,
                &o.bases(0),
                "/v1/runs",
                o.admin_token.as_deref(),
                &json!({
                    "name": log.header.name,
                    "header": log.header,
                    "config": o.config,
                    "training": o.training_rate.map(|rate| json!({"rate": rate})),
                }),
            )
            .await?;
            v["id"]
                .as_str()
                .context("the server returned no run id")?
                .to_string()
        }
    };
    let mut tokens = Vec::new();
    for (k, r) in log.header.robots.iter().enumerate() {
        let v = post_any(
            &c,
            &o.bases(k),
            &format!("/v1/runs/{run}/robots"),
            None,
            &json!({"id": r.id, "start": r.start, "t0": r.t0}),
        )
        .await
        .with_context(|| format!("registering robot {}", r.id))?;
        tokens.push((
            r.id.clone(),
            v["token"].as_str().context("no token")?.to_string(),
        ));
    }
    Ok((run, tokens))
}

/// Plays the records of `log` into `run` with one client per robot.
pub async fn play(
    log: &Log,
    run: &str,
    tokens: Vec<(String, String)>,
    o: &ReplayOptions,
) -> Result<ReplaySummary> {
    let total = log.records.len() as u64;
    let bar = if o.progress {
        ProgressBar::new(total)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} acknowledged ({per_sec})",
    )?);
    let counters = Arc::new(Counters {
        acked: AtomicU64::new(0),
        dups: AtomicU64::new(0),
        rejected: AtomicU64::new(0),
        retried: AtomicU64::new(0),
    });
    let t_data0 = log
        .records
        .iter()
        .map(|r| r.t)
        .fold(f64::INFINITY, f64::min);
    let start = Instant::now();
    let mut tasks = Vec::new();
    for (k, (robot, token)) in tokens.into_iter().enumerate() {
        let records: Vec<Record> = log
            .records
            .iter()
            .filter(|r| r.robot == robot)
            .cloned()
            .collect();
        let (c, counters, bar, bases) = (client()?, counters.clone(), bar.clone(), o.bases(k));
        let (run, pace, batch, retry) = (run.to_string(), o.pace, o.batch.max(1), o.retry);
        tasks.push(tokio::spawn(async move {
            let urls: Vec<String> = bases
                .iter()
                .map(|b| format!("{b}/v1/runs/{run}/observations"))
                .collect();
            // The server this robot posts to; it moves on when that one fails.
            let at = AtomicUsize::new(0);
            let mut latencies = Vec::with_capacity(records.len());
            let mut i = 0;
            while i < records.len() {
                let mut n = 1;
                if let Pace::Scaled(speed) = pace {
                    let due = Duration::from_secs_f64(((records[i].t - t_data0) / speed).max(0.0));
                    if let Some(wait) = due.checked_sub(start.elapsed()) {
                        tokio::time::sleep(wait).await;
                    }
                    // Everything already due goes in one request.
                    while i + n < records.len()
                        && n < batch
                        && (records[i + n].t - t_data0) / speed <= start.elapsed().as_secs_f64()
                    {
                        n += 1;
                    }
                } else {
                    n = batch.min(records.len() - i);
                }
                let chunk = &records[i..i + n];
                let (v, latency_ms) =
                    post_records(&c, &urls, &token, chunk, &retry, &at, &counters.retried).await?;
                latencies.push(latency_ms);
                for a in v["acks"].as_array().into_iter().flatten() {
                    match a["status"].as_str() {
                        Some("stored") => {
                            counters.acked.fetch_add(1, Ordering::Relaxed);
                        }
                        Some("duplicate") => {
                            counters.acked.fetch_add(1, Ordering::Relaxed);
                            counters.dups.fetch_add(1, Ordering::Relaxed);
                        }
                        _ => {
                            counters.rejected.fetch_add(1, Ordering::Relaxed);
                            bar.println(format!("robot {robot}: rejected: {}", a["error"]));
                        }
                    }
                }
                bar.inc(n as u64);
                i += n;
            }
            Ok::<_, anyhow::Error>(latencies)
        }));
    }
    let mut lat = Vec::new();
    for t in tasks {
        lat.extend(t.await.context("robot client")??);
    }
    bar.finish_and_clear();
    lat.sort_by(f64::total_cmp);
    let pct = |p: f64| {
        lat.get(((lat.len().max(1) - 1) as f64 * p).round() as usize)
            .copied()
            .unwrap_or(0.0)
    };
    let wall = start.elapsed().as_secs_f64();
    let acked = counters.acked.load(Ordering::Relaxed);
    Ok(ReplaySummary {
        run: run.to_string(),
        sent: total,
        acknowledged: acked,
        duplicates: counters.dups.load(Ordering::Relaxed),
        rejected: counters.rejected.load(Ordering::Relaxed),
        retried: counters.retried.load(Ordering::Relaxed),
        wall_time_s: wall,
        records_per_s: acked as f64 / wall.max(1e-9),
        latency_ms_p50: pct(0.5),
        latency_ms_p99: pct(0.99),
    })
}
