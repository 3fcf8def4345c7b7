//! The server's overhead on a whole run: a log posted over HTTP by its robots as concurrent
//! clients (one per robot, each waiting for its acknowledgement before its next request) to
//! a real server on 127.0.0.1 with a durable SQLite store (every record committed before its
//! acknowledgement) and one websocket listener on the run's `live` stream, against the same
//! log through `run_log` offline (same particles and seed), in one process. Rounds
//! alternate the two, so that both see the same load on the machine.
//!
//! ```sh
//! cargo run --profile test -p fleetslam-server --example server_overhead -- \
//!     ../shared/datasets/mrclam-dataset6 [PARTICLES] [ROUNDS] [DURATION_S|all] [RUNS]
//! ```
//!
//! The source is a UTIAS MRCLAM data set's directory, imported as `fleetslam import mrclam`
//! does (its first `DURATION_S` seconds; all of it when omitted or `all`), or a log file
//! (`log.ndjson`). `PARTICLES` defaults to 1,000 and `ROUNDS` to 3; seed 1, [`BATCH`]
//! records per request. The server takes its defaults under the `FLEETSLAM_<FIELD>`
//! variables, as `fleetslam serve` does (e.g. `FLEETSLAM_SNAPSHOT_EVERY=2000
//! FLEETSLAM_SNAPSHOT_EVERY_WORK_MS=1000000` for snapshots by the record count alone).
//! Per round it prints the offline wall time, the server's wall time (from the first post
//! until the run's end is answered: every record stored, applied and the run's result
//! stored) and their ratio, the longest wait between two states the listener received, and
//! checks that the server's trajectories and landmarks equal the offline run's bit for bit;
//! then the median ratio. It also prints the CPU time this process used on each side, and
//! the server's by thread name: the filter's workers (`rayon-N`, rayon's shared pool,
//! named here), the server's async runtime's (`tokio-rt-worker`: the handlers, and the
//! coordinator's blocking thread, where each step's serial parts run), SQLite's, and the
//! clients' and listener's own runtime's (`clients-rt`).
//!
//! With `RUNS` above 1 (default 1), that many runs of the log are posted to one server at
//! the same time, each by its own clients and with its own listener: each run's wall time
//! and longest gap between states show how the runs share the machine, and the ratio is the
//! time until the last run ended against `RUNS` offline runs one after another.

/// The `fleetslam` binary's allocator (crates/fleetslam-cli/src/main.rs), so that both sides
/// are measured as that binary runs them.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

use fleetslam_core::config::FilterConfig;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::{Log, Record};
use fleetslam_data::import::{MrclamOptions, import_mrclam};
use fleetslam_data::run::{RunOutput, TrajectoryEstimate, run_log};
use fleetslam_server::config::ServerConfig;
use futures::StreamExt;
use serde_json::{Value, json};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

/// Records per request (as `fleetslam replay --batch 20`).
const BATCH: usize = 20;

/// What the websocket listener saw.
#[derive(Debug, Default)]
struct Heard {
    states: u64,
    events: u64,
    /// `applied` of the newest state received.
    last_applied: u64,
    /// The longest wait between two states received before the run's end was announced.
    max_gap: Duration,
}

impl Heard {
    /// Takes in a state message received at `at`, after the previous one (if any) at `last`.
    fn state(&mut self, v: &Value, at: Instant, last: &mut Option<Instant>) {
        self.states += 1;
        self.last_applied = v["state"]["applied"].as_u64().unwrap();
        if let Some(l) = *last {
            self.max_gap = self.max_gap.max(at - l);
        }
        *last = Some(at);
    }
}

async fn post(c: &reqwest::Client, url: &str, token: Option<&str>, body: &Value) -> Value {
    let mut req = c.post(url).json(body);
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    let resp = req.send().await.unwrap();
    let status = resp.status();
    let v: Value = resp.json().await.unwrap_or(Value::Null);
    assert!(status.is_success(), "POST {url}: {status}: {v}");
    v
}

/// What one run of a server round measured and returned.
struct Round {
    /// Wall time from the first post of the round until this run's end was answered [s].
    wall: f64,
    /// Of which the filter's steps [s].
    steps_s: f64,
    traj: Value,
    state: Value,
    heard: Heard,
    /// Requests refused as busy (503) and retried.
    busy: u64,
    /// Snapshots the run stored (at the robots' registrations, by `snapshot_every` records
    /// or `snapshot_every_work_ms` of stepping, and at the end).
    snapshots: usize,
}

/// A run created on the server, its robots' tokens and its listener.
struct Posting {
    run: String,
    tokens: Vec<(String, String)>,
    listener: tokio::task::JoinHandle<Heard>,
}

/// Creates a run for `log`, adds its robots and connects a websocket listener to its `live`
/// stream, which reads every message, as the dashboard does.
async fn create_run(
    c: &reqwest::Client,
    addr: std::net::SocketAddr,
    log: &Log,
    particles: usize,
    clients: &tokio::runtime::Handle,
) -> Posting {
    let base = format!("http://{addr}");
    let v = post(
        c,
        &format!("{base}/v1/runs"),
        None,
        &json!({"name": "server_overhead", "header": log.header,
                "config": {"particles": particles, "seed": 1}}),
    )
    .await;
    let run = v["id"].as_str().unwrap().to_string();
    let mut tokens = Vec::new();
    for r in &log.header.robots {
        let v = post(
            c,
            &format!("{base}/v1/runs/{run}/robots"),
            None,
            &json!({"id": r.id, "start": r.start, "t0": r.t0}),
        )
        .await;
        tokens.push((r.id.clone(), v["token"].as_str().unwrap().to_string()));
    }
    // Connected and read on the clients' runtime; posting starts once it is connected.
    let (connected, is_connected) = tokio::sync::oneshot::channel();
    let url = format!("ws://{addr}/v1/runs/{run}/live");
    let listener = clients.spawn(async move {
        let (mut ws, _) = tokio_tungstenite::connect_async(url).await.unwrap();
        connected.send(()).unwrap();
        let mut heard = Heard::default();
        let mut last = None;
        while let Some(Ok(msg)) = ws.next().await {
            // Pings and pongs carry no message.
            let Message::Text(text) = msg else { continue };
            let v: Value = serde_json::from_str(&text).unwrap();
            match v["type"].as_str() {
                Some("state") => heard.state(&v, Instant::now(), &mut last),
                Some("event") => {
                    heard.events += 1;
                    if v["event"]["event"] == "run_ended" {
                        // The final state follows within one tick; wait for it.
                        let deadline = tokio::time::sleep(Duration::from_secs(2));
                        tokio::pin!(deadline);
                        loop {
                            tokio::select! {
                                _ = &mut deadline => return heard,
                                m = ws.next() => {
                                    let Some(Ok(m)) = m else { return heard };
                                    let Message::Text(text) = m else { continue };
                                    let v: Value = serde_json::from_str(&text).unwrap();
                                    if v["type"] == "state" {
                                        // The run's end is not a gap between states.
                                        heard.state(&v, Instant::now(), &mut None);
                                        if v["state"]["status"] == "ended" {
                                            return heard;
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
                _ => {}
            }
        }
        heard
    });
    is_connected.await.unwrap();
    Posting {
        run,
        tokens,
        listener,
    }
}

/// Posts `log` to a run as its robots would (one client per robot, [`BATCH`] records per
/// request), ends the run and returns the seconds from `started` until the end is answered
/// and the number of requests retried after 503.
async fn post_run(
    c: reqwest::Client,
    base: String,
    log: Arc<Log>,
    run: String,
    tokens: Vec<(String, String)>,
    batch: usize,
    started: Instant,
) -> (f64, u64) {
    let busy = Arc::new(AtomicU64::new(0));
    let mut clients = Vec::new();
    for (robot, token) in tokens {
        let records: Vec<Record> = log
            .records
            .iter()
            .filter(|r| r.robot == robot)
            .cloned()
            .collect();
        let (c, url, busy) = (
            c.clone(),
            format!("{base}/v1/runs/{run}/observations"),
            busy.clone(),
        );
        clients.push(tokio::spawn(async move {
            for chunk in records.chunks(batch) {
                loop {
                    let resp = c
                        .post(&url)
                        .bearer_auth(&token)
                        .json(chunk)
                        .send()
                        .await
                        .unwrap();
                    if resp.status() == reqwest::StatusCode::SERVICE_UNAVAILABLE {
                        busy.fetch_add(1, Ordering::Relaxed);
                        tokio::time::sleep(Duration::from_millis(20)).await;
                        continue;
                    }
                    let status = resp.status();
                    let v: Value = resp.json().await.unwrap();
                    assert_eq!(status, reqwest::StatusCode::OK, "robot {robot}: {v}");
                    break;
                }
            }
        }));
    }
    for t in clients {
        t.await.unwrap();
    }
    let resp = c
        .post(format!("{base}/v1/runs/{run}/end"))
        .send()
        .await
        .unwrap();
    assert!(resp.status().is_success(), "{}", resp.status());
    (
        started.elapsed().as_secs_f64(),
        busy.load(Ordering::Relaxed),
    )
}

/// One server round: `runs` runs of the same log on one server, posted at the same time.
/// Also returns each thread's CPU time ([`thread_cpu_s`]) when the last run ended, before
/// the server stops.
async fn server_round(
    log: &Arc<Log>,
    particles: usize,
    batch: usize,
    runs: usize,
    clients: &tokio::runtime::Handle,
) -> (Vec<Round>, std::collections::BTreeMap<u64, (String, f64)>) {
    let dir = tempfile::tempdir().unwrap();
    // The defaults under the server's own `FLEETSLAM_<FIELD>` variables (e.g.
    // `FLEETSLAM_SNAPSHOT_EVERY`), as `fleetslam serve` reads them.
    let config = ServerConfig::load(
        None,
        json!({ "bind": "127.0.0.1:0", "data_dir": dir.path() }),
    )
    .unwrap();
    config.validate().unwrap();
    let running = fleetslam_server::server::start(&config).await.unwrap();
    let base = format!("http://{}", running.addr);
    let c = reqwest::Client::new();
    let mut postings = Vec::new();
    for _ in 0..runs {
        postings.push(create_run(&c, running.addr, log, particles, clients).await);
    }
    let started = Instant::now();
    let posters: Vec<_> = postings
        .iter()
        .map(|p| {
            clients.spawn(post_run(
                c.clone(),
                base.clone(),
                log.clone(),
                p.run.clone(),
                p.tokens.clone(),
                batch,
                started,
            ))
        })
        .collect();
    let mut rounds = Vec::new();
    for (p, poster) in postings.into_iter().zip(posters) {
        let (wall, busy) = poster.await.unwrap();
        let heard = tokio::time::timeout(Duration::from_secs(10), p.listener)
            .await
            .expect("the websocket listener heard the run end")
            .unwrap();
        let get = |path: String| {
            let c = c.clone();
            async move {
                c.get(path)
                    .send()
                    .await
                    .unwrap()
                    .json::<Value>()
                    .await
                    .unwrap()
            }
        };
        let run = &p.run;
        let traj = get(format!("{base}/v1/runs/{run}/trajectories")).await;
        let state = get(format!("{base}/v1/runs/{run}/state")).await;
        // The time the filter spent in its steps, from the run's stored metrics.
        let result: Value = serde_json::from_str(
            &running
                .store
                .get_artifact(run, fleetslam_server::history::RESULT)
                .await
                .unwrap()
                .expect("an ended run has its result"),
        )
        .unwrap();
        let steps_s = result["metrics"]["step_ms_mean"].as_f64().unwrap()
            * result["metrics"]["applied"].as_f64().unwrap()
            / 1e3;
        let snapshots = running.store.snapshot_index(run).await.unwrap().len();
        rounds.push(Round {
            wall,
            steps_s,
            traj,
            state,
            heard,
            busy,
            snapshots,
        });
    }
    let threads = thread_cpu_s();
    running.stop().await.unwrap();
    (rounds, threads)
}

/// A `stat` line of `/proc` (a process's or a thread's): its command name and the CPU time
/// it used, user and system [s] (fields 14 and 15, in the kernel's clock ticks of 1/100 s).
fn parse_stat(stat: &str) -> Option<(String, f64)> {
    // The name is in parentheses and may hold spaces and parentheses itself.
    let open = stat.find('(')?;
    let (head, rest) = stat.rsplit_once(')')?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    // Field 3 is the first after the name.
    let ticks = |field: usize| f.get(field - 3)?.parse::<f64>().ok();
    Some((
        head.get(open + 1..)?.to_string(),
        (ticks(14)? + ticks(15)?) / 100.0,
    ))
}

/// CPU time this process has used so far, over all its threads [s]; `NaN` where there is
/// no `/proc`.
fn process_cpu_s() -> f64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| parse_stat(&s))
        .map_or(f64::NAN, |(_, cpu)| cpu)
}

/// CPU time [s] of each live thread of this process by thread id, with its name
/// (`/proc/self/task/*/stat`); empty where there is no `/proc`.
fn thread_cpu_s() -> std::collections::BTreeMap<u64, (String, f64)> {
    let mut out = std::collections::BTreeMap::new();
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return out;
    };
    for e in dir.flatten() {
        let Ok(tid) = e.file_name().to_string_lossy().parse::<u64>() else {
            continue;
        };
        let stat = std::fs::read_to_string(e.path().join("stat")).unwrap_or_default();
        if let Some(named) = parse_stat(&stat) {
            out.insert(tid, named);
        }
    }
    out
}

/// The CPU time threads used between two [`thread_cpu_s`] readings, summed by thread name
/// (a thread born after `before` counts whole; one that ended before `after` is missing).
fn cpu_by_name(
    before: &std::collections::BTreeMap<u64, (String, f64)>,
    after: &std::collections::BTreeMap<u64, (String, f64)>,
) -> String {
    let mut by: std::collections::BTreeMap<&str, f64> = std::collections::BTreeMap::new();
    for (tid, (name, cpu)) in after {
        let was = before.get(tid).map_or(0.0, |b| b.1);
        *by.entry(name.as_str()).or_default() += cpu - was;
    }
    by.iter()
        .filter(|(_, s)| **s > 0.0)
        .map(|(n, s)| format!("{n} {s:.2} s"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn offline_round(log: &Log, particles: usize) -> (f64, RunOutput) {
    let mut cfg = FilterConfig::from_header(&log.header);
    cfg.particles = particles;
    cfg.seed = 1;
    let mut slam = FastSlam::new(cfg).unwrap();
    let started = Instant::now();
    let out = run_log(&mut slam, log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    (started.elapsed().as_secs_f64(), out)
}

/// Panics unless the server's trajectories and landmarks are the offline run's, bit for bit.
fn check_identical(out: &RunOutput, traj: &Value, state: &Value) {
    for (robot, pts) in &out.estimate.trajectories {
        let offline: Vec<[f64; 4]> = pts
            .iter()
            .map(|p| [p.t, p.pose.x, p.pose.y, p.pose.theta])
            .collect();
        assert_eq!(
            traj["robots"][robot],
            json!(offline),
            "robot {robot}'s trajectory differs from the offline run's"
        );
    }
    let offline: Vec<Value> = out
        .final_estimate
        .landmarks
        .iter()
        .map(|l| json!({"mean": l.gaussian.mean, "cov": l.gaussian.cov}))
        .collect();
    let server: Vec<Value> = state["landmarks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| json!({"mean": l["mean"], "cov": l["cov"]}))
        .collect();
    assert_eq!(
        server, offline,
        "the landmarks differ from the offline run's"
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let usage =
        "usage: server_overhead MRCLAM_DIR|LOG [PARTICLES] [ROUNDS] [DURATION_S|all] [RUNS]";
    let path = std::path::Path::new(args.get(1).expect(usage));
    let particles: usize = args.get(2).map_or(1000, |p| p.parse().expect(usage));
    let rounds: usize = args.get(3).map_or(3, |p| p.parse().expect(usage));
    let duration: Option<f64> = args
        .get(4)
        .filter(|d| d.as_str() != "all")
        .map(|p| p.parse().expect(usage));
    let runs: usize = args.get(5).map_or(1, |p| p.parse().expect(usage));
    assert!(runs >= 1, "{usage}");
    let batch = BATCH;
    let mut log = if path.is_dir() {
        let opts = MrclamOptions {
            duration,
            ..MrclamOptions::default()
        };
        import_mrclam(path, &opts).unwrap().log
    } else {
        Log::read_path(path).unwrap()
    };
    log.sort();
    let log = Arc::new(log);
    let n = log.records.len();
    println!(
        "{n} records, {} robots, {particles} particles, seed 1, {batch} records per request, \
         {runs} run(s) at once, {} cores",
        log.header.robots.len(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    // Named, so that the CPU time by thread tells the filter's workers apart.
    rayon::ThreadPoolBuilder::new()
        .thread_name(|i| format!("rayon-{i}"))
        .build_global()
        .unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    // The robots' clients and the websocket listener run on a runtime of their own, so that
    // the CPU time by thread tells the server's (`tokio-rt-worker`) from theirs
    // (`clients-rt`): on a deployment they run on the robots and the dashboard's machine.
    // Both runtimes share this machine's cores, as before.
    let clients = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("clients-rt")
        .enable_all()
        .build()
        .unwrap();
    let mut ratios = Vec::new();
    for round in 1..=rounds {
        let cpu0 = process_cpu_s();
        let (offline_s, out) = offline_round(&log, particles);
        let cpu1 = process_cpu_s();
        let threads1 = thread_cpu_s();
        let started = Instant::now();
        let (rs, threads2) =
            rt.block_on(server_round(&log, particles, batch, runs, clients.handle()));
        let all_s = started.elapsed().as_secs_f64();
        let cpu2 = process_cpu_s();
        // CPU time against wall time: how much of the cores each side kept busy (the
        // server's includes its set-up, its clients and its listener, all in this process).
        println!(
            "round {round}: CPU time offline {:.2} s in {offline_s:.2} s, server {:.2} s in \
             {all_s:.2} s (with set-up); server by thread: {}",
            cpu1 - cpu0,
            cpu2 - cpu1,
            cpu_by_name(&threads1, &threads2)
        );
        for (k, r) in rs.iter().enumerate() {
            assert_eq!(r.state["applied"].as_u64(), Some(n as u64), "{}", r.state);
            check_identical(&out, &r.traj, &r.state);
            assert!(
                r.heard.states > 0,
                "the websocket listener received no state"
            );
            assert_eq!(
                r.heard.last_applied, n as u64,
                "the websocket listener did not receive the final state"
            );
            let ratio = r.wall / (offline_s * runs as f64);
            if runs == 1 {
                ratios.push(ratio);
            }
            println!(
                "round {round}{}: offline {offline_s:.2} s, server {:.2} s (filter steps {:.2} s, \
                 {} snapshots), ratio {ratio:.3} (identical; listener: {} states, longest gap \
                 {:.0} ms, {} events; {} requests retried after 503)",
                if runs > 1 {
                    format!(" run {}", k + 1)
                } else {
                    String::new()
                },
                r.wall,
                r.steps_s,
                r.snapshots,
                r.heard.states,
                r.heard.max_gap.as_secs_f64() * 1e3,
                r.heard.events,
                r.busy
            );
        }
        if runs > 1 {
            // All runs posted at once: the server's time for all of them against the offline
            // time of as many runs one after another.
            let last = rs.iter().map(|r| r.wall).fold(0.0, f64::max);
            let ratio = last / (offline_s * runs as f64);
            ratios.push(ratio);
            println!(
                "round {round}: {runs} runs in {last:.2} s (round with set-up {all_s:.2} s) \
                 against {runs} x offline {offline_s:.2} s: ratio {ratio:.3}"
            );
        }
    }
    ratios.sort_by(f64::total_cmp);
    println!(
        "median ratio {:.3} over {rounds} rounds (min {:.3}, max {:.3})",
        ratios[ratios.len() / 2],
        ratios[0],
        ratios[ratios.len() - 1]
    );
}
