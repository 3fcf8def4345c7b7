//! Starting and stopping a server: store, router, listener, graceful shutdown.

use crate::app::{AppState, app};
use crate::config::ServerConfig;
use anyhow::Context;
use fleetslam_store::Store;
use std::net::SocketAddr;
use tokio::sync::oneshot;

/// A running server.
#[derive(Debug)]
pub struct Running {
    pub addr: SocketAddr,
    pub store: Store,
    shutdown: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

impl Running {
    /// Stops accepting connections, finishes the requests under way and returns.
    pub async fn stop(mut self) -> anyhow::Result<()> {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        self.task.await.context("server task")??;
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
    let state = AppState::new(store.clone(), cfg.api());
    let recovered = crate::recovery::recover(&state)
        .await
        .map_err(|e| anyhow::anyhow!("recovering runs: {e}"))?;
    if recovered > 0 {
        tracing::info!(runs = recovered, "recovered active runs");
    }
    let listener = tokio::net::TcpListener::bind(&cfg.bind)
        .await
        .with_context(|| format!("listening on {}", cfg.bind))?;
    let addr = listener.local_addr()?;
    let (tx, rx) = oneshot::channel::<()>();
    let router = app(state);
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
        shutdown: Some(tx),
        task,
    })
}
