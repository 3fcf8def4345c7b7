//! Starting and stopping a server: store, router, listener, graceful shutdown.

use crate::app::{AppState, app};
use crate::config::ServerConfig;
use anyhow::Context;
use fleetslam_store::Store;
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::sync::oneshot;

/// A running server.
#[derive(Debug)]
pub struct Running {
    pub addr: SocketAddr,
    pub store: Store,
    /// Where Foxglove connects (`foxglove_bind`), when it is served.
    pub foxglove: Option<SocketAddr>,
    state: AppState,
    shutdown: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

impl Running {
    /// Stops accepting connections, finishes the requests under way (so that everything
    /// acknowledged is answered), then stores a snapshot of every running run, so that the
    /// next start resumes them without replaying their records. Runs stay active.
    pub async fn stop(mut self) -> anyhow::Result<()> {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        self.task.await.context("server task")??;
        let runs: Vec<_> = self.state.runs.read().await.values().cloned().collect();
        for live in runs {
            if let Err(e) = live.handle.checkpoint().await {
                tracing::warn!(run = %live.handle.id, error = %e, "no final snapshot");
            }
        }
        if let Some(c) = &self.state.cluster {
            c.release_all().await;
        }
        if let Some(f) = &self.state.foxglove {
            f.stop();
        }
        Ok(())
    }

    /// Waits until the server stops (it does not stop by itself).
    pub async fn wait(self) -> anyhow::Result<()> {
        self.task.await.context("server task")??;
        Ok(())
    }
}

/// Opens the store (creating the embedded SQLite one on first start) and starts serving.
pub async fn start(cfg: &ServerConfig) -> anyhow::Result<Running> {
    cfg.validate().map_err(anyhow::Error::msg)?;
    let store = match &cfg.database_url {
        Some(url) => Store::open(url)
            .await
            .with_context(|| format!("opening the store at {url}"))?,
        None => Store::open_default(&cfg.data_dir)
            .await
            .with_context(|| format!("opening the store in {}", cfg.data_dir.display()))?,
    };
    let listener = tokio::net::TcpListener::bind(&cfg.bind)
        .await
        .with_context(|| format!("listening on {}", cfg.bind))?;
    let addr = listener.local_addr()?;
    cfg.check_exposure(&addr).map_err(anyhow::Error::msg)?;
    let mut api = cfg.api();
    api.auth.loopback = addr.ip().is_loopback();
    let mut state = AppState::new(store.clone(), api);
    if let Some(bind) = cfg.foxglove_addr().map_err(anyhow::Error::msg)? {
        let live = crate::foxglove_live::FoxgloveLive::start(bind).await?;
        tracing::info!(addr = %live.addr(), "Foxglove live view (Foxglove WebSocket protocol)");
        state = state.with_foxglove(Arc::new(live));
    }
    match cfg.cluster() {
        Some(cc) => {
            // Runs are recovered by whichever replica takes them (crate::cluster).
            let replica = cc.replica_id.clone();
            let cluster = crate::cluster::Cluster::connect(cc).await?;
            state = state.with_cluster(cluster.clone());
            cluster.spawn(state.clone());
            tracing::info!(%replica, "cluster replica");
        }
        None => {
            // Connections wait in the listener's backlog until the runs are back.
            let recovered = crate::recovery::recover(&state)
                .await
                .map_err(|e| anyhow::anyhow!("recovering runs: {e}"))?;
            if recovered > 0 {
                tracing::info!(runs = recovered, "recovered active runs");
            }
        }
    }
    let (tx, rx) = oneshot::channel::<()>();
    let router = app(state.clone());
    let task = tokio::spawn(async move {
        axum::serve(listener, router)
            .with_graceful_shutdown(async {
                let _ = rx.await;
            })
            .await
    });
    tracing::info!(%addr, backend = store.backend(), "fleetslam serving");
    Ok(Running {
        addr,
        store,
        foxglove: state.foxglove.as_ref().map(|f| f.addr()),
        state,
        shutdown: Some(tx),
        task,
    })
}

/// Resolves on SIGINT (Ctrl-C) or SIGTERM (what `docker stop` and systemd send).
pub async fn shutdown_signal() -> std::io::Result<&'static str> {
    #[cfg(unix)]
    {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        tokio::select! {
            r = tokio::signal::ctrl_c() => r.map(|()| "SIGINT"),
            _ = term.recv() => Ok("SIGTERM"),
        }
    }
    #[cfg(not(unix))]
    {
        tokio::signal::ctrl_c().await.map(|()| "Ctrl-C")
    }
}
