//! The server is killed hard (SIGKILL) in the middle of a multi-robot replay and started
//! again on the same store; the replay client resumes (it re-sends what was not
//! acknowledged). Every record is then stored exactly once and the run's result equals an
//! uninterrupted offline run's, bit for bit. On SQLite always, on PostgreSQL when
//! FLEETSLAM_TEST_POSTGRES_URL is set.

mod common;
use common::{assert_equals_offline, assert_stored_once, get_json, ok, serve};
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_fleetslam");

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn crash_and_resume(dir: &Path, store: &[&str]) {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let sim = dir.join("sim");
    ok(&[
        "simulate",
        "--robots",
        "3",
        "--duration",
        "40",
        "--seed",
        "4",
        "--out",
        sim.to_str().unwrap(),
    ]);
    let log = sim.join("log.ndjson");
    let records = std::fs::read_to_string(&log).unwrap().lines().count() - 1;
    let port = free_port();
    let url = format!("http://127.0.0.1:{port}");
    let bind = format!("127.0.0.1:{port}");
    let (mut server, _) = serve(&bind, store);

    // The robots post in real time, 8x faster: the replay takes ~5 s.
    let mut replay = Command::new(BIN)
        .args(["replay", log.to_str().unwrap(), "--server", &url])
        .args([
            "--speed",
            "8",
            "--batch",
            "5",
            "--particles",
            "50",
            "--seed",
            "5",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(replay.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    let run = line
        .strip_prefix("run ")
        .unwrap_or_else(|| panic!("no run id in {line:?}"))
        .trim()
        .to_string();

    // Kill the server once a quarter of the records are in.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let st = get_json(&rt, &format!("{url}/v1/runs/{run}/state"));
        if st["applied"].as_u64().unwrap_or(0) as usize > records / 4 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the replay never got going: {st}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    server.0.kill().unwrap(); // SIGKILL
    server.0.wait().unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let _server = serve(&bind, store);

    // The client resumes by itself; it ends the run when its log is done.
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(s) = replay.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < deadline, "the replay did not finish");
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut out, &mut rest).unwrap();
    assert!(status.success(), "replay failed: {rest}");
    assert!(
        rest.contains(&format!("{records} records sent, {records} acknowledged")),
        "{rest}"
    );
    assert!(
        !rest.contains(", 0 requests retried"),
        "the client never had to retry: {rest}"
    );

    // Every record exactly once; the result equals the uninterrupted offline run.
    let exported = dir.join("exported");
    ok(&[
        "export",
        &run,
        "--server",
        &url,
        "--out",
        exported.to_str().unwrap(),
    ]);
    assert_stored_once(&exported, records, "the crashed run");
    assert_equals_offline(&log, &exported, &dir.join("offline"), "the crashed run");
}

#[test]
fn sigkill_mid_replay_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    crash_and_resume(dir.path(), &["--data-dir", data.to_str().unwrap()]);
}

#[test]
fn sigkill_mid_replay_postgres() {
    let Ok(url) = std::env::var("FLEETSLAM_TEST_POSTGRES_URL") else {
        eprintln!(
            "PostgreSQL skipped: set FLEETSLAM_TEST_POSTGRES_URL to run this test against it"
        );
        return;
    };
    let rt = tokio::runtime::Runtime::new().unwrap();
    let name = format!("fleetslam_crash_{}", std::process::id());
    let db = rt
        .block_on(fleetslam_store::admin::create_postgres_database(
            &url, &name,
        ))
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let outcome = std::panic::catch_unwind(|| {
        crash_and_resume(dir.path(), &["--database-url", &db]);
    });
    rt.block_on(fleetslam_store::admin::drop_postgres_database(&url, &name))
        .unwrap();
    if let Err(e) = outcome {
        std::panic::resume_unwind(e);
    }
}
