//! Live runs in Foxglove (`foxglove_bind`): a client speaking the Foxglove WebSocket
//! protocol (the `foxglove` crate's own message types, over tokio-tungstenite) sees the
//! run's topics advertised, subscribes, and receives the robots' poses, the filter's series
//! and the map while robots post over HTTP; the poses and the last map are the server's own,
//! value for value, and the run's topics go when it ends.

mod common;

use fleetslam_core::log::Log;
use fleetslam_data::sim::{SimConfig, simulate};
use fleetslam_server::config::ServerConfig;
use fleetslam_server::server::start;
use foxglove::Decode;
use foxglove::schemas::{PoseInFrame, SceneUpdate};
use foxglove::ws_protocol::client::{Subscribe, Subscription};
use foxglove::ws_protocol::server::ServerMessage;
use futures::{SinkExt, StreamExt};
use serde_json::{Value, json};
use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

/// The data time of a foxglove timestamp [s].
fn secs(t: &foxglove::schemas::Timestamp) -> f64 {
    f64::from(t.sec()) + f64::from(t.nsec()) * 1e-9
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn foxglove_client_receives_poses_filter_and_map_of_a_live_run() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        bind: "127.0.0.1:0".into(),
        data_dir: dir.path().to_path_buf(),
        foxglove_bind: Some("127.0.0.1:0".into()),
        state_rate_hz: 20.0,
        ..ServerConfig::default()
    };
    let running = start(&cfg).await.unwrap();
    let base = format!("http://{}", running.addr);
    let fox = running.foxglove.expect("the Foxglove server is up");
    let http = reqwest::Client::new();

    let mut log: Log = simulate(&SimConfig {
        robots: 2,
        landmarks: 12,
        duration: 20.0,
        seed: 7,
        ..SimConfig::default()
    })
    .unwrap()
    .log;
    log.sort();
    let (run, tokens) = common::setup_over_http(&http, &base, &log, json!({"particles": 30})).await;
    let tokens: BTreeMap<String, String> = tokens.into_iter().collect();
    let post = |records: Vec<fleetslam_core::log::Record>| {
        let (http, base, run, tokens) = (http.clone(), base.clone(), run.clone(), tokens.clone());
        async move {
            for r in records {
                let resp = http
                    .post(format!("{base}/v1/runs/{run}/observations"))
                    .bearer_auth(&tokens[&r.robot])
                    .json(&[&r])
                    .send()
                    .await
                    .unwrap();
                assert!(resp.status().is_success(), "{}", resp.text().await.unwrap());
            }
        }
    };
    let half = log.records.len() / 2;
    post(log.records[..half].to_vec()).await;

    // Connect, and wait for the run's topics.
    let mut req = format!("ws://{fox}").into_client_request().unwrap();
    req.headers_mut()
        .insert("sec-websocket-protocol", "foxglove.sdk.v1".parse().unwrap());
    let (mut ws, _) = tokio_tungstenite::connect_async(req).await.unwrap();
    let prefix = format!("/run/{run}");
    let wanted: BTreeSet<String> = ["/landmarks", "/filter"]
        .iter()
        .map(|t| format!("{prefix}{t}"))
        .chain(
            log.header
                .robots
                .iter()
                .map(|r| format!("{prefix}/robot/{}/pose", r.id)),
        )
        .collect();
    let mut topics: BTreeMap<u64, String> = BTreeMap::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while !wanted.iter().all(|t| topics.values().any(|x| x == t)) {
        let msg = tokio::time::timeout_at(deadline, ws.next())
            .await
            .unwrap_or_else(|_| panic!("not advertised: {wanted:?}; advertised: {topics:?}"))
            .unwrap()
            .unwrap();
        if let Ok(ServerMessage::Advertise(a)) = ServerMessage::try_from(&msg) {
            for c in a.channels {
                assert!(
                    c.schema_name == "foxglove.PoseInFrame"
                        || c.schema_name == "foxglove.SceneUpdate"
                        || c.schema_name == "foxglove.FrameTransform"
                        || c.schema_name == "foxglove.PosesInFrame"
                        || c.schema_name == "fleetslam.FilterStats",
                    "{}: {}",
                    c.topic,
                    c.schema_name
                );
                topics.insert(c.id, c.topic.to_string());
            }
        }
    }
    // Subscribe to them (subscription id = channel id).
    let subs: Vec<Subscription> = topics
        .iter()
        .filter(|(_, t)| wanted.contains(*t))
        .map(|(id, _)| Subscription::new(*id as u32, *id))
        .collect();
    ws.send(Message::from(&Subscribe::new(subs))).await.unwrap();
    // Let the subscription land before the rest is posted.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut rest = Some(tokio::spawn(post(log.records[half..].to_vec())));

    // Receive until the run's topics go (the run is ended once its records are in).
    let mut poses: BTreeMap<String, Vec<PoseInFrame>> = BTreeMap::new();
    let mut filter: Vec<Value> = Vec::new();
    let mut last_map: Option<SceneUpdate> = None;
    let mut ended = false;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    loop {
        let msg = tokio::time::timeout_at(deadline, ws.next())
            .await
            .expect("the run's topics never went")
            .unwrap()
            .unwrap();
        match ServerMessage::try_from(&msg) {
            Ok(ServerMessage::MessageData(m)) => {
                let topic = &topics[&u64::from(m.subscription_id)];
                let rest = topic.strip_prefix(&prefix).unwrap();
                if rest == "/landmarks" {
                    last_map = Some(SceneUpdate::decode(&m.data[..]).unwrap());
                } else if rest == "/filter" {
                    filter.push(serde_json::from_slice(&m.data).unwrap());
                } else {
                    let robot = rest
                        .strip_prefix("/robot/")
                        .and_then(|r| r.strip_suffix("/pose"))
                        .unwrap();
                    poses
                        .entry(robot.to_string())
                        .or_default()
                        .push(PoseInFrame::decode(&m.data[..]).unwrap());
                }
            }
            Ok(ServerMessage::Unadvertise(u)) => {
                let gone: BTreeSet<&str> = u
                    .channel_ids
                    .iter()
                    .filter_map(|id| topics.get(id).map(String::as_str))
                    .collect();
                if gone.contains(format!("{prefix}/landmarks").as_str()) {
                    break;
                }
            }
            _ => {}
        }
        if let Some(posting) = rest.take_if(|r| r.is_finished()) {
            posting.await.unwrap();
            let resp = http
                .post(format!("{base}/v1/runs/{run}/end"))
                .send()
                .await
                .unwrap();
            assert!(resp.status().is_success(), "{}", resp.text().await.unwrap());
            ended = true;
        }
    }
    assert!(ended);

    // Each robot's poses are the tail of its trajectory, value for value: every point from
    // the subscription on (at least the records posted after it), through the last one.
    let get = |path: String| {
        let http = http.clone();
        async move {
            let v: Value = http.get(path).send().await.unwrap().json().await.unwrap();
            v
        }
    };
    let traj = get(format!("{base}/v1/runs/{run}/trajectories")).await;
    for r in &log.header.robots {
        let got: Vec<[f64; 4]> = poses[&r.id]
            .iter()
            .map(|p| {
                let pose = p.pose.as_ref().unwrap();
                let (pos, q) = (
                    pose.position.as_ref().unwrap(),
                    pose.orientation.as_ref().unwrap(),
                );
                [
                    secs(p.timestamp.as_ref().unwrap()),
                    pos.x,
                    pos.y,
                    2.0 * q.z.atan2(q.w),
                ]
            })
            .collect();
        let pts: Vec<[f64; 4]> = serde_json::from_value(traj["robots"][&r.id].clone()).unwrap();
        let after = log.records[half..]
            .iter()
            .filter(|x| x.robot == r.id)
            .count();
        assert!(
            got.len() >= after && got.len() <= pts.len(),
            "robot {}: {} poses, {after} records posted after subscribing, {} points",
            r.id,
            got.len(),
            pts.len()
        );
        for (g, w) in got.iter().zip(&pts[pts.len() - got.len()..]) {
            assert!((g[0] - w[0]).abs() < 1e-6, "robot {}: {g:?} vs {w:?}", r.id);
            assert_eq!((g[1], g[2]), (w[1], w[2]), "robot {}", r.id);
            let dtheta = (g[3] - w[3] + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            assert!(dtheta.abs() < 1e-9, "robot {}: {g:?} vs {w:?}", r.id);
        }
    }
    // The filter's series likewise: the tail of GET series, through the run's last record.
    let series = get(format!("{base}/v1/runs/{run}/series")).await;
    let points: Vec<[f64; 4]> = serde_json::from_value(series["points"].clone()).unwrap();
    let got: Vec<[f64; 4]> = filter
        .iter()
        .map(|m| ["t", "ess", "step_ms", "landmarks"].map(|k| m[k].as_f64().unwrap()))
        .collect();
    assert!(
        got.len() >= log.records.len() - half && got.len() <= points.len(),
        "{} filter points of {}",
        got.len(),
        points.len()
    );
    assert_eq!(got[..], points[points.len() - got.len()..]);
    let state = get(format!("{base}/v1/runs/{run}/state")).await;
    // The last map is the final state's, landmark for landmark.
    let map = last_map.expect("a map arrived");
    let want: Vec<[f64; 2]> = state["landmarks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| {
            [
                l["mean"][0].as_f64().unwrap(),
                l["mean"][1].as_f64().unwrap(),
            ]
        })
        .collect();
    let got: Vec<[f64; 2]> = map
        .entities
        .iter()
        .map(|e| {
            let p = e.cylinders[0]
                .pose
                .as_ref()
                .unwrap()
                .position
                .as_ref()
                .unwrap();
            [p.x, p.y]
        })
        .collect();
    assert!(!want.is_empty());
    assert_eq!(got, want);
    running.stop().await.unwrap();
}

#[test]
fn foxglove_on_a_public_address_needs_open_reads() {
    let mut cfg = ServerConfig {
        foxglove_bind: Some("0.0.0.0:8765".into()),
        ..ServerConfig::default()
    };
    let err = cfg.validate().unwrap_err();
    assert!(err.contains("no authentication"), "{err}");
    cfg.read_access = fleetslam_server::auth::ReadAccess::Open;
    cfg.validate().unwrap();
    cfg.foxglove_bind = Some("localhost:8765".into());
    let err = cfg.validate().unwrap_err();
    assert!(err.contains("foxglove_bind must be host:port"), "{err}");
}
