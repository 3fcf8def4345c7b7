//! The dashboard (`web/`) end to end in headless Chromium: a real server on 127.0.0.1:0, a
//! real run from a slice of MRCLAM Dataset 6 (or a simulated log when the data set is not
//! beside the checkout), robots posting over HTTP, and the page driven over WebDriver
//! (`/usr/bin/chromedriver`, Debian's `chromium-driver`).
//!
//! Checks: the pages load without script or console errors; the history lists the runs; a
//! finished run's map shows the server's number of landmarks and robots; scrubbing the
//! timeline changes the shown time; the live view follows a run over the websocket as its
//! robots post, and turns into the stored view when the run ends; the comparison shows both
//! runs; the layout fits a phone in landscape. Screenshots go to
//! `$CARGO_TARGET_TMPDIR/dashboard/`; with `FLEETSLAM_UPDATE_SCREENSHOT=1` the run view is
//! also written to `docs/dashboard.png` for the README.
//!
//! Without Chromium the test prints a loud notice and passes, unless
//! `FLEETSLAM_REQUIRE_BROWSER=1` (set by `.ci/run`), which makes it fail.
//! Run with `cargo test -p fleetslam-server --test dashboard -- --nocapture`.

use fleetslam_core::log::{Log, Record};
use fleetslam_server::config::ServerConfig;
use fleetslam_server::server::{Running, start};
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const CHROMEDRIVER: &str = "/usr/bin/chromedriver";
const CHROMIUM: &str = "/usr/bin/chromium";
const DATASETS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/datasets");
/// Seconds of MRCLAM Dataset 6 replayed (from the earliest start).
const SLICE_S: f64 = 120.0;
/// Particles of the test runs: enough for a sensible map, few enough for a debug build.
const PARTICLES: usize = 100;
/// The server's websocket heartbeat period [ms] (short, so that a silent network is noticed
/// within the test).
const HEARTBEAT_MS: u64 = 400;

type BoxError = Box<dyn std::error::Error + Send + Sync>;
type Res<T> = Result<T, BoxError>;

fn env_path(var: &str, default: &str) -> PathBuf {
    std::env::var_os(var).map_or_else(|| PathBuf::from(default), PathBuf::from)
}

/// The test's log and its ground truth (as `PUT /v1/runs/{run}/truth` takes it): a slice of
/// real data when present, else a small simulated one.
fn test_log() -> (Log, Value, String) {
    let dir = Path::new(DATASETS).join("mrclam-dataset6");
    if dir.is_dir() {
        let opts = fleetslam_data::import::MrclamOptions {
            duration: Some(SLICE_S),
            odometry_delay: 0.15,
            ..Default::default()
        };
        let imp = fleetslam_data::import::import_mrclam(&dir, &opts).expect("import MRCLAM");
        let mut log = imp.log;
        log.sort();
        let truth = truth_json(&imp.truth);
        (
            log,
            truth,
            format!("MRCLAM Dataset 6, first {SLICE_S:.0} s"),
        )
    } else {
        println!(
            "NOTE: {} is missing; the dashboard test uses a simulated log",
            dir.display()
        );
        let sim = fleetslam_data::sim::simulate(&fleetslam_data::sim::SimConfig {
            robots: 3,
            duration: 40.0,
            seed: 3,
            ..Default::default()
        })
        .expect("simulate");
        let mut log = sim.log;
        log.sort();
        let truth = truth_json(&sim.truth);
        (log, truth, "simulated, 3 robots, 40 s".into())
    }
}

/// Robots of the scale run.
const SCALE_ROBOTS: usize = 10;
/// Landmarks the scale run's map must hold while the page is measured.
const SCALE_MAP: usize = 5000;
/// Particles of the scale run (the page's cost does not depend on them).
const SCALE_PARTICLES: usize = 20;
/// Data time posted in real time while the page is measured [s].
const SCALE_MEASURED_S: f64 = 6.0;

/// The scale run's log: 10 robots sweeping an arena dense with landmarks (about 90 in view
/// per record), long enough for the map to hold more than [`SCALE_MAP`] landmarks before the
/// measured part (offline with these particles and seed: 4,926 landmarks after 70 s, 5,180
/// after 90 s, 5,394 after 110 s).
fn scale_log() -> (Log, Value) {
    let sim = fleetslam_data::sim::simulate(&fleetslam_data::sim::SimConfig {
        robots: SCALE_ROBOTS,
        landmarks: 6000,
        arena: [60.0, 60.0],
        speed: 1.0,
        duration: 110.0,
        seed: 5,
        ..Default::default()
    })
    .expect("simulate");
    let mut log = sim.log;
    log.sort();
    (log, truth_json(&sim.truth))
}

fn truth_json(truth: &fleetslam_data::formats::Truth) -> Value {
    let robots: serde_json::Map<String, Value> = truth
        .trajectories
        .iter()
        .map(|(id, pts)| {
            let pts: Vec<[f64; 4]> = pts
                .iter()
                .map(|p| [p.t, p.pose.x, p.pose.y, p.pose.theta])
                .collect();
            (id.clone(), json!(pts))
        })
        .collect();
    let landmarks: Vec<Value> = truth
        .landmarks
        .iter()
        .map(|l| json!({"id": l.id, "x": l.mean[0], "y": l.mean[1]}))
        .collect();
    json!({"robots": robots, "landmarks": landmarks})
}

// --- the server side ---------------------------------------------------------------------

struct Server {
    running: Option<Running>,
    base: String,
    http: reqwest::Client,
    _dir: tempfile::TempDir,
}

impl Server {
    async fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let cfg = ServerConfig {
            bind: "127.0.0.1:0".into(),
            data_dir: dir.path().to_path_buf(),
            ws_heartbeat_ms: HEARTBEAT_MS,
            max_landmarks_per_record: 2000,
            ..ServerConfig::default()
        };
        let running = start(&cfg).await.expect("server starts");
        let base = format!("http://{}", running.addr);
        Self {
            running: Some(running),
            base,
            http: reqwest::Client::new(),
            _dir: dir,
        }
    }

    async fn send(&self, req: reqwest::RequestBuilder, expect: u16) -> Value {
        let resp = req.send().await.expect("request");
        let status = resp.status().as_u16();
        let text = resp.text().await.unwrap_or_default();
        assert_eq!(status, expect, "unexpected answer: {text}");
        serde_json::from_str(&text).unwrap_or(Value::Null)
    }

    /// Creates a run from the log's header and registers its robots; returns (run, tokens).
    /// Creates a run from the log's header (with `config` over it), uploads its ground truth
    /// and registers its robots; returns (run, tokens).
    async fn create_run(
        &self,
        log: &Log,
        truth: &Value,
        name: &str,
        config: Value,
    ) -> (String, Vec<(String, String)>) {
        let v = self
            .send(
                self.http
                    .post(format!("{}/v1/runs", self.base))
                    .json(&json!({
                        "name": name,
                        "header": log.header,
                        "config": config,
                    })),
                201,
            )
            .await;
        let run = v["id"].as_str().unwrap().to_string();
        self.send(
            self.http
                .put(format!("{}/v1/runs/{run}/truth", self.base))
                .json(truth),
            204,
        )
        .await;
        let mut tokens = Vec::new();
        for r in &log.header.robots {
            let v = self
                .send(
                    self.http
                        .post(format!("{}/v1/runs/{run}/robots", self.base))
                        .json(&json!({"id": r.id, "start": r.start, "t0": r.t0})),
                    201,
                )
                .await;
            tokens.push((r.id.clone(), v["token"].as_str().unwrap().to_string()));
        }
        (run, tokens)
    }

    /// Posts `records` as k concurrent robot clients (one per robot, each with its token).
    async fn post(&self, run: &str, tokens: &[(String, String)], records: &[Record]) {
        let mut tasks = Vec::new();
        for (robot, token) in tokens {
            let mine: Vec<Record> = records
                .iter()
                .filter(|r| &r.robot == robot)
                .cloned()
                .collect();
            let http = self.http.clone();
            let url = format!("{}/v1/runs/{run}/observations", self.base);
            let token = token.clone();
            tasks.push(tokio::spawn(async move {
                for chunk in mine.chunks(50) {
                    let resp = http
                        .post(&url)
                        .bearer_auth(&token)
                        .json(chunk)
                        .send()
                        .await
                        .expect("post");
                    let status = resp.status();
                    assert!(
                        status.is_success(),
                        "{status}: {}",
                        resp.text().await.unwrap()
                    );
                }
            }));
        }
        for t in tasks {
            t.await.unwrap();
        }
    }

    /// The run's applied count once it has not changed for longer than the reorder window.
    async fn settled_applied(&self, run: &str) -> u64 {
        let mut last = (u64::MAX, Instant::now());
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let applied = self.get(&format!("/v1/runs/{run}/state")).await["applied"]
                .as_u64()
                .unwrap();
            if applied != last.0 {
                last = (applied, Instant::now());
            } else if last.1.elapsed() > Duration::from_millis(2500) {
                return applied;
            }
            assert!(Instant::now() < deadline, "run {run} never settled");
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// Posts `records` one robot's run of consecutive records at a time, in time order: after
    /// a pause longer than the reorder window (the robots fall silent and stop holding each
    /// other back) concurrent clients could be refused as too late, sequential ones cannot.
    async fn post_in_order(&self, run: &str, tokens: &[(String, String)], records: &[Record]) {
        let url = format!("{}/v1/runs/{run}/observations", self.base);
        for chunk in records.chunk_by(|a, b| a.robot == b.robot) {
            let token = &tokens.iter().find(|(r, _)| r == &chunk[0].robot).unwrap().1;
            self.send(self.http.post(&url).bearer_auth(token).json(chunk), 200)
                .await;
        }
    }

    async fn end(&self, run: &str) {
        self.send(
            self.http.post(format!("{}/v1/runs/{run}/end", self.base)),
            204,
        )
        .await;
    }

    async fn get(&self, path: &str) -> Value {
        self.send(self.http.get(format!("{}{path}", self.base)), 200)
            .await
    }

    /// The number of landmarks and robots of an ended run's final state, as the server
    /// reports it (its final state, or the stored summary).
    async fn final_counts(&self, run: &str) -> (usize, usize) {
        let resp = self
            .http
            .get(format!("{}/v1/runs/{run}/state", self.base))
            .send()
            .await
            .unwrap();
        if resp.status().is_success() {
            let s: Value = resp.json().await.unwrap();
            if let (Some(l), Some(r)) = (s["landmarks"].as_array(), s["robots"].as_array()) {
                return (l.len(), r.len());
            }
        }
        let v = self.get(&format!("/v1/runs/{run}")).await;
        let s = &v["run"]["summary"];
        let count = |v: &Value| {
            v.as_array()
                .map(Vec::len)
                .or(v.as_u64().map(|n| n as usize))
                .expect("summary counts")
        };
        (count(&s["landmarks"]), count(&s["robots"]))
    }
}

/// A TCP proxy in front of the server that can drop every connection through it at once (a
/// network drop for the browser), while it keeps accepting new ones.
struct Proxy {
    addr: std::net::SocketAddr,
    conns: Arc<Mutex<Vec<tokio::task::AbortHandle>>>,
    /// While set, bytes are held in both directions and connections stay open: a network
    /// that went away without a reset.
    stalled: Arc<std::sync::atomic::AtomicBool>,
    task: tokio::task::JoinHandle<()>,
}

/// Copies `from` to `to`, holding each piece while `stalled` is set.
async fn pump(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    stalled: Arc<std::sync::atomic::AtomicBool>,
) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = match from.read(&mut buf).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        while stalled.load(std::sync::atomic::Ordering::Relaxed) {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        if to.write_all(&buf[..n]).await.is_err() {
            return;
        }
    }
}

impl Proxy {
    async fn start(target: std::net::SocketAddr) -> Self {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let conns: Arc<Mutex<Vec<tokio::task::AbortHandle>>> = Arc::default();
        let stalled: Arc<std::sync::atomic::AtomicBool> = Arc::default();
        let (registry, held) = (conns.clone(), stalled.clone());
        let task = tokio::spawn(async move {
            while let Ok((inbound, _)) = listener.accept().await {
                let held = held.clone();
                let conn = tokio::spawn(async move {
                    if let Ok(outbound) = tokio::net::TcpStream::connect(target).await {
                        let (ir, iw) = inbound.into_split();
                        let (or, ow) = outbound.into_split();
                        tokio::select! {
                            () = pump(ir, ow, held.clone()) => {}
                            () = pump(or, iw, held) => {}
                        }
                    }
                });
                registry.lock().unwrap().push(conn.abort_handle());
            }
        });
        Self {
            addr,
            conns,
            stalled,
            task,
        }
    }

    /// Holds (true) or lets through (false) every byte, without closing anything.
    fn stall(&self, on: bool) {
        self.stalled.store(on, std::sync::atomic::Ordering::Relaxed);
    }

    /// Closes every connection under way (the websocket included).
    fn drop_connections(&self) {
        for c in self.conns.lock().unwrap().drain(..) {
            c.abort();
        }
    }
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.drop_connections();
        self.task.abort();
    }
}

// --- the browser: chromedriver, driven through fantoccini --------------------------------

/// chromedriver, stopped on drop.
struct Driver {
    child: Child,
    base: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Driver {
    async fn start(path: &Path) -> Res<Self> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        let child = Command::new(path)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("starting {}: {e}", path.display()))?;
        let driver = Self {
            child,
            base: format!("http://127.0.0.1:{port}"),
        };
        let http = reqwest::Client::new();
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if let Ok(r) = http.get(format!("{}/status", driver.base)).send().await
                && r.status().is_success()
            {
                return Ok(driver);
            }
            if Instant::now() > deadline {
                return Err("chromedriver did not become ready within 20 s".into());
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
}

/// A WebDriver command that fantoccini has no method for (Chrome's DevTools bridge, the
/// browser log): `method` on `session/<id>/<path>` with a JSON body.
#[derive(Debug)]
struct Raw {
    method: http::Method,
    path: &'static str,
    body: Value,
}

impl fantoccini::wd::WebDriverCompatibleCommand for Raw {
    fn endpoint(
        &self,
        base_url: &url::Url,
        session_id: Option<&str>,
    ) -> Result<url::Url, url::ParseError> {
        base_url.join(&format!(
            "session/{}/{}",
            session_id.unwrap_or_default(),
            self.path
        ))
    }

    fn method_and_body(&self, _: &url::Url) -> (http::Method, Option<String>) {
        (self.method.clone(), Some(self.body.to_string()))
    }
}

/// One browser session, driven through fantoccini.
struct Browser {
    client: fantoccini::Client,
    _profile: tempfile::TempDir,
}

impl Browser {
    async fn new(driver: &Driver, chromium: &Path) -> Res<Self> {
        let profile = tempfile::tempdir()?;
        // The flags keep Chromium off the network (this machine has none) and quiet.
        let args = [
            "--headless=new".to_string(),
            "--no-sandbox".into(),
            "--disable-gpu".into(),
            "--disable-dev-shm-usage".into(),
            "--disable-quic".into(),
            "--no-first-run".into(),
            "--disable-background-networking".into(),
            "--disable-component-update".into(),
            "--disable-sync".into(),
            "--disable-extensions".into(),
            "--hide-scrollbars".into(),
            "--force-device-scale-factor=1".into(),
            "--window-size=1440,900".into(),
            format!("--user-data-dir={}", profile.path().display()),
        ];
        let caps: fantoccini::wd::Capabilities = serde_json::from_value(json!({
            "browserName": "chrome",
            "goog:chromeOptions": {"binary": chromium, "args": args},
            "goog:loggingPrefs": {"browser": "ALL"},
        }))?;
        // chromedriver speaks plain HTTP on loopback: no TLS connector.
        let connector = hyper_util::client::legacy::connect::HttpConnector::new();
        let client = fantoccini::ClientBuilder::new(connector)
            .capabilities(caps)
            .connect(&driver.base)
            .await
            .map_err(|e| format!("no session from chromedriver: {e}"))?;
        Ok(Self {
            client,
            _profile: profile,
        })
    }

    async fn raw(&self, method: http::Method, path: &'static str, body: Value) -> Res<Value> {
        Ok(self.client.issue_cmd(Raw { method, path, body }).await?)
    }

    async fn goto(&self, url: &str) -> Res<()> {
        Ok(self.client.goto(url).await?)
    }

    /// Runs `script` (a function body; `return` gives the value) in the page.
    async fn js(&self, script: &str) -> Res<Value> {
        Ok(self.client.execute(script, Vec::new()).await?)
    }

    /// Polls `script` until it returns something truthy; returns that value.
    async fn wait_for(&self, what: &str, script: &str, timeout: Duration) -> Value {
        let deadline = Instant::now() + timeout;
        let mut last: Value;
        loop {
            match self.js(script).await {
                Ok(v) if !(v.is_null() || v == false || v == "" || v == 0) => return v,
                Ok(v) => last = v,
                Err(e) => last = Value::String(e.to_string()),
            }
            if Instant::now() > deadline {
                let errors = self.page_errors().await;
                panic!("timed out waiting for {what} (last: {last}); page errors: {errors:?}");
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// The status element's data attributes.
    async fn status(&self) -> Value {
        self.js("return Object.assign({}, document.getElementById('status')?.dataset || {});")
            .await
            .unwrap_or(Value::Null)
    }

    /// Emulates a phone's viewport (width x height CSS pixels, touch) through the DevTools
    /// protocol: a headless window's size includes browser chrome that a phone does not have.
    async fn emulate_phone(&self, width: u32, height: u32) -> Res<()> {
        self.raw(
            http::Method::POST,
            "goog/cdp/execute",
            json!({"cmd": "Emulation.setDeviceMetricsOverride", "params": {
                "width": width, "height": height, "deviceScaleFactor": 1, "mobile": true,
                "screenOrientation": {"type": "landscapePrimary", "angle": 90},
            }}),
        )
        .await?;
        self.raw(
            http::Method::POST,
            "goog/cdp/execute",
            json!({"cmd": "Emulation.setTouchEmulationEnabled", "params": {"enabled": true}}),
        )
        .await?;
        Ok(())
    }

    async fn screenshot(&self, path: &Path) -> Res<()> {
        let png = self.client.screenshot().await?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(path, png)?;
        println!("screenshot: {}", path.display());
        Ok(())
    }

    /// Errors the page's own hook collected (script errors, unhandled rejections,
    /// console.error) and severe entries of the browser's console log, except failed loads
    /// of the optional per-run endpoints (a 404 or 409 there means "this run has none", which
    /// the page handles by hiding that part).
    async fn page_errors(&self) -> Vec<String> {
        let mut out: Vec<String> = match self.js("return window.__fleetslamErrors || null;").await {
            Ok(Value::Array(v)) => v.iter().map(|e| e.to_string()).collect(),
            Ok(_) => vec!["the page's error hook (js/errors.js) is not installed".into()],
            Err(e) => vec![format!("reading the page's errors: {e}")],
        };
        let log = self
            .raw(http::Method::POST, "se/log", json!({"type": "browser"}))
            .await;
        let entries = match log {
            Ok(Value::Array(entries)) => entries,
            other => {
                println!("NOTE: the browser's console log is not available: {other:?}");
                Vec::new()
            }
        };
        {
            for e in entries {
                let level = e["level"].as_str().unwrap_or("");
                let msg = e["message"].as_str().unwrap_or("").to_string();
                let optional = (msg.contains("status of 404") || msg.contains("status of 409"))
                    && [
                        "/state",
                        "/timeline",
                        "/trajectories",
                        "/truth",
                        "/evaluation",
                    ]
                    .iter()
                    .any(|p| msg.contains(&format!("{p} ")) || msg.contains(&format!("{p}?")));
                if level == "SEVERE" && !optional {
                    out.push(format!("console: {msg}"));
                } else if level == "SEVERE" || level == "WARNING" {
                    println!("console ({level}, allowed): {msg}");
                }
            }
        }
        out
    }

    async fn quit(self) {
        let _ = self.client.close().await;
    }
}

async fn assert_no_errors(browser: &Browser, stage: &str) {
    let errors = browser.page_errors().await;
    assert!(
        errors.is_empty(),
        "the page reported errors ({stage}): {errors:#?}"
    );
}

fn artifacts() -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("dashboard")
}

// --- the test ------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_in_headless_chromium() {
    let driver_path = env_path("FLEETSLAM_CHROMEDRIVER", CHROMEDRIVER);
    let chromium = env_path("FLEETSLAM_CHROMIUM", CHROMIUM);
    if !driver_path.exists() || !chromium.exists() {
        let msg = format!(
            "the dashboard browser test needs Chromium and ChromeDriver ({} and {}); install \
             them with `apt-get install -y chromium chromium-driver`",
            chromium.display(),
            driver_path.display()
        );
        if std::env::var("FLEETSLAM_REQUIRE_BROWSER").is_ok_and(|v| v == "1") {
            panic!("{msg} (FLEETSLAM_REQUIRE_BROWSER=1)");
        }
        eprintln!("\n{}\nSKIPPED: {msg}\n{}\n", "!".repeat(78), "!".repeat(78));
        return;
    }
    let started = Instant::now();
    let (log, truth, what) = test_log();
    let robots = log.header.robots.len();
    let server = Server::start().await;
    let driver = Driver::start(&driver_path)
        .await
        .expect("chromedriver starts");
    let browser = Browser::new(&driver, &chromium)
        .await
        .expect("a Chromium session");
    // The browser goes through a proxy that can drop its connections.
    let proxy = Proxy::start(server.running.as_ref().unwrap().addr).await;
    let base = format!("http://{}", proxy.addr);
    let shots = artifacts();
    println!("data: {what}, {} records; server {base}", log.records.len());

    // A stored run: the whole slice, posted by k concurrent robot clients, then ended.
    let (stored, tokens) = server
        .create_run(
            &log,
            &truth,
            &format!("{what}, FastSLAM 2.0"),
            json!({"particles": PARTICLES, "seed": 1}),
        )
        .await;
    server.post(&stored, &tokens, &log.records).await;
    server.end(&stored).await;
    let (landmarks, state_robots) = server.final_counts(&stored).await;
    assert!(landmarks > 0, "the run mapped no landmark");
    assert_eq!(state_robots, robots);
    println!(
        "stored run {stored}: {landmarks} landmarks, {robots} robots ({:.1} s)",
        started.elapsed().as_secs_f64()
    );

    // A live run: the page opens before any data, then follows the posts over the websocket.
    let (live, live_tokens) = server
        .create_run(
            &log,
            &truth,
            &format!("{what}, FastSLAM 1.0"),
            json!({"particles": PARTICLES, "seed": 1, "version": "1"}),
        )
        .await;
    browser.goto(&format!("{base}/#/run/{live}")).await.unwrap();
    browser
        .wait_for(
            "the live websocket",
            "return document.getElementById('status')?.dataset.ws === 'open';",
            Duration::from_secs(10),
        )
        .await;
    let t_mid = log.records[log.records.len() / 2].t;
    let (first, second): (Vec<Record>, Vec<Record>) =
        log.records.iter().cloned().partition(|r| r.t < t_mid);
    server.post(&live, &live_tokens, &first).await;
    // Once the server has applied all it will of the first half (the merge releases the
    // last records after the reorder window), the page shows the same count.
    let applied_1 = server.settled_applied(&live).await;
    browser
        .wait_for(
            "the live map to catch up with the server",
            &format!(
                "const d = document.getElementById('status').dataset; \
                 return Number(d.landmarks) > 0 && Number(d.applied) === {applied_1};"
            ),
            Duration::from_secs(10),
        )
        .await;
    let shown_robots = browser.status().await["robots"].clone();
    assert_eq!(shown_robots, robots.to_string(), "robots on the live map");
    browser
        .wait_for(
            "events in the live list",
            "return document.querySelectorAll('[data-testid=events] li').length;",
            Duration::from_secs(5),
        )
        .await;
    // The network drops: the page says so, then reconnects by itself.
    proxy.drop_connections();
    let banner = browser
        .wait_for(
            "the page to say the live connection is lost",
            "const b = document.querySelector('[data-testid=ws-banner]'); \
             return b && !b.hidden && /lost/.test(b.textContent) ? b.textContent : null;",
            Duration::from_secs(10),
        )
        .await;
    println!("after the drop: {banner}");
    browser
        .screenshot(&shots.join("live-dropped.png"))
        .await
        .unwrap();
    browser
        .wait_for(
            "the live view to reconnect",
            "const d = document.getElementById('status').dataset; \
             const ev = [...document.querySelectorAll('[data-testid=events] li')] \
               .some(li => /restored/.test(li.textContent)); \
             return d.ws === 'open' && ev;",
            Duration::from_secs(15),
        )
        .await;
    // The network goes silent without a reset: only the heartbeat can tell. The page says
    // the connection is lost within three heartbeat periods, and comes back when the network
    // does.
    proxy.stall(true);
    let stalled_at = Instant::now();
    browser
        .wait_for(
            "the page to notice a silent connection",
            "const b = document.querySelector('[data-testid=ws-banner]'); \
             return b && !b.hidden && /lost/.test(b.textContent) ? b.textContent : null;",
            Duration::from_secs(10),
        )
        .await;
    let noticed = stalled_at.elapsed();
    println!("a silent connection noticed after {noticed:?}");
    // Three periods after the last message heard, which came at most a period before.
    assert!(
        noticed >= Duration::from_millis(2 * HEARTBEAT_MS),
        "lost after {noticed:?}, before three heartbeats: something else closed it"
    );
    proxy.stall(false);
    browser
        .wait_for(
            "the live view to reconnect after the silence",
            "const d = document.getElementById('status').dataset; \
             const n = [...document.querySelectorAll('[data-testid=events] li')] \
               .filter(li => /restored/.test(li.textContent)).length; \
             return d.ws === 'open' && n >= 2;",
            Duration::from_secs(15),
        )
        .await;
    server.post_in_order(&live, &live_tokens, &second).await;
    browser
        .wait_for(
            "the live map to move on",
            &format!(
                "return Number(document.getElementById('status').dataset.applied) > {applied_1};"
            ),
            Duration::from_secs(20),
        )
        .await;
    browser.screenshot(&shots.join("live.png")).await.unwrap();
    assert_no_errors(&browser, "live view").await;

    // The live run opened again mid-way: data time counts from the run's start, and the
    // charts hold the run's history from before the page opened.
    let t_start = server.get(&format!("/v1/runs/{live}/state")).await["t_start"]
        .as_f64()
        .expect("a live state carries the run's start time");
    browser.goto(&format!("{base}/#/run/{live}")).await.unwrap();
    let reopened = browser
        .wait_for(
            "the live run opened mid-way, its charts filled",
            "const d = document.getElementById('status').dataset;              return d.ws === 'open' && d.backfilled === '1' && d.elapsed !== ''                ? Object.assign({}, d) : null;",
            Duration::from_secs(10),
        )
        .await;
    println!("reopened mid-way: {reopened}");
    let num = |k: &str| reopened[k].as_str().unwrap().parse::<f64>().unwrap();
    let first_half = t_mid - t_start;
    assert!(
        num("elapsed") >= first_half,
        "data time {} s does not count from the run's start ({first_half} s of data before \
         the page opened)",
        num("elapsed")
    );
    assert!(
        num("chartFrom") <= 0.1 * first_half && num("chartPoints") >= 50.0,
        "the charts do not hold the run's history: {reopened}"
    );
    assert_no_errors(&browser, "live run opened mid-way").await;
    server.end(&live).await;
    browser
        .wait_for(
            "the live view to turn into the stored run",
            "const d = document.getElementById('status').dataset; \
             return d.runStatus === 'ended' && d.ready === '1';",
            Duration::from_secs(15),
        )
        .await;
    assert_no_errors(&browser, "live run ended").await;

    // History: both runs listed with their status.
    browser.goto(&format!("{base}/#/runs")).await.unwrap();
    let listed = browser
        .wait_for(
            "the run history",
            "const rows = [...document.querySelectorAll('[data-testid=run-row]')]; \
             return rows.length >= 2 ? rows.map(r => [r.dataset.runId, r.dataset.status]) : null;",
            Duration::from_secs(10),
        )
        .await;
    for run in [&stored, &live] {
        assert!(
            listed
                .as_array()
                .unwrap()
                .iter()
                .any(|r| r[0] == **run && r[1] == "ended"),
            "run {run} is not listed as ended: {listed}"
        );
    }
    browser.screenshot(&shots.join("runs.png")).await.unwrap();
    assert_no_errors(&browser, "run history").await;

    // The stored run: its final map, then scrubbing back in time.
    browser
        .goto(&format!("{base}/#/run/{stored}"))
        .await
        .unwrap();
    let status = browser
        .wait_for(
            "the stored run's map",
            "const d = document.getElementById('status').dataset; \
             return d.ready === '1' && d.view === 'run' ? Object.assign({}, d) : null;",
            Duration::from_secs(15),
        )
        .await;
    assert_eq!(
        status["landmarks"],
        landmarks.to_string(),
        "landmarks on the map: {status}"
    );
    assert_eq!(
        status["robots"],
        robots.to_string(),
        "robots on the map: {status}"
    );
    // Its ground truth is overlaid and its error figures shown.
    let ate = browser
        .wait_for(
            "the error against ground truth",
            "const e = document.querySelector('[data-testid=team-ate] .fig-value'); \
             const truth = document.querySelector('[data-testid=show-truth]'); \
             return e && truth && truth.closest('label').offsetParent !== null ? e.textContent : null;",
            Duration::from_secs(10),
        )
        .await;
    println!("team ATE shown: {ate}");
    // The charts fill with states sampled over the run; then the picture.
    browser
        .wait_for(
            "the stored run's charts",
            "return document.getElementById('status').dataset.sampled === '1';",
            Duration::from_secs(20),
        )
        .await;
    tokio::time::sleep(Duration::from_millis(400)).await;
    browser.screenshot(&shots.join("run.png")).await.unwrap();
    if std::env::var("FLEETSLAM_UPDATE_SCREENSHOT").is_ok_and(|v| v == "1") {
        let docs = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../docs/dashboard.png")
            .canonicalize()
            .unwrap_or_else(|_| {
                Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/dashboard.png")
            });
        browser.screenshot(&docs).await.unwrap();
    }
    let has_timeline = browser
        .js("return !!document.querySelector('[data-testid=timeline]');")
        .await
        .unwrap();
    assert_eq!(has_timeline, true, "the stored run has no timeline");
    let before = browser.status().await["time"].clone();
    browser
        .js(
            "const s = document.querySelector('[data-testid=timeline]'); \
             s.value = String(Math.round(s.max * 0.4)); \
             s.dispatchEvent(new Event('input', {bubbles: true}));",
        )
        .await
        .unwrap();
    let after = browser
        .wait_for(
            "the scrubbed time",
            "const d = document.getElementById('status').dataset; \
             return d.scrubbed ? d.time : null;",
            Duration::from_secs(10),
        )
        .await;
    let (t_before, t_after) = (
        before.as_str().unwrap().parse::<f64>().unwrap(),
        after.as_str().unwrap().parse::<f64>().unwrap(),
    );
    assert!(
        t_after < t_before - 1.0,
        "scrubbing to 40% did not move the shown time back: {t_before} -> {t_after}"
    );
    let label = browser
        .js("return document.querySelector('[data-testid=time-label]').textContent;")
        .await
        .unwrap();
    println!("scrubbed: t {t_before} -> {t_after} ({label})");
    // The pose toggle: the weighted mean, then back to the best particle.
    let legend = browser
        .js(
            "document.querySelector('[data-testid=pose-mean]').click(); \
             return document.querySelector('[data-testid=map-legend]').textContent;",
        )
        .await
        .unwrap();
    assert!(
        legend.as_str().unwrap().contains("weighted mean"),
        "the legend does not say the poses are the weighted mean: {legend}"
    );
    browser
        .js("document.querySelector('[data-testid=pose-best]').click();")
        .await
        .unwrap();
    browser
        .screenshot(&shots.join("run-scrubbed.png"))
        .await
        .unwrap();
    assert_no_errors(&browser, "stored run and scrubbing").await;

    // The comparison of the two runs.
    browser
        .goto(&format!("{base}/#/compare/{stored}/{live}"))
        .await
        .unwrap();
    let cmp = browser
        .wait_for(
            "the comparison",
            "const d = document.getElementById('status').dataset; \
             return d.view === 'compare' && d.ready === '1' ? Object.assign({}, d) : null;",
            Duration::from_secs(10),
        )
        .await;
    assert_eq!(
        cmp["robots"],
        format!("{robots},{robots}"),
        "robots in the comparison: {cmp}"
    );
    let canvases = browser
        .js("return document.querySelectorAll('[data-testid=compare-view] canvas.map-canvas').length;")
        .await
        .unwrap();
    assert_eq!(canvases, 2);
    tokio::time::sleep(Duration::from_millis(300)).await;
    browser
        .screenshot(&shots.join("compare.png"))
        .await
        .unwrap();
    assert_no_errors(&browser, "comparison").await;

    // Scale: 10 robots mapping more than 5,000 landmarks, watched live. Measured: what the
    // websocket carries per second and per state (compact states carry only the landmarks
    // that changed), against the size of a full state, and the map's draw time per frame.
    let (big, big_truth) = scale_log();
    let (scale_run, scale_tokens) = server
        .create_run(
            &big,
            &big_truth,
            "scale: 10 robots, 5,000 landmarks",
            json!({"particles": SCALE_PARTICLES, "seed": 1}),
        )
        .await;
    let t_end = big.records.last().unwrap().t;
    let (bulk, paced): (Vec<Record>, Vec<Record>) = big
        .records
        .iter()
        .cloned()
        .partition(|r| r.t < t_end - SCALE_MEASURED_S);
    server.post(&scale_run, &scale_tokens, &bulk).await;
    server.settled_applied(&scale_run).await;
    browser
        .goto(&format!("{base}/#/run/{scale_run}"))
        .await
        .unwrap();
    let start = browser
        .wait_for(
            "the scale run's map",
            &format!(
                "const d = document.getElementById('status').dataset; \
                 return d.ws === 'open' && Number(d.landmarks) >= {SCALE_MAP} \
                   ? Object.assign({{}}, d) : null;"
            ),
            Duration::from_secs(30),
        )
        .await;
    let measured_from = Instant::now();
    let t0 = paced[0].t;
    for second in 0..(SCALE_MEASURED_S.ceil() as usize) {
        let slice: Vec<Record> = paced
            .iter()
            .filter(|r| ((r.t - t0).floor() as usize) == second)
            .cloned()
            .collect();
        server
            .post_in_order(&scale_run, &scale_tokens, &slice)
            .await;
        let due = measured_from + Duration::from_secs(second as u64 + 1);
        tokio::time::sleep_until(due.into()).await;
    }
    let end = browser.status().await;
    let wall = measured_from.elapsed().as_secs_f64();
    let num = |v: &Value, k: &str| v[k].as_str().unwrap().parse::<f64>().unwrap();
    let bytes = num(&end, "wsBytes") - num(&start, "wsBytes");
    let states = num(&end, "wsStates") - num(&start, "wsStates");
    let full = server
        .http
        .get(format!("{}/v1/runs/{scale_run}/state", server.base))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap()
        .len() as f64;
    println!(
        "scale ({SCALE_ROBOTS} robots, {} landmarks shown): websocket {:.1} kB/s, {:.1} kB per \
         state over {states} states (a full state is {:.1} kB); map frame mean {} ms, max {} \
         ms over {} frames",
        end["landmarks"],
        bytes / wall / 1e3,
        bytes / states.max(1.0) / 1e3,
        full / 1e3,
        end["frameMs"],
        end["frameMaxMs"],
        end["frames"]
    );
    // The page keeps receiving states while robots post (measured here: 15 and 18 states
    // over the 6 s, as the server publishes them after each second's records), and a state
    // carries what changed (measured: 48 kB per state against a full state of 893 kB).
    assert!(
        states >= 2.0 * SCALE_MEASURED_S,
        "{states} states in {wall:.1} s"
    );
    assert!(
        bytes / states < 0.1 * full,
        "compact states are not compact: {:.0} bytes per state, a full state {full:.0}",
        bytes / states
    );
    browser.screenshot(&shots.join("scale.png")).await.unwrap();
    assert_no_errors(&browser, "scale run").await;

    // A phone in landscape: nothing wider than the screen, the map visible.
    browser.emulate_phone(844, 390).await.unwrap();
    browser
        .goto(&format!("{base}/#/run/{stored}"))
        .await
        .unwrap();
    browser
        .wait_for(
            "the stored run on a phone",
            "return document.getElementById('status').dataset.ready === '1';",
            Duration::from_secs(10),
        )
        .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    browser
        .screenshot(&shots.join("phone-landscape.png"))
        .await
        .unwrap();
    let fit = browser
        .js(
            "const c = document.querySelector('canvas.map-canvas').getBoundingClientRect(); \
             return {overflow: document.documentElement.scrollWidth - window.innerWidth, \
                     mapW: c.width, mapH: c.height, w: window.innerWidth, h: window.innerHeight};",
        )
        .await
        .unwrap();
    println!("phone in landscape: {fit}");
    assert!(
        fit["overflow"].as_f64().unwrap() <= 0.0,
        "the page is wider than a phone in landscape: {fit}"
    );
    assert!(
        fit["mapW"].as_f64().unwrap() > 300.0 && fit["mapH"].as_f64().unwrap() > 150.0,
        "the map is too small on a phone in landscape: {fit}"
    );
    assert_no_errors(&browser, "phone in landscape").await;

    browser.quit().await;
    drop(driver);
    // For working on the dashboard: keep the server (with its two runs) up for a while.
    if let Some(secs) = std::env::var("FLEETSLAM_DASHBOARD_HOLD_S")
        .ok()
        .and_then(|v| v.parse::<u64>().ok())
    {
        println!("holding the server at {base}/ for {secs} s");
        tokio::time::sleep(Duration::from_secs(secs)).await;
    }
    drop(proxy);
    if let Some(r) = server.running {
        r.stop().await.unwrap();
    }
    println!(
        "dashboard test done in {:.1} s; screenshots in {}",
        started.elapsed().as_secs_f64(),
        shots.display()
    );
}
