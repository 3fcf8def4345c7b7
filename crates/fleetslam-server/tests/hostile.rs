//! The trust boundary over real HTTP: a table of hostile and faulty requests (each gets the
//! right 4xx with a JSON error naming what was wrong, stores nothing, and the run goes on
//! advancing), and a seeded fuzzer posting mutated records and bodies.

use fleetslam_core::log::{Log, Record};
use fleetslam_data::sim::{SimConfig, simulate};
use fleetslam_server::config::ServerConfig;
use fleetslam_server::server::{Running, start};
use rand::{Rng, SeedableRng};
use reqwest::StatusCode;
use serde_json::{Value, json};

const ADMIN: &str = "admin-token-0123456789";
const READ: &str = "read-token-0123456789";

struct Server {
    base: String,
    running: Running,
    client: reqwest::Client,
    _dir: tempfile::TempDir,
}

async fn serve(edit: impl FnOnce(&mut ServerConfig)) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = ServerConfig {
        bind: "127.0.0.1:0".into(),
        data_dir: dir.path().to_path_buf(),
        admin_token: Some(ADMIN.into()),
        read_token: Some(READ.into()),
        ..ServerConfig::default()
    };
    edit(&mut cfg);
    let running = start(&cfg).await.unwrap();
    Server {
        base: format!("http://{}", running.addr),
        running,
        client: reqwest::Client::new(),
        _dir: dir,
    }
}

/// What came back: status, and the error code and message (of the body, or of the first
/// rejected record's acknowledgement).
#[derive(Debug)]
struct Answer {
    status: StatusCode,
    json: bool,
    code: String,
    message: String,
    body: Value,
}

impl Server {
    async fn send(
        &self,
        method: &str,
        path: &str,
        token: Option<&str>,
        content_type: Option<&str>,
        headers: &[(&str, &str)],
        body: Vec<u8>,
    ) -> Answer {
        let method = reqwest::Method::from_bytes(method.as_bytes()).unwrap();
        let mut req = self
            .client
            .request(method, format!("{}{path}", self.base))
            .body(body);
        if let Some(t) = token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        if let Some(c) = content_type {
            req = req.header("content-type", c);
        }
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        let resp = req.send().await.expect("the server answers");
        let status = resp.status();
        let json = resp
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .is_some_and(|c| c.starts_with("application/json"));
        let bytes = resp.bytes().await.unwrap();
        let body: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        let rejected = body["acks"]
            .as_array()
            .and_then(|a| a.iter().find(|a| a["status"] == "rejected"));
        let (code, message) = match rejected {
            Some(a) => (a["code"].clone(), a["error"].clone()),
            None => (body["error"].clone(), body["message"].clone()),
        };
        Answer {
            status,
            json,
            code: code.as_str().unwrap_or("").to_string(),
            message: message.as_str().unwrap_or("").to_string(),
            body,
        }
    }

    async fn json(&self, method: &str, path: &str, token: Option<&str>, body: Value) -> Answer {
        self.send(
            method,
            path,
            token,
            Some("application/json"),
            &[],
            serde_json::to_vec(&body).unwrap(),
        )
        .await
    }

    async fn create_run(&self, header: Value) -> (String, String) {
        let a = self
            .json(
                "POST",
                "/v1/runs",
                Some(ADMIN),
                json!({"name": "t", "header": header, "config": {"particles": 20, "seed": 3}}),
            )
            .await;
        assert_eq!(a.status, StatusCode::CREATED, "{:?}", a.body);
        (
            a.body["id"].as_str().unwrap().into(),
            a.body["enrollment_token"].as_str().unwrap().into(),
        )
    }

    async fn register(&self, run: &str, token: &str, id: &str, log: &Log) -> String {
        let start = log.header.robots[0].start;
        let a = self
            .json(
                "POST",
                &format!("/v1/runs/{run}/robots"),
                Some(token),
                json!({"id": id, "start": start, "t0": 0.0}),
            )
            .await;
        assert_eq!(a.status, StatusCode::CREATED, "{:?}", a.body);
        a.body["token"].as_str().unwrap().into()
    }

    /// (records, robots, runs) in the store: what a refused request must not change.
    async fn counts(&self, run: &str) -> (i64, usize, i64) {
        let store = &self.running.store;
        let runs = store
            .count_runs(&fleetslam_store::RunFilter::default())
            .await
            .unwrap();
        (
            store.record_count(run).await.unwrap(),
            store.robots(run).await.unwrap().len(),
            runs,
        )
    }
}

fn sim_log() -> Log {
    let mut log = simulate(&SimConfig {
        robots: 2,
        duration: 30.0,
        seed: 5,
        ..SimConfig::default()
    })
    .unwrap()
    .log;
    log.sort();
    log
}

/// A record with a seq no good record uses.
trait TapSeq {
    fn tap_seq(self, seq: u64) -> Value;
}
impl TapSeq for Value {
    fn tap_seq(mut self, seq: u64) -> Value {
        self["seq"] = json!(seq);
        self
    }
}

fn body(v: &Value) -> Vec<u8> {
    serde_json::to_vec(v).unwrap()
}

struct Case {
    name: &'static str,
    method: &'static str,
    path: String,
    token: Option<String>,
    content_type: Option<&'static str>,
    headers: Vec<(&'static str, &'static str)>,
    body: Vec<u8>,
    status: u16,
    code: &'static str,
    /// A word the message must contain: the field, setting or rule that was broken.
    names: &'static str,
}

// One row of the table: what is sent and what must come back, in the table's column order.
#[allow(clippy::too_many_arguments)]
fn case(
    name: &'static str,
    method: &'static str,
    path: impl Into<String>,
    token: Option<&str>,
    body: Vec<u8>,
    status: u16,
    code: &'static str,
    names: &'static str,
) -> Case {
    Case {
        name,
        method,
        path: path.into(),
        token: token.map(str::to_string),
        content_type: Some("application/json"),
        headers: Vec::new(),
        body,
        status,
        code,
        names,
    }
}

impl Case {
    fn content_type(mut self, c: Option<&'static str>) -> Self {
        self.content_type = c;
        self
    }
    fn header(mut self, k: &'static str, v: &'static str) -> Self {
        self.headers.push((k, v));
        self
    }
}

#[tokio::test]
async fn hostile_inputs_are_refused_clearly_and_change_nothing() {
    let log = sim_log();
    let srv = serve(|c| {
        c.read_access = fleetslam_server::auth::ReadAccess::Token;
        c.body_limit_bytes = 8 << 20;
        c.reorder_window_ms = 200;
        c.max_robots_per_run = 3;
        c.max_active_runs = 4;
        c.max_landmarks_per_record = 100;
    })
    .await;
    let header = serde_json::to_value(&log.header).unwrap();
    let (run, enroll) = srv.create_run(header.clone()).await;
    let (other_run, other_enroll) = srv.create_run(header.clone()).await;
    let mut ack_header = header.clone();
    ack_header["motion_model"] = json!("ackermann");
    let (ack_run, _) = srv.create_run(ack_header).await;
    // Robots enrol themselves with the run's enrollment token; "bearer" in any case.
    let t1 = srv.register(&run, &enroll, "1", &log).await;
    let t2 = srv.register(&run, ADMIN, "2", &log).await;
    let other_t = srv.register(&other_run, &other_enroll, "1", &log).await;
    let ack_t = srv.register(&ack_run, ADMIN, "1", &log).await;

    let good: Vec<Record> = log
        .records
        .iter()
        .filter(|r| r.robot == "1")
        .cloned()
        .collect();
    let rec = |i: usize| serde_json::to_value(&good[i]).unwrap();
    let with = |i: usize, k: &str, v: Value| {
        let mut r = rec(i);
        r[k] = v;
        r
    };
    let obs = format!("/v1/runs/{run}/observations");
    let robots = format!("/v1/runs/{run}/robots");
    let start = serde_json::to_value(log.header.robots[0].start).unwrap();
    // Record 0 is stored first, so that repeats of it can be tested.
    let a = srv.json("POST", &obs, Some(&t1), rec(0)).await;
    assert_eq!(a.status, StatusCode::OK, "{:?}", a.body);
    let mut next = 1;

    let many_landmarks = {
        let mut r = rec(1);
        r["landmarks"] = json!(vec![json!({"id": 1, "z": [1.0, 0.1]}); 101]);
        r
    };
    let huge_landmarks = {
        let mut r = rec(1);
        r["landmarks"] = json!(vec![json!({"z": [1.0, 0.1]}); 200_000]);
        r
    };
    let many_sightings = {
        let mut r = rec(1);
        r["robots"] = json!(vec![json!({"robot": "2", "z": [1.0, 0.1]}); 65]);
        r
    };
    let many_records: Vec<Value> = (0..10_001)
        .map(|i| json!({"robot": "1", "seq": 100 + i, "t": 1.0}))
        .collect();
    let ndjson_bad = format!(
        "{}\n{{\"robot\":\"1\",\"seq\":\n",
        serde_json::to_string(&rec(1)).unwrap()
    );
    let mut changed = rec(0);
    changed["t"] = json!(good[0].t + 0.001);
    let bad_cov = json!({"mean": {"x": 0, "y": 0, "theta": 0},
                         "cov": [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]});
    let asym_cov = json!({"mean": {"x": 0, "y": 0, "theta": 0},
                          "cov": [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]});
    let long_id = "r".repeat(200);
    let run_body = |name: &str| body(&json!({"name": name, "header": header}));

    let cases: Vec<Case> = vec![
        // --- authorization
        case(
            "create without a token",
            "POST",
            "/v1/runs",
            None,
            run_body("x"),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "create with a wrong token",
            "POST",
            "/v1/runs",
            Some("not-the-admin-token-xx"),
            run_body("x"),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "create with a robot token",
            "POST",
            "/v1/runs",
            Some(&t1),
            run_body("x"),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "create with an enrollment token",
            "POST",
            "/v1/runs",
            Some(&enroll),
            run_body("x"),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "create with the read token",
            "POST",
            "/v1/runs",
            Some(READ),
            run_body("x"),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "create with a Basic scheme",
            "POST",
            "/v1/runs",
            None,
            run_body("x"),
            401,
            "unauthorized",
            "admin token",
        )
        .header("authorization", "Basic YWRtaW46YWRtaW4="),
        case(
            "register without a token",
            "POST",
            &robots,
            None,
            body(&json!({"id": "9", "start": start})),
            401,
            "unauthorized",
            "enrollment token",
        ),
        case(
            "register with another run's enrollment token",
            "POST",
            &robots,
            Some(&other_enroll),
            body(&json!({"id": "9", "start": start})),
            401,
            "unauthorized",
            "enrollment token",
        ),
        case(
            "register with a robot token",
            "POST",
            &robots,
            Some(&t1),
            body(&json!({"id": "9", "start": start})),
            401,
            "unauthorized",
            "enrollment token",
        ),
        case(
            "register with the read token",
            "POST",
            &robots,
            Some(READ),
            body(&json!({"id": "9", "start": start})),
            401,
            "unauthorized",
            "enrollment token",
        ),
        case(
            "post without a token",
            "POST",
            &obs,
            None,
            body(&rec(1)),
            401,
            "unauthorized",
            "token",
        ),
        case(
            "post with the admin token",
            "POST",
            &obs,
            Some(ADMIN),
            body(&rec(1)),
            401,
            "unauthorized",
            "robot token",
        ),
        case(
            "post with the enrollment token",
            "POST",
            &obs,
            Some(&enroll),
            body(&rec(1)),
            401,
            "unauthorized",
            "robot token",
        ),
        case(
            "post with another run's robot token",
            "POST",
            &obs,
            Some(&other_t),
            body(&rec(1)),
            401,
            "unauthorized",
            "robot token",
        ),
        case(
            "post another robot's record",
            "POST",
            &obs,
            Some(&t2),
            body(&rec(1)),
            403,
            "forbidden",
            "own records",
        ),
        case(
            "end with a robot token",
            "POST",
            format!("/v1/runs/{run}/end"),
            Some(&t1),
            Vec::new(),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "delete with the read token",
            "DELETE",
            format!("/v1/runs/{run}"),
            Some(READ),
            Vec::new(),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "upload truth with the enrollment token",
            "PUT",
            format!("/v1/runs/{run}/truth"),
            Some(&enroll),
            body(&json!({})),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "re-run with a robot token",
            "POST",
            format!("/v1/runs/{run}/rerun"),
            Some(&t1),
            body(&json!({})),
            401,
            "unauthorized",
            "admin token",
        ),
        case(
            "read state without a token",
            "GET",
            format!("/v1/runs/{run}/state"),
            None,
            Vec::new(),
            401,
            "unauthorized",
            "read token",
        ),
        case(
            "read state with a robot token",
            "GET",
            format!("/v1/runs/{run}/state"),
            Some(&t1),
            Vec::new(),
            401,
            "unauthorized",
            "read token",
        ),
        case(
            "list runs without a token",
            "GET",
            "/v1/runs",
            None,
            Vec::new(),
            401,
            "unauthorized",
            "read token",
        ),
        case(
            "export with a wrong query token",
            "GET",
            format!("/v1/runs/{run}/export?access_token=nope"),
            None,
            Vec::new(),
            401,
            "unauthorized",
            "read token",
        ),
        case(
            "metrics without a token",
            "GET",
            "/metrics",
            None,
            Vec::new(),
            401,
            "unauthorized",
            "read token",
        ),
        // --- web pages of other origins, content types
        case(
            "create from a foreign web page",
            "POST",
            "/v1/runs",
            Some(ADMIN),
            run_body("x"),
            403,
            "forbidden",
            "origin",
        )
        .header("origin", "http://evil.example"),
        case(
            "post from a rebound DNS name",
            "POST",
            &obs,
            Some(&t1),
            body(&rec(1)),
            403,
            "forbidden",
            "origin",
        )
        .header("origin", "http://evil.example:8080"),
        case(
            "live websocket from a foreign page",
            "GET",
            format!("/v1/runs/{run}/live?access_token={READ}"),
            None,
            Vec::new(),
            403,
            "forbidden",
            "origin",
        )
        .header("origin", "https://evil.example")
        .header("connection", "upgrade")
        .header("upgrade", "websocket")
        .header("sec-websocket-version", "13")
        .header("sec-websocket-key", "dGhlIHNhbXBsZSBub25jZQ=="),
        case(
            "create as text/plain",
            "POST",
            "/v1/runs",
            Some(ADMIN),
            run_body("x"),
            415,
            "unsupported_media_type",
            "application/json",
        )
        .content_type(Some("text/plain")),
        case(
            "post as a form",
            "POST",
            &obs,
            Some(&t1),
            body(&rec(1)),
            415,
            "unsupported_media_type",
            "application/json",
        )
        .content_type(Some("application/x-www-form-urlencoded")),
        case(
            "register without a content type",
            "POST",
            &robots,
            Some(ADMIN),
            body(&json!({"id": "9", "start": start})),
            415,
            "unsupported_media_type",
            "Content-Type",
        )
        .content_type(None),
        // --- bounded record fields
        case(
            "seq 2^63",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "seq", json!(1u64 << 63))),
            400,
            "bad_request",
            "seq",
        ),
        case(
            "negative seq",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "seq", json!(-1))),
            400,
            "bad_request",
            "seq",
        ),
        case(
            "t far in the future",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "t", json!(1e11)).tap_seq(5000)),
            409,
            "too_far_ahead",
            "max_future_s",
        ),
        case(
            "t an hour and a bit ahead",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "t", json!(good[good.len() - 1].t + 3601.0)).tap_seq(5001)),
            409,
            "too_far_ahead",
            "max_future_s",
        ),
        case(
            "t is a string",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "t", json!("soon"))),
            400,
            "bad_request",
            "t",
        ),
        case(
            "t beyond any clock",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "t", json!(1e300))),
            400,
            "bad_request",
            "t",
        ),
        case(
            "a motion of 1e9 s",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "motion", json!({"velocity": [[0.1, 0.0, 1e9]]}))),
            400,
            "bad_request",
            "max_motion_s",
        ),
        case(
            "an Ackermann segment of 1e9 s",
            "POST",
            format!("/v1/runs/{ack_run}/observations"),
            Some(&ack_t),
            body(&with(1, "motion", json!({"ackermann": [[1.0, 0.1, 1e9]]}))),
            400,
            "bad_request",
            "max_motion_s",
        ),
        case(
            "10,001 motion segments",
            "POST",
            &obs,
            Some(&t1),
            body(&with(
                1,
                "motion",
                json!(vec![[0.0, 0.0, 0.001]; 10_001])
                    .as_array()
                    .map(|a| json!({"velocity": a}))
                    .unwrap(),
            )),
            400,
            "bad_request",
            "max_motion_segments",
        ),
        case(
            "a negative duration",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "motion", json!({"velocity": [[0.1, 0.0, -1.0]]}))),
            400,
            "bad_request",
            "negative duration",
        ),
        case(
            "the wrong motion model",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "motion", json!({"odometry": [0.1, 0.0, 0.0]}))),
            400,
            "bad_request",
            "motion model",
        ),
        case(
            "101 landmark observations",
            "POST",
            &obs,
            Some(&t1),
            body(&many_landmarks),
            400,
            "bad_request",
            "max_landmarks_per_record",
        ),
        case(
            "200,000 landmark observations",
            "POST",
            &obs,
            Some(&t1),
            body(&huge_landmarks),
            400,
            "bad_request",
            "max_landmarks_per_record",
        ),
        case(
            "65 robot sightings",
            "POST",
            &obs,
            Some(&t1),
            body(&many_sightings),
            400,
            "bad_request",
            "max_sightings_per_record",
        ),
        case(
            "a robot sighting itself",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "robots", json!([{"robot": "1", "z": [1.0, 0.0]}]))),
            400,
            "bad_request",
            "itself",
        ),
        case(
            "a landmark with one number",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "landmarks", json!([{"z": [1.0]}]))),
            400,
            "bad_request",
            "landmarks[0]",
        ),
        case(
            "an unknown field",
            "POST",
            &obs,
            Some(&t1),
            body(&with(1, "colour", json!("red"))),
            400,
            "bad_request",
            "colour",
        ),
        case(
            "10,001 records in one request",
            "POST",
            &obs,
            Some(&t1),
            body(&json!(many_records)),
            413,
            "too_large",
            "max_records_per_request",
        ),
        case(
            "an empty array",
            "POST",
            &obs,
            Some(&t1),
            b"[]".to_vec(),
            400,
            "bad_request",
            "no records",
        ),
        case(
            "broken JSON",
            "POST",
            &obs,
            Some(&t1),
            b"{\"robot\": \"1\", \"seq\"".to_vec(),
            400,
            "bad_request",
            "record",
        ),
        case(
            "NDJSON with a broken line 2",
            "POST",
            &obs,
            Some(&t1),
            ndjson_bad.into_bytes(),
            400,
            "bad_request",
            "line 2",
        )
        .content_type(Some("application/x-ndjson")),
        case(
            "a body over the limit",
            "POST",
            &obs,
            Some(&t1),
            vec![b' '; 9 << 20],
            413,
            "too_large",
            "body_limit_bytes",
        ),
        // --- repeats
        case(
            "a stored seq with other content",
            "POST",
            &obs,
            Some(&t1),
            body(&changed),
            409,
            "seq_conflict",
            "other content",
        ),
        // --- registration
        case(
            "a start covariance that is not PSD",
            "POST",
            &robots,
            Some(ADMIN),
            body(&json!({"id": "3", "start": bad_cov})),
            400,
            "bad_request",
            "positive semi-definite",
        ),
        case(
            "an asymmetric start covariance",
            "POST",
            &robots,
            Some(ADMIN),
            body(&json!({"id": "3", "start": asym_cov})),
            400,
            "bad_request",
            "symmetric",
        ),
        case(
            "t0 is a string",
            "POST",
            &robots,
            Some(ADMIN),
            body(&json!({"id": "3", "start": start, "t0": "now"})),
            400,
            "bad_request",
            "t0",
        ),
        case(
            "a robot id of 200 bytes",
            "POST",
            &robots,
            Some(ADMIN),
            body(&json!({"id": long_id, "start": start})),
            400,
            "bad_request",
            "id",
        ),
        case(
            "a robot id with a slash",
            "POST",
            &robots,
            Some(ADMIN),
            body(&json!({"id": "a/b", "start": start})),
            400,
            "bad_request",
            "id",
        ),
        case(
            "a robot id taken",
            "POST",
            &robots,
            Some(ADMIN),
            body(&json!({"id": "2", "start": start})),
            409,
            "conflict",
            "already registered",
        ),
        case(
            "a robot in an unknown run",
            "POST",
            "/v1/runs/nope/robots",
            Some(ADMIN),
            body(&json!({"id": "3", "start": start})),
            404,
            "not_found",
            "no run",
        ),
        // --- runs
        case(
            "a run name of 200 bytes",
            "POST",
            "/v1/runs",
            Some(ADMIN),
            run_body(&long_id),
            400,
            "bad_request",
            "name",
        ),
        case(
            "a header with 4 robots over a bound of 3",
            "POST",
            "/v1/runs",
            Some(ADMIN),
            body(&json!({"header": {
            "fleetslam_log": 1, "landmark_kind": "range_bearing_2d", "motion_model": "velocity",
            "robots": [{"id": "a"}, {"id": "b"}, {"id": "c"}, {"id": "d"}]}})),
            400,
            "bad_request",
            "max_robots_per_run",
        ),
        case(
            "an unknown config field",
            "POST",
            "/v1/runs",
            Some(ADMIN),
            body(&json!({"header": header, "config": {"colour": 1}})),
            400,
            "bad_request",
            "colour",
        ),
        // --- queries, paths, methods
        case(
            "a bad query value",
            "GET",
            "/v1/runs?limit=many",
            Some(READ),
            Vec::new(),
            400,
            "bad_request",
            "limit",
        ),
        case(
            "an unknown query field",
            "GET",
            format!("/v1/runs/{run}/state?colour=1"),
            Some(READ),
            Vec::new(),
            400,
            "bad_request",
            "colour",
        ),
        case(
            "a non-finite scrub time",
            "GET",
            format!("/v1/runs/{run}/state?t=inf"),
            Some(READ),
            Vec::new(),
            400,
            "bad_request",
            "finite",
        ),
        case(
            "a path that is not UTF-8",
            "GET",
            "/v1/runs/%FF%FE/state",
            Some(READ),
            Vec::new(),
            400,
            "bad_request",
            "UTF-8",
        ),
        case(
            "an unknown method",
            "FROBNICATE",
            "/v1/runs",
            Some(ADMIN),
            Vec::new(),
            405,
            "method_not_allowed",
            "/v1/runs",
        ),
        case(
            "an unknown API path",
            "GET",
            "/v1/nothing",
            Some(READ),
            Vec::new(),
            404,
            "not_found",
            "/v1/nothing",
        ),
    ];
    assert!(cases.len() >= 40, "{} cases", cases.len());
    eprintln!("{} hostile cases", cases.len());

    let mut failures = Vec::new();
    for c in &cases {
        let before = srv.counts(&run).await;
        let a = srv
            .send(
                c.method,
                &c.path,
                c.token.as_deref(),
                c.content_type,
                &c.headers,
                c.body.clone(),
            )
            .await;
        let after = srv.counts(&run).await;
        let ok = a.status.as_u16() == c.status
            && a.json
            && a.code == c.code
            && a.message.contains(c.names)
            && before == after;
        if !ok {
            failures.push(format!(
                "{}: got {} json={} code={:?} message={:?} (stored {before:?} -> {after:?}); \
                 want {} {:?} naming {:?}",
                c.name, a.status, a.json, a.code, a.message, c.status, c.code, c.names
            ));
        }
        // The run still takes and applies good records.
        let a = srv.json("POST", &obs, Some(&t1), rec(next)).await;
        assert_eq!(a.status, StatusCode::OK, "after {:?}: {:?}", c.name, a.body);
        assert_eq!(a.body["acks"][0]["status"], "stored", "after {:?}", c.name);
        next += 1;
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));

    // The good ones still behave: an identical repeat is a duplicate, the retried
    // registration goes through, bounds on robots and runs hold.
    let a = srv.json("POST", &obs, Some(&t1), rec(0)).await;
    assert_eq!(a.body["acks"][0]["status"], "duplicate", "{:?}", a.body);
    srv.register(&run, ADMIN, "3", &log).await;
    let a = srv
        .json(
            "POST",
            &robots,
            Some(ADMIN),
            json!({"id": "4", "start": start}),
        )
        .await;
    assert_eq!(a.status, StatusCode::CONFLICT, "{:?}", a.body);
    assert!(a.message.contains("max_robots_per_run"), "{}", a.message);
    srv.create_run(header.clone()).await;
    let a = srv
        .json("POST", "/v1/runs", Some(ADMIN), json!({"header": header}))
        .await;
    assert_eq!(a.status, StatusCode::SERVICE_UNAVAILABLE, "{:?}", a.body);
    assert_eq!(a.code, "busy");
    assert!(a.message.contains("max_active_runs"), "{}", a.message);
    // Tokens: lower-case scheme, the read token in the query for a browser's websocket.
    let a = srv
        .send(
            "GET",
            "/v1/runs",
            None,
            None,
            &[("authorization", &format!("bearer {READ}"))],
            Vec::new(),
        )
        .await;
    assert_eq!(a.status, StatusCode::OK, "{:?}", a.body);
    let a = srv
        .send(
            "GET",
            &format!("/v1/runs/{run}/timeline?access_token={READ}"),
            None,
            None,
            &[],
            Vec::new(),
        )
        .await;
    assert_eq!(a.status, StatusCode::OK, "{:?}", a.body);
    // The seq conflict is counted in the robot's status; unknown methods share one label.
    let a = srv
        .send(
            "GET",
            &format!("/v1/runs/{run}/state"),
            Some(READ),
            None,
            &[],
            Vec::new(),
        )
        .await;
    let r1 = a.body["robots"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["id"] == "1")
        .unwrap()
        .clone();
    assert_eq!(r1["seq_conflicts"], 1, "{r1}");
    let metrics = srv
        .client
        .get(format!("{}/metrics", srv.base))
        .bearer_auth(READ)
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(!metrics.contains("FROBNICATE"), "{metrics}");
    assert!(metrics.contains("method=\"other\""), "{metrics}");

    // Every good record was applied: robot 1's trajectory has its start and each record.
    let a = srv
        .json(
            "POST",
            &format!("/v1/runs/{run}/end"),
            Some(ADMIN),
            json!({}),
        )
        .await;
    assert_eq!(a.status, StatusCode::NO_CONTENT, "{:?}", a.body);
    let a = srv
        .send(
            "GET",
            &format!("/v1/runs/{run}/trajectories"),
            Some(READ),
            None,
            &[],
            Vec::new(),
        )
        .await;
    assert_eq!(
        a.body["robots"]["1"].as_array().map(Vec::len),
        Some(next + 1),
        "robot 1's trajectory"
    );
    srv.running.stop().await.unwrap();
}

#[tokio::test]
async fn serving_a_network_address_needs_an_admin_token() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        bind: "0.0.0.0:0".into(),
        data_dir: dir.path().to_path_buf(),
        ..ServerConfig::default()
    };
    let e = start(&cfg).await.unwrap_err().to_string();
    assert!(e.contains("admin token"), "{e}");
    let cfg = ServerConfig {
        admin_token: Some("short".into()),
        ..cfg
    };
    let e = start(&cfg).await.unwrap_err().to_string();
    assert!(e.contains("at least 16"), "{e}");
}

/// Mutations of a good record: each returns a body and a content type.
fn mutate(rng: &mut rand_chacha::ChaCha8Rng, good: &Value, seq: u64) -> (Vec<u8>, &'static str) {
    let mut r = good.clone();
    r["seq"] = json!(seq);
    let wild = [
        json!(null),
        json!(-1),
        json!(0),
        json!(1e308),
        json!(-1e308),
        json!(u64::MAX),
        json!(i64::MIN),
        json!("x"),
        json!(""),
        json!([]),
        json!({}),
        json!([1.0]),
        json!([1.0, 2.0, 3.0, 4.0]),
        json!(true),
        json!("9".repeat(400)),
    ];
    let pick = |rng: &mut rand_chacha::ChaCha8Rng| wild[rng.random_range(0..wild.len())].clone();
    let fields = [
        "robot",
        "seq",
        "t",
        "motion",
        "landmarks",
        "robots",
        "extra",
    ];
    match rng.random_range(0..12) {
        0..=3 => {
            let f = fields[rng.random_range(0..fields.len())];
            r[f] = pick(rng);
        }
        4 => {
            let f = fields[rng.random_range(0..fields.len())];
            if let Some(o) = r.as_object_mut() {
                o.remove(f);
            }
        }
        5 => {
            let n = rng.random_range(0..5);
            let m = json!({"velocity": [[pick(rng), pick(rng), pick(rng)]]});
            r["motion"] = if n == 0 {
                json!({"ackermann": [[1.0, 0.1, 1.0]]})
            } else {
                m
            };
        }
        6 => {
            let n = rng.random_range(0..300);
            r["landmarks"] = json!(
                (0..n)
                    .map(|_| json!({"id": pick(rng), "z": pick(rng)}))
                    .collect::<Vec<_>>()
            );
        }
        7 => {
            r["robots"] = json!([{"robot": pick(rng), "z": pick(rng)}]);
        }
        8 => {
            // Truncated or corrupted bytes.
            let mut b = serde_json::to_vec(&r).unwrap();
            let cut = rng.random_range(0..b.len());
            b.truncate(cut);
            if rng.random_bool(0.5) && !b.is_empty() {
                let i = rng.random_range(0..b.len());
                b[i] = rng.random();
            }
            return (b, "application/json");
        }
        9 => {
            let n = rng.random_range(0..64);
            return ((0..n).map(|_| rng.random()).collect(), "application/json");
        }
        10 => {
            let cts = [
                "application/x-ndjson",
                "text/plain",
                "application/json; charset=latin1",
                "",
            ];
            let ct = cts[rng.random_range(0..cts.len())];
            let b = format!("{}\n{}\n", r, pick(rng));
            return (b.into_bytes(), ct);
        }
        _ => {
            r["t"] = json!(good["t"].as_f64().unwrap() + rng.random_range(-5000.0..5000.0));
        }
    }
    (serde_json::to_vec(&json!([r])).unwrap(), "application/json")
}

#[tokio::test]
async fn fuzzed_records_and_bodies_never_break_the_server() {
    let log = sim_log();
    let srv = serve(|c| {
        c.reorder_window_ms = 60_000;
    })
    .await;
    let header = serde_json::to_value(&log.header).unwrap();
    let (run, enroll) = srv.create_run(header).await;
    let t1 = srv.register(&run, &enroll, "1", &log).await;
    let t2 = srv.register(&run, &enroll, "2", &log).await;
    let obs = format!("/v1/runs/{run}/observations");
    let good1: Vec<Value> = log
        .records
        .iter()
        .filter(|r| r.robot == "1")
        .map(|r| serde_json::to_value(r).unwrap())
        .collect();
    let good2: Vec<Value> = log
        .records
        .iter()
        .filter(|r| r.robot == "2")
        .map(|r| serde_json::to_value(r).unwrap())
        .collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2026);
    let requests = 10_000;
    let (mut server_errors, mut dropped, mut next1, mut statuses) = (
        0,
        0,
        0usize,
        std::collections::BTreeMap::<u16, usize>::new(),
    );
    for i in 0..requests {
        // Robot 1 posts its good records in between; robot 2 is the fuzzer.
        if i % 20 == 0 && next1 < good1.len() {
            let a = srv
                .json("POST", &obs, Some(&t1), good1[next1].clone())
                .await;
            assert_eq!(
                a.status,
                StatusCode::OK,
                "good record {next1}: {:?}",
                a.body
            );
            next1 += 1;
        }
        let base = &good2[rng.random_range(0..good2.len())];
        let seq = rng.random_range(0..2 * good2.len() as u64);
        let (b, ct) = mutate(&mut rng, base, seq);
        let (path, token) = match rng.random_range(0..20) {
            0 => (format!("/v1/runs/{run}/robots"), Some(enroll.as_str())),
            1 => ("/v1/runs".to_string(), Some(ADMIN)),
            2 => (obs.clone(), None),
            _ => (obs.clone(), Some(t2.as_str())),
        };
        let mut req = srv.client.post(format!("{}{path}", srv.base)).body(b);
        if !ct.is_empty() {
            req = req.header("content-type", ct);
        }
        if let Some(t) = token {
            req = req.bearer_auth(t);
        }
        match req.send().await {
            Ok(resp) => {
                let s = resp.status();
                *statuses.entry(s.as_u16()).or_default() += 1;
                if s.is_server_error() {
                    server_errors += 1;
                    eprintln!("{s}: {}", resp.text().await.unwrap_or_default());
                } else if !s.is_success() {
                    let v: Value = resp.json().await.expect("every refusal is JSON");
                    assert!(v["error"].is_string() || v["acks"].is_array(), "{v}");
                }
            }
            Err(e) => {
                dropped += 1;
                eprintln!("request {i}: {e}");
            }
        }
    }
    eprintln!("statuses: {statuses:?}");
    assert_eq!((server_errors, dropped), (0, 0), "{statuses:?}");
    // Refusals of every kind were exercised, and some mutated records were stored.
    for s in [200, 400, 401, 409, 415] {
        assert!(statuses.contains_key(&s), "no {s} in {statuses:?}");
    }
    // The rest of robot 1's good records, then the end: each was applied.
    while next1 < good1.len() {
        let a = srv
            .json("POST", &obs, Some(&t1), good1[next1].clone())
            .await;
        assert_eq!(a.status, StatusCode::OK, "{:?}", a.body);
        next1 += 1;
    }
    let a = srv
        .json(
            "POST",
            &format!("/v1/runs/{run}/end"),
            Some(ADMIN),
            json!({}),
        )
        .await;
    assert_eq!(a.status, StatusCode::NO_CONTENT, "{:?}", a.body);
    let a = srv
        .send(
            "GET",
            &format!("/v1/runs/{run}/trajectories"),
            None,
            None,
            &[],
            Vec::new(),
        )
        .await;
    assert_eq!(
        a.body["robots"]["1"].as_array().map(Vec::len),
        Some(good1.len() + 1)
    );
    srv.running.stop().await.unwrap();
}
