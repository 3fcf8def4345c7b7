//! Bounds on websocket connections (`GET /v1/runs/{run}/live`), and their heartbeat
//! ([`Heartbeat`]). At most
//! [`CoordinatorConfig::ws_max_per_run`] per run and [`CoordinatorConfig::ws_max_total`] in
//! all. Each connection streams a run's states and events from its own task; without a bound,
//! clients could make the server hold any number of them. Over a bound, the request gets a
//! JSON 503 (`busy`, with Retry-After) before the upgrade.
//!
//! A [`WsPermit`] is an extractor: a handler that takes one holds a slot until the permit is
//! dropped, so the permit moves into the upgraded connection's task.

use crate::app::AppState;
use crate::coordinator::CoordinatorConfig;
use crate::error::ApiError;
use axum::extract::{FromRequestParts, Path};
use axum::http::request::Parts;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Default for [`CoordinatorConfig::ws_max_per_run`].
pub const DEFAULT_WS_MAX_PER_RUN: usize = 32;
/// Default for [`CoordinatorConfig::ws_max_total`].
pub const DEFAULT_WS_MAX_TOTAL: usize = 256;
/// Default for [`CoordinatorConfig::ws_heartbeat`].
pub const DEFAULT_WS_HEARTBEAT: std::time::Duration = std::time::Duration::from_secs(5);
/// Heartbeat periods without a word from the client (a pong or any message) after which
/// the server closes a live connection; the dashboard gives the server as many.
pub const HEARTBEAT_MISSES: u32 = 3;

/// A live connection's heartbeat. On an idle run nothing else crosses a websocket, so
/// neither end would notice that the other is gone (a closed laptop, a dropped network
/// without a reset): each period the server pings the client (which answers with a pong,
/// browsers by themselves) and sends `{"type":"heartbeat","period_ms":P}` (browsers' scripts
/// never see pings; the dashboard counts a connection silent for [`HEARTBEAT_MISSES`]
/// periods as lost and reconnects), and it closes a connection whose client said nothing for
/// [`HEARTBEAT_MISSES`] periods, which frees its slot.
#[derive(Debug)]
pub struct Heartbeat {
    period: std::time::Duration,
    tick: tokio::time::Interval,
    heard: tokio::time::Instant,
}

impl Heartbeat {
    pub fn new(period: std::time::Duration) -> Self {
        let mut tick = tokio::time::interval_at(tokio::time::Instant::now() + period, period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        Self {
            period,
            tick,
            heard: tokio::time::Instant::now(),
        }
    }

    /// The client said something (a pong, a message).
    pub fn heard(&mut self) {
        self.heard = tokio::time::Instant::now();
    }

    /// Waits for the next beat.
    pub async fn beat(&mut self) {
        self.tick.tick().await;
    }

    /// The client has said nothing for [`HEARTBEAT_MISSES`] periods.
    pub fn dead(&self) -> bool {
        self.heard.elapsed() >= self.period * HEARTBEAT_MISSES
    }

    /// The heartbeat message.
    pub fn message(&self) -> String {
        serde_json::json!({"type": "heartbeat", "period_ms": self.period.as_millis() as u64})
            .to_string()
    }
}

/// The open websocket connections, per run and in total.
#[derive(Debug, Default)]
pub struct WsLimits {
    open: Mutex<Open>,
}

#[derive(Debug, Default)]
struct Open {
    total: usize,
    per_run: HashMap<String, usize>,
}

impl WsLimits {
    fn lock(&self) -> std::sync::MutexGuard<'_, Open> {
        // The counts are updated in one step each: a poisoned lock still holds whole counts.
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Takes a slot for a connection to `run`, or says which bound is reached.
    pub fn acquire(
        self: &Arc<Self>,
        run: &str,
        cfg: &CoordinatorConfig,
    ) -> Result<WsPermit, ApiError> {
        let mut open = self.lock();
        let of_run = open.per_run.get(run).copied().unwrap_or(0);
        let busy = |message: String| ApiError::Busy {
            message,
            retry_after_s: 5,
        };
        if open.total >= cfg.ws_max_total {
            return Err(busy(format!(
                "the server has {} live connections, its bound (ws_max_total); retry later",
                open.total
            )));
        }
        if of_run >= cfg.ws_max_per_run {
            return Err(busy(format!(
                "run {run} has {of_run} live connections, its bound (ws_max_per_run); retry \
                 later, or poll GET /v1/runs/{run}/state"
            )));
        }
        open.total += 1;
        *open.per_run.entry(run.to_string()).or_default() += 1;
        Ok(WsPermit {
            limits: self.clone(),
            run: run.to_string(),
        })
    }

    /// Open connections to `run`, and in all.
    pub fn open(&self, run: &str) -> (usize, usize) {
        let open = self.lock();
        (open.per_run.get(run).copied().unwrap_or(0), open.total)
    }
}

/// One open (or opening) websocket connection's slot, given back when dropped.
#[derive(Debug)]
pub struct WsPermit {
    limits: Arc<WsLimits>,
    run: String,
}

impl Drop for WsPermit {
    fn drop(&mut self) {
        let mut open = self.limits.lock();
        open.total = open.total.saturating_sub(1);
        if let Some(n) = open.per_run.get_mut(&self.run) {
            *n -= 1;
            if *n == 0 {
                open.per_run.remove(&self.run);
            }
        }
    }
}

impl FromRequestParts<AppState> for WsPermit {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        let Path(run) = Path::<String>::from_request_parts(parts, state)
            .await
            .map_err(|e| ApiError::BadRequest(format!("path: {}", e.body_text())))?;
        state.ws.acquire(&run, &state.config.coordinator)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_per_run_and_in_total_and_slots_come_back() {
        let cfg = CoordinatorConfig {
            ws_max_per_run: 2,
            ws_max_total: 3,
            ..CoordinatorConfig::default()
        };
        let limits = Arc::new(WsLimits::default());
        let a1 = limits.acquire("a", &cfg).unwrap();
        let a2 = limits.acquire("a", &cfg).unwrap();
        let e = limits.acquire("a", &cfg).unwrap_err();
        assert!(e.to_string().contains("ws_max_per_run"), "{e}");
        let b1 = limits.acquire("b", &cfg).unwrap();
        let e = limits.acquire("c", &cfg).unwrap_err();
        assert!(e.to_string().contains("ws_max_total"), "{e}");
        assert_eq!(limits.open("a"), (2, 3));
        drop(a1);
        assert_eq!(limits.open("a"), (1, 2));
        let c1 = limits.acquire("c", &cfg).unwrap();
        drop((a2, b1, c1));
        assert_eq!(limits.open("a"), (0, 0));
        assert!(limits.lock().per_run.is_empty());
    }
}
