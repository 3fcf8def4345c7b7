//! Measures acknowledged appends: 5 concurrent writers (robots) post ONE record at a time (or
//! `RECORDS_PER_APPEND` at a time, as robots posting arrays and `fleetslam replay --batch`
//! do) and each waits for its acknowledgement (committed records) before sending the next, as
//! robots talking to the server do. Prints records per second and the ack latency p50 / p99.
//!
//! ```sh
//! cargo run --release -p fleetslam-store --example append_throughput -- [POSTGRES_URL] \
//!     [RECORDS_PER_WRITER [RECORDS_PER_APPEND]]
//! ```
//!
//! SQLite is measured in a temporary directory always; PostgreSQL when a URL is given, in a
//! scratch database created next to the URL's and dropped afterwards.

use std::error::Error;
use std::time::{Duration, Instant};

use fleetslam_store::{NewObservation, NewRun, Store};

const WRITERS: usize = 5;

type Result<T> = std::result::Result<T, Box<dyn Error + Send + Sync>>;

#[tokio::main]
async fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let pg_url = args.iter().find(|a| a.contains("://")).cloned();
    let mut numbers = args.iter().filter(|a| !a.contains("://"));
    let per_writer: i64 = match numbers.next() {
        Some(n) => n.parse()?,
        None => 2000,
    };
    let per_append: i64 = match numbers.next() {
        Some(n) => n.parse()?,
        None => 1,
    };
    if per_append < 1 {
        return Err("RECORDS_PER_APPEND must be at least 1".into());
    }

    let dir = tempfile::tempdir()?;
    let store = Store::open_default(dir.path()).await?;
    measure(&store, per_writer, per_append).await?;
    store.close().await;

    match pg_url {
        Some(url) => {
            let name = format!("fleetslam_bench_{}", std::process::id());
            let db = fleetslam_store::admin::create_postgres_database(&url, &name).await?;
            let result = async {
                let store = Store::open(&db).await?;
                let r = measure(&store, per_writer, per_append).await;
                store.close().await;
                r
            }
            .await;
            fleetslam_store::admin::drop_postgres_database(&url, &name).await?;
            result?;
        }
        None => println!("postgres: skipped (pass a postgres:// URL to measure it)"),
    }
    Ok(())
}

/// Runs the writers against `store` and prints the figures.
async fn measure(store: &Store, per_writer: i64, per_append: i64) -> Result<()> {
    let run_id = format!("throughput-{}", std::process::id());
    store
        .create_run(&NewRun {
            id: run_id.clone(),
            name: Some("append throughput".into()),
            config: serde_json::json!({}),
            header: None,
        })
        .await?;
    let body = r#"{"robot":"r","seq":0,"t":0.0,"motion":{"velocity":[[0.12,0.0,0.2]]},"landmarks":[{"id":7,"z":[2.13,0.31]},{"z":[3.9,-0.2]}]}"#;
    let before = store.writer_stats();
    let start = Instant::now();
    let mut tasks = Vec::new();
    for w in 0..WRITERS {
        let store = store.clone();
        let run_id = run_id.clone();
        tasks.push(tokio::spawn(async move {
            let robot = format!("robot-{w}");
            let mut latencies = Vec::with_capacity(per_writer as usize);
            let mut seq = 0;
            while seq < per_writer {
                let recs: Vec<NewObservation> = (seq..(seq + per_append).min(per_writer))
                    .map(|seq| NewObservation {
                        robot_id: robot.clone(),
                        seq,
                        t: seq as f64 * 0.05,
                        body: body.to_owned(),
                    })
                    .collect();
                seq += recs.len() as i64;
                let sent = Instant::now();
                store.append(&run_id, recs).await?;
                latencies.push(sent.elapsed());
            }
            Ok::<_, fleetslam_store::StoreError>(latencies)
        }));
    }
    let mut latencies = Vec::new();
    for task in tasks {
        latencies.extend(task.await??);
    }
    let wall = start.elapsed();
    let stats = store.writer_stats();
    latencies.sort_unstable();
    let total = WRITERS * per_writer as usize;
    let commits = stats.commits - before.commits;
    println!(
        "{:8}: {} writers x {} records, {} per append: {:.0} acked records/s, ack p50 {:.2} ms, \
         p99 {:.2} ms, {} commits ({:.1} records/commit)",
        store.backend(),
        WRITERS,
        per_writer,
        per_append,
        total as f64 / wall.as_secs_f64(),
        ms(percentile(&latencies, 0.50)),
        ms(percentile(&latencies, 0.99)),
        commits,
        total as f64 / commits.max(1) as f64,
    );
    store.delete_run(&run_id).await?;
    Ok(())
}

fn percentile(sorted: &[Duration], q: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}
