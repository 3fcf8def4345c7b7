//! Readers never slow writers (issue 11): the state, trajectories, timeline and export of a
//! live run answer while its coordinator is stuck in a filter step with a full queue (they
//! never go through its queue), and websocket connections are bounded per run and in total
//! with a JSON 503 before the upgrade and let go of when their client stops answering.

use axum::http::StatusCode;
use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::pose::Pose2;
use fleetslam_core::updater::{
    LandmarkGaussian, LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput,
};
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_store::{NewRun, Store};
use serde_json::{Value, json};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

mod common;
use common::{Harness, sim_log};

/// The EKF behind a gate: every landmark update waits until the test opens it, so the
/// coordinator is stuck in a step for as long as the test wants.
#[derive(Debug)]
struct Gated {
    inner: EkfUpdater,
    open: Arc<(Mutex<bool>, Condvar)>,
}

impl Gated {
    fn wait(&self) {
        let (lock, cv) = &*self.open;
        let mut open = lock.lock().unwrap();
        while !*open {
            open = cv.wait(open).unwrap();
        }
    }
}

impl LandmarkUpdater for Gated {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn kind(&self) -> fleetslam_core::sensor::LandmarkKind {
        self.inner.kind()
    }
    fn initialize(&self, pose: &Pose2, z: &[f64; 3]) -> LandmarkGaussian {
        self.wait();
        self.inner.initialize(pose, z)
    }
    fn update_batch(
        &self,
        needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
    ) {
        self.wait();
        self.inner.update_batch(needs, inputs, outputs)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reads_answer_while_the_coordinator_is_stuck_with_a_full_queue() {
    let log = sim_log(1, 10.0);
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open_default(dir.path()).await.unwrap();
    let mut api = ApiConfig::default();
    api.coordinator.queue_capacity = 1;
    // The coordinator goes on storing requests while the filter steps, up to a backlog of
    // acknowledged records: with none allowed, it takes no request while the step is stuck.
    api.coordinator.max_backlog = 1;
    let state = AppState::new(store.clone(), api);
    let h = Harness {
        router: app(state.clone()),
        store: store.clone(),
        dir: tempfile::tempdir().unwrap(),
    };
    let mut cfg = FilterConfig::from_header(&log.header);
    cfg.particles = 20;
    cfg.seed = 1;
    store
        .create_run(&NewRun {
            id: "busy".into(),
            name: None,
            config: serde_json::to_value(&cfg).unwrap(),
            header: Some(serde_json::to_value(&log.header).unwrap()),
        })
        .await
        .unwrap();
    let gate = Arc::new((Mutex::new(false), Condvar::new()));
    let updater = Arc::new(Gated {
        inner: EkfUpdater::new(cfg.landmark_kind, &cfg.sensor_noise),
        open: gate.clone(),
    });
    let slam = FastSlam::with_updater(cfg.clone(), updater).unwrap();
    let filter = fleetslam_localize::LateJoinSlam::from_slam(slam, Default::default()).unwrap();
    state.start_run("busy", filter).await.unwrap();
    let robot = &log.header.robots[0];
    let (s, v) = h
        .json(
            "POST",
            "/v1/runs/busy/robots",
            None,
            json!({"id": robot.id, "start": robot.start, "t0": robot.t0}),
        )
        .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let token = v["token"].as_str().unwrap().to_string();

    // The first record that observes a landmark gets the coordinator stuck in its step.
    let k = log
        .records
        .iter()
        .position(|r| !r.landmarks.is_empty())
        .unwrap();
    let post = |recs: Vec<fleetslam_core::log::Record>| {
        let (router, token) = (h.router.clone(), token.clone());
        tokio::spawn(async move { post_records(router, &token, &recs).await })
    };
    let first = post(log.records[..=k].to_vec()).await.unwrap();
    assert_eq!(first.0, StatusCode::OK, "{}", first.1);
    // Then one request per record until the queue is full: the coordinator takes none of
    // them while it is stuck (one waits in the queue, the next gets 503).
    let mut waiting = Vec::new();
    let mut full = None;
    for j in k + 1..(k + 12).min(log.records.len()) {
        let task = post(vec![log.records[j].clone()]);
        tokio::time::sleep(Duration::from_millis(200)).await;
        if task.is_finished() {
            let (s, v) = task.await.unwrap();
            if s == StatusCode::SERVICE_UNAVAILABLE {
                full = Some(v);
                break;
            }
            assert_eq!(s, StatusCode::OK, "{v}");
        } else {
            waiting.push(task);
        }
    }
    let full = full.expect("the queue filled up while the coordinator was stuck");
    assert_eq!(full["error"], "busy", "{full}");
    assert!(!waiting.is_empty());

    // Every read of the live run answers now, promptly.
    let quick = Duration::from_secs(5);
    for uri in [
        "/v1/runs/busy/state",
        "/v1/runs/busy/trajectories",
        "/v1/runs/busy/timeline",
        "/v1/runs/busy",
        "/v1/runs",
    ] {
        let (s, v) = tokio::time::timeout(quick, h.get(uri))
            .await
            .unwrap_or_else(|_| panic!("{uri} waited for the busy coordinator"));
        assert_eq!(s, StatusCode::OK, "{uri}: {v}");
    }
    let (s, st) = h.get("/v1/runs/busy/state").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(st["status"], "active");
    let (s, traj) = h.get("/v1/runs/busy/trajectories").await;
    assert_eq!(s, StatusCode::OK);
    assert!(
        traj["robots"][robot.id.as_str()]
            .as_array()
            .is_some_and(|p| !p.is_empty()),
        "the start pose at least: {traj}"
    );
    let (s, zip) = tokio::time::timeout(quick, h.raw("GET", "/v1/runs/busy/export"))
        .await
        .expect("export waited for the busy coordinator");
    assert_eq!(s, StatusCode::OK);
    assert!(zip.starts_with(b"PK"));

    // Open the gate: the waiting requests are answered and every record is applied.
    {
        let (lock, cv) = &*gate;
        *lock.lock().unwrap() = true;
        cv.notify_all();
    }
    let mut posted = k + 1;
    for task in waiting {
        let (s, v) = task.await.unwrap();
        assert_eq!(s, StatusCode::OK, "{v}");
        posted += 1;
    }
    let (s, v) = h.json("POST", "/v1/runs/busy/end", None, json!({})).await;
    assert_eq!(s, StatusCode::NO_CONTENT, "{v}");
    let (_, st) = h.get("/v1/runs/busy/state").await;
    assert_eq!(st["applied"].as_u64().unwrap() as usize, posted, "{st}");
}

/// Posts records as the robot whose token it is, through the router.
async fn post_records(
    router: axum::Router,
    token: &str,
    recs: &[fleetslam_core::log::Record],
) -> (StatusCode, Value) {
    use tower::ServiceExt;
    let req = axum::http::Request::builder()
        .method("POST")
        .uri("/v1/runs/busy/observations")
        .header("content-type", "application/json")
        .header("authorization", format!("Bearer {token}"))
        .body(axum::body::Body::from(serde_json::to_vec(recs).unwrap()))
        .unwrap();
    let resp = router.oneshot(req).await.unwrap();
    let status = resp.status();
    let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX)
        .await
        .unwrap();
    (
        status,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

/// A websocket upgrade request over a raw socket: the status and JSON body of a refusal.
async fn refused_upgrade(addr: std::net::SocketAddr, run: &str) -> (u16, Value) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!(
        "GET /v1/runs/{run}/live HTTP/1.1\r\nHost: {addr}\r\nConnection: Upgrade\r\n\
         Upgrade: websocket\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n"
    );
    s.write_all(req.as_bytes()).await.unwrap();
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        let n = s.read(&mut chunk).await.unwrap();
        assert!(
            n > 0,
            "connection closed early: {}",
            String::from_utf8_lossy(&buf)
        );
        buf.extend_from_slice(&chunk[..n]);
        let text = String::from_utf8_lossy(&buf).to_string();
        let Some(end) = text.find("\r\n\r\n") else {
            continue;
        };
        let head = text[..end].to_ascii_lowercase();
        let len: usize = head
            .lines()
            .find_map(|l| l.strip_prefix("content-length:"))
            .map_or(0, |v| v.trim().parse().unwrap());
        if buf.len() < end + 4 + len {
            continue;
        }
        let status: u16 = head.split_whitespace().nth(1).unwrap().parse().unwrap();
        let body = serde_json::from_slice(&buf[end + 4..end + 4 + len]).unwrap_or(Value::Null);
        return (status, body);
    }
}

/// A client's live websocket.
type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

async fn ws_connect(addr: std::net::SocketAddr, run: &str) -> Result<Ws, (u16, Value)> {
    use futures::StreamExt;
    match tokio_tungstenite::connect_async(format!("ws://{addr}/v1/runs/{run}/live")).await {
        Ok((mut ws, _)) => {
            // The first message is the state: the connection is served.
            let first = ws.next().await.unwrap().unwrap().into_text().unwrap();
            let v: Value = serde_json::from_str(&first).unwrap();
            assert_eq!(v["type"], "state");
            Ok(ws)
        }
        // Refused before the upgrade: read the whole answer again over a plain socket.
        Err(tokio_tungstenite::tungstenite::Error::Http(resp)) => {
            let refused = resp.status().as_u16();
            let (status, body) = refused_upgrade(addr, run).await;
            if status == 101 && refused == 503 {
                // A slot came free between the two requests (the connection's close was
                // still on its way): the refusal stands, without its body.
                return Err((refused, Value::Null));
            }
            assert_eq!(status, refused);
            Err((status, body))
        }
        Err(e) => panic!("websocket connection failed: {e}"),
    }
}

/// A server with `api` over a fresh store, on a loopback port, holding `n` new runs of a
/// one-robot log: its harness, address, task and run ids.
async fn serve_runs(
    api: ApiConfig,
    n: usize,
) -> (
    Harness,
    std::net::SocketAddr,
    tokio::task::JoinHandle<()>,
    Vec<String>,
) {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open_default(dir.path()).await.unwrap();
    let router = app(AppState::new(store.clone(), api));
    let h = Harness {
        router: router.clone(),
        store,
        dir,
    };
    let log = sim_log(1, 2.0);
    let mut runs = Vec::new();
    for _ in 0..n {
        let (s, v) = h
            .json("POST", "/v1/runs", None, json!({"header": log.header}))
            .await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        runs.push(v["id"].as_str().unwrap().to_string());
    }
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let server = tokio::spawn(async move { axum::serve(listener, router).await.unwrap() });
    (h, addr, server, runs)
}

/// Connects to `run`'s live websocket once a slot is free: up to `tries` attempts,
/// `pause` apart while the server answers 503.
async fn connect_when_free(
    addr: std::net::SocketAddr,
    run: &str,
    tries: usize,
    pause: Duration,
) -> Option<Ws> {
    for _ in 0..tries {
        match ws_connect(addr, run).await {
            Ok(ws) => return Some(ws),
            Err((503, _)) => tokio::time::sleep(pause).await,
            Err(other) => panic!("{other:?}"),
        }
    }
    None
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn websocket_connections_are_bounded_per_run_and_in_total() {
    let mut api = ApiConfig::default();
    api.coordinator.ws_max_per_run = 2;
    api.coordinator.ws_max_total = 3;
    let (h, addr, server, runs) = serve_runs(api, 2).await;

    let a1 = ws_connect(addr, &runs[0]).await.unwrap();
    let _a2 = ws_connect(addr, &runs[0]).await.unwrap();
    let (status, body) = ws_connect(addr, &runs[0]).await.unwrap_err();
    assert_eq!(status, 503, "{body}");
    assert_eq!(body["error"], "busy", "{body}");
    assert!(
        body["message"].as_str().unwrap().contains("ws_max_per_run"),
        "{body}"
    );
    let _b1 = ws_connect(addr, &runs[1]).await.unwrap();
    let (status, body) = ws_connect(addr, &runs[1]).await.unwrap_err();
    assert_eq!(status, 503, "{body}");
    assert!(
        body["message"].as_str().unwrap().contains("ws_max_total"),
        "{body}"
    );
    // An unknown run is still a 404, not a connection.
    let (s, v) = h.get("/v1/runs/nope/live").await;
    assert!(s.is_client_error(), "{s} {v}");

    // A closed connection gives its slot back.
    drop(a1);
    let again = connect_when_free(addr, &runs[0], 100, Duration::from_millis(20)).await;
    assert!(again.is_some(), "the slot of a closed connection came back");
    server.abort();
}

/// An idle run's connection gets a heartbeat (a ping and a message) every period and stays
/// open while its client answers; a client that stops answering is dropped after three
/// periods, which gives its slot back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heartbeats_keep_idle_connections_and_drop_silent_clients() {
    use futures::StreamExt;
    let mut api = ApiConfig::default();
    api.coordinator.ws_max_per_run = 1;
    api.coordinator.ws_heartbeat = Duration::from_millis(100);
    let (_h, addr, server, runs) = serve_runs(api, 1).await;
    let run = &runs[0];

    // Read for 10 periods: reading answers the pings, so the connection stays; nothing
    // happens in the run, so heartbeats are all that arrives.
    let mut ws = ws_connect(addr, run).await.unwrap();
    let until = tokio::time::Instant::now() + Duration::from_millis(1000);
    let mut beats = 0;
    while let Ok(msg) = tokio::time::timeout_at(until, ws.next()).await {
        let msg = msg.expect("the connection stays open").unwrap();
        if let Ok(text) = msg.into_text()
            && !text.is_empty()
        {
            let v: Value = serde_json::from_str(&text).unwrap();
            assert_eq!(v["type"], "heartbeat", "{v}");
            assert_eq!(v["period_ms"], 100);
            beats += 1;
        }
    }
    assert!(
        (8..=11).contains(&beats),
        "{beats} heartbeats in 10 periods"
    );
    // The one slot is taken.
    assert_eq!(ws_connect(addr, run).await.unwrap_err().0, 503);

    // Stop reading: no pong goes back, and after three periods the server lets go.
    let stopped = std::time::Instant::now();
    let again = connect_when_free(addr, run, 200, Duration::from_millis(10)).await;
    let waited = stopped.elapsed();
    assert!(again.is_some(), "a silent client kept its slot");
    assert!(
        waited >= Duration::from_millis(150),
        "the silent client was dropped after {waited:?}, before three periods"
    );
    drop(ws);
    server.abort();
}
