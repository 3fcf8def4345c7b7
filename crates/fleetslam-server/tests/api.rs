//! The HTTP API through `oneshot` (no socket), the websocket against a real server on
//! 127.0.0.1:0, and k concurrent robot clients whose result equals the offline run.

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use fleetslam_core::config::FilterConfig;
use fleetslam_core::filter::FastSlam;
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_store::Store;
use serde_json::{Value, json};
use tower::ServiceExt;

mod common;
use common::{harness, setup, sim_log};

#[tokio::test]
async fn k_concurrent_robot_clients_equal_the_offline_run() {
    let log = sim_log(3, 15.0);
    let config = json!({"particles": 60, "seed": 11});
    let h = harness(ApiConfig::default()).await;
    let (run, tokens) = setup(&h, &log, config.clone()).await;

    // Each robot posts its own records, in order, in small batches, all robots at once.
    let mut tasks = Vec::new();
    for (robot, token) in tokens {
        let router = h.router.clone();
        let records: Vec<_> = log
            .records
            .iter()
            .filter(|r| r.robot == robot)
            .cloned()
            .collect();
        let uri = format!("/v1/runs/{run}/observations");
        tasks.push(tokio::spawn(async move {
            for chunk in records.chunks(7) {
                let req = Request::builder()
                    .method("POST")
                    .uri(&uri)
                    .header(header::CONTENT_TYPE, "application/json")
                    .header(header::AUTHORIZATION, format!("Bearer {token}"))
                    .body(Body::from(serde_json::to_vec(chunk).unwrap()))
                    .unwrap();
                let resp = router.clone().oneshot(req).await.unwrap();
                assert_eq!(resp.status(), StatusCode::OK);
                tokio::task::yield_now().await;
            }
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
    let (s, _) = h
        .json("POST", &format!("/v1/runs/{run}/end"), None, json!({}))
        .await;
    assert_eq!(s, StatusCode::NO_CONTENT);
    // An ended run takes no more data, and says so.
    let (s, v) = h
        .json(
            "POST",
            &format!("/v1/runs/{run}/robots"),
            None,
            json!({"id": "late"}),
        )
        .await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    assert!(v["message"].as_str().unwrap().contains("ended"), "{v}");
    let (_, v) = h.get(&format!("/v1/runs/{run}")).await;
    assert_eq!(
        v["run"]["summary"]["applied"].as_u64().unwrap() as usize,
        log.records.len()
    );
    // The ended run's state is its stored result.
    let (s, summary) = h.get(&format!("/v1/runs/{run}/state")).await;
    assert_eq!(s, StatusCode::OK, "{summary}");
    assert_eq!(summary["status"], "ended");

    // Offline, same seed and configuration.
    let mut cfg: FilterConfig = FilterConfig::from_header(&log.header);
    cfg.particles = 60;
    cfg.seed = 11;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, &log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    let est = slam.estimate();
    // Trajectories: the same poses after the same records, bit for bit.
    let (_, traj) = h.get(&format!("/v1/runs/{run}/trajectories")).await;
    for (robot, pts) in &out.estimate.trajectories {
        let offline: Vec<[f64; 4]> = pts
            .iter()
            .map(|p| [p.t, p.pose.x, p.pose.y, p.pose.theta])
            .collect();
        assert_eq!(traj["robots"][robot], json!(offline), "robot {robot}");
    }
    for (i, r) in est.robots.iter().enumerate() {
        let server = &summary["robots"][i];
        assert_eq!(server["id"], json!(r.id));
        assert_eq!(
            server["best"],
            serde_json::to_value(r.best).unwrap(),
            "robot {}",
            r.id
        );
        assert_eq!(
            server["mean"],
            serde_json::to_value(r.mean).unwrap(),
            "robot {}",
            r.id
        );
    }
    let lms: Vec<Value> = est
        .landmarks
        .iter()
        .map(|l| json!({"mean": l.gaussian.mean, "cov": l.gaussian.cov}))
        .collect();
    let server_lms: Vec<Value> = summary["landmarks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| json!({"mean": l["mean"], "cov": l["cov"]}))
        .collect();
    assert_eq!(server_lms, lms);
}

#[tokio::test]
async fn repeats_are_acknowledged_again_and_applied_once() {
    let log = sim_log(1, 3.0);
    let h = harness(ApiConfig::default()).await;
    let (run, tokens) = setup(&h, &log, json!({"particles": 10})).await;
    let token = &tokens[0].1;
    let uri = format!("/v1/runs/{run}/observations");
    let first = serde_json::to_vec(&log.records[0]).unwrap();
    let (s, v) = h
        .call("POST", &uri, Some(token), "application/json", first.clone())
        .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["acks"][0]["status"], "stored");
    let arrival = v["acks"][0]["arrival"].clone();
    let (s, v) = h
        .call("POST", &uri, Some(token), "application/json", first)
        .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["acks"][0]["status"], "duplicate");
    // NDJSON of the next records, with a gap.
    let lines: String = log.records[1..4]
        .iter()
        .chain(log.records[6..7].iter())
        .map(|r| serde_json::to_string(r).unwrap() + "\n")
        .collect();
    let (s, v) = h
        .call(
            "POST",
            &uri,
            Some(token),
            "application/x-ndjson",
            lines.into_bytes(),
        )
        .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["acks"].as_array().unwrap().len(), 4);
    let state = h.state_when(&run, |s| s["robots"][0]["records"] == 5).await;
    assert_eq!(state["robots"][0]["gaps"], 2, "{state}");
    assert!(arrival.as_i64().unwrap() >= 1);
}

/// (name, path, token, body, expected status, text the message must contain).
type Case<'a> = (
    &'a str,
    String,
    Option<&'a str>,
    Vec<u8>,
    StatusCode,
    &'a str,
);

/// Every bad input gets the right 4xx with a message that says what was wrong.
#[tokio::test]
async fn bad_input_table() {
    let log = sim_log(2, 3.0);
    let h = harness(ApiConfig {
        auth: fleetslam_server::auth::AuthConfig {
            admin_token: Some("sesame".into()),
            loopback: true,
            ..Default::default()
        },
        body_limit: 64 << 10,
        ..ApiConfig::default()
    })
    .await;
    // Run creation needs the admin token.
    let (s, v) = h
        .json("POST", "/v1/runs", None, json!({"header": log.header}))
        .await;
    assert_eq!(s, StatusCode::UNAUTHORIZED, "{v}");
    let (s, v) = h
        .json(
            "POST",
            "/v1/runs",
            Some("sesame"),
            json!({"header": log.header}),
        )
        .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let run = v["id"].as_str().unwrap().to_string();
    let (s, v) = h
        .json(
            "POST",
            &format!("/v1/runs/{run}/robots"),
            Some("sesame"),
            json!({"id": "1", "start": log.header.robots[0].start, "t0": 0.0}),
        )
        .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let token = v["token"].as_str().unwrap().to_string();
    let obs = format!("/v1/runs/{run}/observations");
    let good = serde_json::to_value(log.records.iter().find(|r| r.robot == "1").unwrap()).unwrap();
    let with = |k: &str, val: Value| {
        let mut g = good.clone();
        g[k] = val;
        serde_json::to_vec(&g).unwrap()
    };
    let big = vec![b' '; 70 << 10];
    let cases: Vec<Case> = vec![
        (
            "create: bad particles",
            "/v1/runs".into(),
            Some("sesame"),
            serde_json::to_vec(&json!({"config": {"particles": 0}})).unwrap(),
            StatusCode::BAD_REQUEST,
            "particles",
        ),
        (
            "create: unknown version",
            "/v1/runs".into(),
            Some("sesame"),
            serde_json::to_vec(&json!({"config": {"version": "3"}})).unwrap(),
            StatusCode::BAD_REQUEST,
            "version",
        ),
        (
            "create: unknown field",
            "/v1/runs".into(),
            Some("sesame"),
            serde_json::to_vec(&json!({"colour": 1})).unwrap(),
            StatusCode::BAD_REQUEST,
            "colour",
        ),
        (
            "robot: duplicate",
            format!("/v1/runs/{run}/robots"),
            Some("sesame"),
            serde_json::to_vec(&json!({"id": "1"})).unwrap(),
            StatusCode::CONFLICT,
            "already",
        ),
        (
            "robot: bad id",
            format!("/v1/runs/{run}/robots"),
            Some("sesame"),
            serde_json::to_vec(&json!({"id": ""})).unwrap(),
            StatusCode::BAD_REQUEST,
            "id must be",
        ),
        (
            "robot: unknown run",
            "/v1/runs/nope/robots".into(),
            Some("sesame"),
            serde_json::to_vec(&json!({"id": "x"})).unwrap(),
            StatusCode::NOT_FOUND,
            "no run",
        ),
        (
            "obs: no token",
            obs.clone(),
            None,
            serde_json::to_vec(&good).unwrap(),
            StatusCode::UNAUTHORIZED,
            "token",
        ),
        (
            "obs: wrong token",
            obs.clone(),
            Some("deadbeef"),
            serde_json::to_vec(&good).unwrap(),
            StatusCode::UNAUTHORIZED,
            "unknown robot token",
        ),
        (
            "obs: malformed JSON",
            obs.clone(),
            Some(&token),
            b"{\"robot\":".to_vec(),
            StatusCode::BAD_REQUEST,
            "record",
        ),
        (
            "obs: not JSON",
            obs.clone(),
            Some(&token),
            b"hello".to_vec(),
            StatusCode::BAD_REQUEST,
            "NDJSON",
        ),
        (
            "obs: wrong type",
            obs.clone(),
            Some(&token),
            with("seq", json!("seven")),
            StatusCode::BAD_REQUEST,
            "seq",
        ),
        (
            "obs: negative seq",
            obs.clone(),
            Some(&token),
            with("seq", json!(-1)),
            StatusCode::BAD_REQUEST,
            "seq",
        ),
        (
            "obs: NaN time",
            obs.clone(),
            Some(&token),
            String::from_utf8(with("t", json!(0.0)))
                .unwrap()
                .replacen("\"t\":0.0", "\"t\":NaN", 1)
                .into_bytes(),
            StatusCode::BAD_REQUEST,
            "record",
        ),
        (
            "obs: huge time",
            obs.clone(),
            Some(&token),
            with("t", json!(1e300)),
            StatusCode::BAD_REQUEST,
            "finite time",
        ),
        (
            "obs: infinite range",
            obs.clone(),
            Some(&token),
            String::from_utf8(with("landmarks", json!([{"id": 1, "z": [7.0, 0.1]}])))
                .unwrap()
                .replacen("[7.0,0.1]", "[1e400,0.1]", 1)
                .into_bytes(),
            StatusCode::BAD_REQUEST,
            "record",
        ),
        (
            "obs: huge range",
            obs.clone(),
            Some(&token),
            with("landmarks", json!([{"id": 1, "z": [1e300, 0.1]}])),
            StatusCode::BAD_REQUEST,
            "beyond 1e6",
        ),
        (
            "obs: wrong measurement size",
            obs.clone(),
            Some(&token),
            with("landmarks", json!([{"id": 1, "z": [1.0]}])),
            StatusCode::BAD_REQUEST,
            "[range, bearing]",
        ),
        (
            "obs: other robot's record",
            obs.clone(),
            Some(&token),
            with("robot", json!("2")),
            StatusCode::FORBIDDEN,
            "token",
        ),
        (
            "obs: empty batch",
            obs.clone(),
            Some(&token),
            b"[]".to_vec(),
            StatusCode::BAD_REQUEST,
            "no records",
        ),
        (
            "obs: oversized body",
            obs.clone(),
            Some(&token),
            big,
            StatusCode::PAYLOAD_TOO_LARGE,
            "body_limit_bytes",
        ),
        (
            "state: unknown run",
            "/v1/runs/nope/state".into(),
            None,
            Vec::new(),
            StatusCode::NOT_FOUND,
            "no run",
        ),
    ];
    for (name, uri, tok, body, want, needle) in cases {
        let method = if uri.ends_with("/state") {
            "GET"
        } else {
            "POST"
        };
        let (s, v) = h.call(method, &uri, tok, "application/json", body).await;
        assert_eq!(s, want, "{name}: {v}");
        assert!(
            v.to_string().contains(needle),
            "{name}: message {v} lacks {needle:?}"
        );
    }
    // Time going back within one batch: the later seq is refused (409), the first stored.
    let mut a = log
        .records
        .iter()
        .filter(|r| r.robot == "1")
        .nth(5)
        .unwrap()
        .clone();
    let mut b = a.clone();
    a.t += 10.0;
    b.seq += 1;
    b.t += 5.0;
    let (s, v) = h
        .call(
            "POST",
            &obs,
            Some(&token),
            "application/json",
            serde_json::to_vec(&[a, b]).unwrap(),
        )
        .await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    assert_eq!(v["acks"][0]["status"], "stored", "{v}");
    assert_eq!(v["acks"][1]["status"], "rejected", "{v}");
    assert!(
        v["acks"][1]["error"]
            .as_str()
            .unwrap()
            .contains("out of time order"),
        "{v}"
    );
    // A sequence regression: record 1 then record 0 later than what was applied.
    let r1 = log
        .records
        .iter()
        .filter(|r| r.robot == "1")
        .nth(1)
        .unwrap()
        .clone();
    let (s, v) = h
        .call(
            "POST",
            &obs,
            Some(&token),
            "application/json",
            serde_json::to_vec(&r1).unwrap(),
        )
        .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let state = h.state_when(&run, |s| s["robots"][0]["records"] == 2).await;
    assert_eq!(
        state["robots"][0]["gaps"], 4,
        "seqs 0, 2, 3 and 4 are missing: {state}"
    );
}

#[tokio::test]
async fn websocket_streams_state_and_events() {
    use futures::StreamExt;
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open_default(dir.path()).await.unwrap();
    let router = app(AppState::new(store, ApiConfig::default()));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let server = tokio::spawn(async move { axum::serve(listener, router).await.unwrap() });
    // Create a run over the real socket with a raw HTTP/1.1 request (no client crate).
    let log = sim_log(1, 2.0);
    let body =
        serde_json::to_string(&json!({"header": log.header, "config": {"particles": 10}})).unwrap();
    let resp = raw_http(addr, "POST", "/v1/runs", &body).await;
    let run = serde_json::from_str::<Value>(resp.split("\r\n\r\n").nth(1).unwrap()).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/v1/runs/{run}/live"))
        .await
        .unwrap();
    let first = ws.next().await.unwrap().unwrap().into_text().unwrap();
    let v: Value = serde_json::from_str(&first).unwrap();
    assert_eq!(v["type"], "state");
    assert_eq!(v["state"]["run"], json!(run));
    // Registering a robot produces an event.
    let reg =
        serde_json::to_string(&json!({"id": "1", "start": log.header.robots[0].start})).unwrap();
    raw_http(addr, "POST", &format!("/v1/runs/{run}/robots"), &reg).await;
    let mut saw_join = false;
    for _ in 0..10 {
        let msg = tokio::time::timeout(std::time::Duration::from_secs(5), ws.next())
            .await
            .unwrap()
            .unwrap()
            .unwrap();
        let v: Value = serde_json::from_str(&msg.into_text().unwrap()).unwrap();
        if v["type"] == "event" && v["event"]["event"] == "robot_joined" {
            saw_join = true;
            break;
        }
    }
    assert!(saw_join);
    server.abort();
}

async fn raw_http(addr: std::net::SocketAddr, method: &str, path: &str, body: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).await.unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).await.unwrap();
    out
}
