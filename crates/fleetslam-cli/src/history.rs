//! `fleetslam runs`, `export` and `delete`: through a server's API (`--server URL`), or
//! straight on a store (`--data-dir`, `--database-url`) by calling the same API in-process,
//! so both paths give the same answers.

use anyhow::{Context, Result, bail};
use axum::body::Body;
use axum::http::{Method, Request, StatusCode};
use clap::Args;
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_store::Store;
use serde_json::Value;
use std::io::Read;
use std::path::PathBuf;
use tower::ServiceExt;

/// Where the runs are.
#[derive(Debug, Args)]
pub struct Target {
    /// A running server's base URL.
    #[arg(long, conflicts_with_all = ["data_dir", "database_url"])]
    server: Option<String>,
    /// The embedded store's directory (when no --server or --database-url is given: `data`).
    #[arg(long)]
    data_dir: Option<PathBuf>,
    /// A `postgres://` or `sqlite://` store URL.
    #[arg(long, conflicts_with = "data_dir")]
    database_url: Option<String>,
    /// Sent with every request: reads and, for `delete`, the admin action.
    #[arg(long, env = "FLEETSLAM_ADMIN_TOKEN")]
    admin_token: Option<String>,
    /// Sent when no admin token is given: enough for `runs` and `export` on a server whose
    /// reads need a token.
    #[arg(long, env = "FLEETSLAM_READ_TOKEN")]
    read_token: Option<String>,
}

enum Api {
    Http {
        base: String,
        admin: Option<String>,
        client: reqwest::Client,
    },
    Local {
        router: axum::Router,
        store: Store,
    },
}

impl Target {
    async fn open(&self) -> Result<Api> {
        if let Some(s) = &self.server {
            return Ok(Api::Http {
                base: s.trim_end_matches('/').to_string(),
                admin: self.admin_token.clone().or_else(|| self.read_token.clone()),
                client: reqwest::Client::new(),
            });
        }
        let store = match &self.database_url {
            Some(url) => Store::open(url).await?,
            None => {
                let dir = self
                    .data_dir
                    .clone()
                    .unwrap_or_else(|| PathBuf::from("data"));
                if !dir.join(fleetslam_store::DEFAULT_DB_FILE).is_file() {
                    bail!(
                        "no store in {}: give --data-dir, --database-url or --server",
                        dir.display()
                    );
                }
                Store::open_default(&dir).await?
            }
        };
        // No recovery: this process only reads and deletes.
        let router = app(AppState::new(store.clone(), ApiConfig::default()));
        Ok(Api::Local { router, store })
    }
}

impl Api {
    async fn call(&self, method: Method, path: &str) -> Result<(StatusCode, Vec<u8>)> {
        match self {
            Api::Http {
                base,
                admin,
                client,
            } => {
                let mut req = client.request(method, format!("{base}{path}"));
                if let Some(t) = admin {
                    req = req.bearer_auth(t);
                }
                let resp = req
                    .send()
                    .await
                    .with_context(|| format!("reaching {base}"))?;
                let status = StatusCode::from_u16(resp.status().as_u16())?;
                Ok((status, resp.bytes().await?.to_vec()))
            }
            Api::Local { router, .. } => {
                let req = Request::builder()
                    .method(method)
                    .uri(path)
                    .body(Body::empty())?;
                let resp = router.clone().oneshot(req).await?;
                let status = resp.status();
                let body = axum::body::to_bytes(resp.into_body(), usize::MAX).await?;
                Ok((status, body.to_vec()))
            }
        }
    }

    /// The body of a successful answer, or the API's error message.
    async fn ok(&self, method: Method, path: &str) -> Result<Vec<u8>> {
        let (status, body) = self.call(method, path).await?;
        if !status.is_success() {
            let v: Value = serde_json::from_slice(&body).unwrap_or(Value::Null);
            bail!(
                "{status}: {}",
                v["message"]
                    .as_str()
                    .map_or_else(|| String::from_utf8_lossy(&body).into_owned(), String::from)
            );
        }
        Ok(body)
    }

    async fn close(self) {
        if let Api::Local { store, .. } = self {
            store.close().await;
        }
    }
}

#[derive(Debug, Args)]
pub struct RunsArgs {
    #[command(flatten)]
    target: Target,
    /// Only runs with this status: active, ended, failed.
    #[arg(long)]
    status: Option<String>,
    #[arg(long, default_value_t = 50)]
    limit: usize,
    /// Print the JSON answer instead of a table.
    #[arg(long)]
    json: bool,
}

pub async fn cmd_runs(a: RunsArgs) -> Result<()> {
    let api = a.target.open().await?;
    let mut path = format!("/v1/runs?limit={}", a.limit);
    if let Some(s) = &a.status {
        path.push_str(&format!("&status={s}"));
    }
    let body = api.ok(Method::GET, &path).await?;
    api.close().await;
    let v: Value = serde_json::from_slice(&body)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    println!(
        "{:<36}  {:<7}  {:>7}  {:>6}  {:>9}  {:>8}  name",
        "id", "status", "records", "robots", "landmarks", "updater"
    );
    for r in v["runs"].as_array().into_iter().flatten() {
        let s = &r["summary"];
        println!(
            "{:<36}  {:<7}  {:>7}  {:>6}  {:>9}  {:>8}  {}",
            r["id"].as_str().unwrap_or(""),
            r["status"].as_str().unwrap_or(""),
            r["records"],
            r["robots"],
            s["landmarks"],
            s["updater"].as_str().unwrap_or("-"),
            r["name"].as_str().unwrap_or("")
        );
    }
    println!("{} runs in all", v["total"]);
    Ok(())
}

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// The run's id.
    run: String,
    #[command(flatten)]
    target: Target,
    /// Writes trajectory_<robot>.tum, landmarks.csv, metrics.json and log.ndjson here (the
    /// files `fleetslam run` writes, and the log it reads).
    #[arg(long)]
    out: PathBuf,
    /// Also keep the zip as OUT/run-<id>.zip.
    #[arg(long)]
    keep_zip: bool,
    /// `files` (the default: the files above) or `mcap` (OUT/run-<id>.mcap, for Foxglove
    /// and other MCAP readers: poses, frame transforms, landmarks with their 2-sigma
    /// ellipses and ids, and the ground truth when the run has one).
    #[arg(long, value_parser = ["files", "mcap"], default_value = "files")]
    format: String,
}

pub async fn cmd_export(a: ExportArgs) -> Result<()> {
    let api = a.target.open().await?;
    if a.format == "mcap" {
        let body = api
            .ok(
                Method::GET,
                &format!("/v1/runs/{}/export?format=mcap", a.run),
            )
            .await
            .with_context(|| format!("exporting run {} as MCAP", a.run))?;
        api.close().await;
        std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
        let path = a.out.join(format!("run-{}.mcap", a.run));
        std::fs::write(&path, &body).with_context(|| format!("writing {}", path.display()))?;
        println!(
            "run {} exported to {} ({} bytes)",
            a.run,
            path.display(),
            body.len()
        );
        return Ok(());
    }
    let zip = api
        .ok(Method::GET, &format!("/v1/runs/{}/export", a.run))
        .await
        .with_context(|| format!("exporting run {}", a.run))?;
    api.close().await;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(&zip))?;
    let mut names = Vec::new();
    for i in 0..archive.len() {
        let mut f = archive.by_index(i)?;
        // Names come from our own server, but never write outside OUT.
        let Some(name) = f.enclosed_name() else {
            bail!("the export holds an unsafe file name {:?}", f.name());
        };
        let mut body = Vec::new();
        f.read_to_end(&mut body)?;
        let path = a.out.join(&name);
        std::fs::write(&path, body).with_context(|| format!("writing {}", path.display()))?;
        names.push(name.display().to_string());
    }
    if a.keep_zip {
        std::fs::write(a.out.join(format!("run-{}.zip", a.run)), &zip)?;
    }
    println!(
        "run {} exported to {}: {}",
        a.run,
        a.out.display(),
        names.join(", ")
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct DeleteArgs {
    /// The run's id.
    run: String,
    #[command(flatten)]
    target: Target,
    /// Delete a run the store lists as active (a server may be running it: stop it first).
    #[arg(long)]
    force: bool,
}

pub async fn cmd_delete(a: DeleteArgs) -> Result<()> {
    let api = a.target.open().await?;
    if matches!(api, Api::Local { .. }) && !a.force {
        let body = api.ok(Method::GET, &format!("/v1/runs/{}", a.run)).await?;
        let v: Value = serde_json::from_slice(&body)?;
        if v["run"]["status"] == "active" {
            api.close().await;
            bail!(
                "run {} is active: end it through its server (or pass --force if no server runs it)",
                a.run
            );
        }
    }
    let res = api
        .ok(Method::DELETE, &format!("/v1/runs/{}", a.run))
        .await
        .with_context(|| format!("deleting run {}", a.run));
    api.close().await;
    res?;
    println!("run {} deleted with all its data", a.run);
    Ok(())
}
