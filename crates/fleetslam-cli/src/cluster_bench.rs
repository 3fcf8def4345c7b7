//! `fleetslam cluster-bench`: what a cluster of replicas does on this machine. Starts a
//! 3-node NATS JetStream cluster (R3) and 1, 2, 3 replicas on loopback ports, with a fresh
//! PostgreSQL database each time; `runs` replays of simulated 3-robot logs post as fast as
//! they are acknowledged, spread over all replicas. Prints the records acknowledged per
//! second and the acknowledgement latency; then, with 3 replicas and paced robots, kills
//! (SIGKILL) one replica and measures how long each of its runs waits for a new owner (kill
//! to the new owner's first state: its recovery from PostgreSQL, after which it publishes).

use crate::localcluster::{self, Proc};
use anyhow::{Context, Result, bail};
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

pub struct BenchOptions {
    pub database_url: String,
    pub replicas: Vec<usize>,
    pub runs: usize,
    pub duration_s: f64,
    pub batch: usize,
    pub nats_server: Option<PathBuf>,
}

/// One replay's summary line, parsed.
struct Summary {
    records: u64,
    wall_s: f64,
    p50_ms: f64,
    p99_ms: f64,
}

fn number_before(text: &str, unit: &str) -> Option<f64> {
    let i = text.find(unit)?;
    text[..i].split_whitespace().last()?.parse().ok()
}

fn parse_summary(line: &str) -> Option<Summary> {
    // "... N acknowledged (...) ...; R records/s over W s; ack latency p50 A ms, p99 B ms"
    Some(Summary {
        records: number_before(line, " acknowledged")? as u64,
        wall_s: number_before(line, " s;")?,
        p50_ms: number_before(line.split("p50").nth(1)?, " ms")?,
        p99_ms: number_before(line.split("p99").nth(1)?, " ms")?,
    })
}

fn simulate(exe: &Path, dir: &Path, o: &BenchOptions) -> Result<Vec<PathBuf>> {
    (0..o.runs)
        .map(|k| {
            let out = dir.join(format!("sim{k}"));
            let status = Command::new(exe)
                .args(["simulate", "--robots", "3", "--duration"])
                .arg(o.duration_s.to_string())
                .args(["--seed", &(100 + k).to_string(), "--out"])
                .arg(&out)
                .stdout(Stdio::null())
                .status()?;
            if !status.success() {
                bail!("simulate failed");
            }
            Ok(out.join("log.ndjson"))
        })
        .collect()
}

/// Starts the replays; returns the children and the run ids.
fn replays(
    exe: &Path,
    logs: &[PathBuf],
    servers: &str,
    pace: &[&str],
    batch: usize,
) -> Result<Vec<(Proc, BufReader<std::process::ChildStdout>, String)>> {
    logs.iter()
        .map(|log| {
            let mut child = Command::new(exe)
                .arg("replay")
                .arg(log)
                .args(["--server", servers, "--particles", "50", "--batch"])
                .arg(batch.to_string())
                .args(pace)
                .stdout(Stdio::piped())
                .stderr(Stdio::null())
                .spawn()?;
            let mut out = BufReader::new(child.stdout.take().context("stdout")?);
            let mut line = String::new();
            out.read_line(&mut line)?;
            let run = line
                .strip_prefix("run ")
                .with_context(|| format!("no run id in {line:?}"))?
                .trim()
                .to_string();
            Ok((Proc(child), out, run))
        })
        .collect()
}

fn finish(rs: Vec<(Proc, BufReader<std::process::ChildStdout>, String)>) -> Result<Vec<Summary>> {
    rs.into_iter()
        .map(|(mut child, mut out, _)| {
            let status = child.0.wait()?;
            let mut rest = String::new();
            out.read_to_string(&mut rest)?;
            if !status.success() {
                bail!("a replay failed: {rest}");
            }
            rest.lines()
                .find_map(parse_summary)
                .with_context(|| format!("no summary in {rest:?}"))
        })
        .collect()
}

/// Seconds since midnight UTC of a tracing line's timestamp (`2026-12-02T11:18:12.614444Z`).
fn line_time(line: &str) -> Option<f64> {
    let t = line
        .split_whitespace()
        .next()?
        .split('T')
        .nth(1)?
        .trim_end_matches('Z');
    let mut it = t.split(':');
    let (h, m, s): (f64, f64, f64) = (
        it.next()?.parse().ok()?,
        it.next()?.parse().ok()?,
        it.next()?.parse().ok()?,
    );
    Some(h * 3600.0 + m * 60.0 + s)
}

fn now_of_day() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() % 86400.0)
}

/// A cluster: NATS nodes, a database, replicas.
struct Cluster {
    _nodes: Vec<Proc>,
    replicas: Vec<(Proc, String)>,
    db_name: String,
}

impl Cluster {
    /// The replicas' base URLs, comma-separated (`replay --server`).
    fn servers(&self) -> String {
        self.replicas
            .iter()
            .map(|(_, u)| u.as_str())
            .collect::<Vec<_>>()
            .join(",")
    }

    /// Stops the replicas and drops the database.
    async fn stop(self, database_url: &str) -> Result<()> {
        drop(self.replicas);
        fleetslam_store::admin::drop_postgres_database(database_url, &self.db_name).await?;
        Ok(())
    }
}

async fn start_cluster(
    exe: &Path,
    nats: &Path,
    dir: &Path,
    o: &BenchOptions,
    n: usize,
) -> Result<Cluster> {
    std::fs::create_dir_all(dir)?;
    let (nodes, urls) = localcluster::nats_cluster(nats, dir, 3)?;
    let db_name = format!("fleetslam_bench_{}_{n}", std::process::id());
    let db = fleetslam_store::admin::create_postgres_database(&o.database_url, &db_name).await?;
    let nats_urls = urls.join(",");
    let replicas = (0..n)
        .map(|i| {
            localcluster::replica(
                exe,
                dir,
                i,
                &nats_urls,
                &db,
                3,
                &[("FLEETSLAM_REORDER_WINDOW_MS", "30000")],
            )
            .map_err(anyhow::Error::msg)
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Cluster {
        _nodes: nodes,
        replicas,
        db_name,
    })
}

pub async fn run(o: BenchOptions) -> Result<()> {
    let exe = std::env::current_exe()?;
    let nats = o
        .nats_server
        .clone()
        .or_else(localcluster::nats_server)
        .context("no nats-server found: install Debian's nats-server or pass --nats-server")?;
    let tmp = tempfile::tempdir()?;
    let logs = simulate(&exe, tmp.path(), &o)?;
    let total: usize = logs
        .iter()
        .map(|l| std::fs::read_to_string(l).map(|t| t.lines().count() - 1))
        .sum::<std::io::Result<usize>>()?;
    println!(
        "{} runs x 3 simulated robots, {total} records, 50 particles; NATS: 3 nodes, R3",
        o.runs
    );
    println!(
        "| replicas | records/s acknowledged | ack latency p50 (median over runs) | p99 (worst run) |"
    );
    println!("|---|---|---|---|");
    for &n in &o.replicas {
        let dir = tmp.path().join(format!("cluster{n}"));
        let c = start_cluster(&exe, &nats, &dir, &o, n).await?;
        let servers = c.servers();
        let started = Instant::now();
        let rs = replays(&exe, &logs, &servers, &["--fast"], o.batch)?;
        let sums = finish(rs)?;
        let wall = started.elapsed().as_secs_f64();
        let acked: u64 = sums.iter().map(|s| s.records).sum();
        let mut p50: Vec<f64> = sums.iter().map(|s| s.p50_ms).collect();
        p50.sort_by(f64::total_cmp);
        let p99 = sums.iter().map(|s| s.p99_ms).fold(0.0, f64::max);
        let slowest = sums.iter().map(|s| s.wall_s).fold(0.0, f64::max);
        println!(
            "| {n} | {:.0} ({acked} in {slowest:.1} s; {wall:.1} s with set-up) | {:.1} ms | {p99:.1} ms |",
            acked as f64 / slowest.max(1e-9),
            p50[p50.len() / 2]
        );
        c.stop(&o.database_url).await?;
    }

    // Failover: paced robots, one replica killed.
    let dir = tmp.path().join("failover");
    let mut c = start_cluster(&exe, &nats, &dir, &o, 3).await?;
    let servers = c.servers();
    let rs = replays(&exe, &logs, &servers, &["--speed", "5"], 5)?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let killed_at = now_of_day();
    c.replicas[0].0.kill();
    let sums = finish(rs)?;
    let took = |line: &str| line.contains("run recovered; reading its subject");
    let owned_by_r0: Vec<String> = std::fs::read_to_string(dir.join("replica0.log"))?
        .lines()
        .filter(|l| l.contains("took the run"))
        .filter_map(|l| {
            l.split("run=")
                .nth(1)?
                .split_whitespace()
                .next()
                .map(str::to_string)
        })
        .collect();
    let mut waits = Vec::new();
    for i in 1..3 {
        for line in std::fs::read_to_string(dir.join(format!("replica{i}.log")))?.lines() {
            if took(line)
                && owned_by_r0.iter().any(|r| line.contains(r.as_str()))
                && let Some(t) = line_time(line)
                && t > killed_at
            {
                waits.push(t - killed_at);
            }
        }
    }
    waits.sort_by(f64::total_cmp);
    let acked: u64 = sums.iter().map(|s| s.records).sum();
    println!(
        "failover (3 replicas, lease 3 s): {} runs moved; kill -> new owner's first state: {}; {acked} of {total} records acknowledged",
        waits.len(),
        waits
            .iter()
            .map(|w| format!("{w:.2} s"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    c.stop(&o.database_url).await
}
