//! A cluster on this machine's loopback ports: a 3-node NATS JetStream cluster and
//! `fleetslam serve --cluster` replicas, as child processes. Used by `fleetslam
//! cluster-bench` and by the cluster test (`tests/cluster.rs` includes this file).
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// A child process, killed (SIGKILL) on drop.
pub struct Proc(pub Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Proc {
    /// SIGKILL, and wait for it to be gone.
    pub fn kill(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

/// The `nats-server` binary, where Debian's package or a manual install puts it.
pub fn nats_server() -> Option<PathBuf> {
    [
        "/usr/sbin/nats-server",
        "/usr/bin/nats-server",
        "/usr/local/bin/nats-server",
    ]
    .into_iter()
    .map(PathBuf::from)
    .find(|p| p.exists())
}

/// Starts `nodes` JetStream nodes clustered on loopback ports, each storing in `dir/natsI`
/// and logging to `dir/natsI.log`; returns them and their client URLs.
pub fn nats_cluster(
    bin: &Path,
    dir: &Path,
    nodes: usize,
) -> std::io::Result<(Vec<Proc>, Vec<String>)> {
    let client: Vec<u16> = (0..nodes).map(|_| free_port()).collect();
    let routes: Vec<u16> = (0..nodes).map(|_| free_port()).collect();
    let all_routes = routes
        .iter()
        .map(|p| format!("nats://127.0.0.1:{p}"))
        .collect::<Vec<_>>()
        .join(",");
    let mut procs = Vec::new();
    for i in 0..nodes {
        let store = dir.join(format!("nats{i}"));
        std::fs::create_dir_all(&store)?;
        let log = std::fs::File::create(dir.join(format!("nats{i}.log")))?;
        let mut cmd = Command::new(bin);
        cmd.args(["-a", "127.0.0.1", "-p", &client[i].to_string(), "-js"])
            .arg("-sd")
            .arg(&store)
            .args(["-n", &format!("n{i}")]);
        if nodes > 1 {
            cmd.args(["--cluster_name", "fleetslam"])
                .args(["--cluster", &format!("nats://127.0.0.1:{}", routes[i])])
                .args(["--routes", &all_routes]);
        }
        procs.push(Proc(cmd.stdout(Stdio::null()).stderr(log).spawn()?));
    }
    let urls = client
        .iter()
        .map(|p| format!("nats://127.0.0.1:{p}"))
        .collect();
    Ok((procs, urls))
}

/// Starts replica `i` (`fleetslam serve --cluster`, logging to `dir/replicaI.log`) and
/// returns once it listens, with its base URL.
pub fn replica(
    fleetslam: &Path,
    dir: &Path,
    i: usize,
    nats: &str,
    db: &str,
    stream_replicas: usize,
    env: &[(&str, &str)],
) -> Result<(Proc, String), String> {
    let bind = format!("127.0.0.1:{}", free_port());
    let log_path = dir.join(format!("replica{i}.log"));
    let log = std::fs::File::create(&log_path).map_err(|e| e.to_string())?;
    let mut cmd = Command::new(fleetslam);
    cmd.args(["serve", "--bind", &bind, "--database-url", db])
        .args([
            "--cluster",
            "--nats",
            nats,
            "--replica-id",
            &format!("r{i}"),
        ])
        .args(["--stream-replicas", &stream_replicas.to_string()])
        .env("RUST_LOG", "warn,fleetslam_server=info");
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = Proc(
        cmd.stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .map_err(|e| e.to_string())?,
    );
    let mut line = String::new();
    let stdout = child.0.stdout.take().ok_or("no stdout")?;
    BufReader::new(stdout)
        .read_line(&mut line)
        .map_err(|e| e.to_string())?;
    if !line.contains("serving on") {
        return Err(format!(
            "replica {i} did not start: {line:?}; its log:\n{}",
            std::fs::read_to_string(&log_path).unwrap_or_default()
        ));
    }
    Ok((child, format!("http://{bind}")))
}
