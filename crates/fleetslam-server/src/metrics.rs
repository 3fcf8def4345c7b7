//! Prometheus metrics at `GET /metrics` (OpenMetrics text): requests by route and status,
//! request latency, and per run the queue depth, particles, effective sample size, records
//! applied and step latency.

use crate::app::AppState;
use axum::extract::{MatchedPath, Request, State};
use axum::http::{Method, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::sync::atomic::AtomicU64;
use std::time::Instant;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    method: String,
    /// The route pattern (`/v1/runs/{run}/state`), not the path, so runs don't explode the
    /// label set.
    route: String,
    status: u16,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RunLabels {
    run: String,
}

type FloatGauge = Gauge<f64, AtomicU64>;

/// The server's metrics.
#[derive(Debug)]
pub struct Metrics {
    registry: Registry,
    requests: Family<RequestLabels, Counter>,
    latency: Histogram,
    runs_active: Gauge,
    queue_depth: Family<RunLabels, Gauge>,
    particles: Family<RunLabels, Gauge>,
    ess: Family<RunLabels, FloatGauge>,
    applied: Family<RunLabels, Gauge>,
    step_seconds: Family<RunLabels, FloatGauge>,
    /// Cluster mode ([`crate::cluster::ClusterStats`]); zero on a single server.
    cluster: Family<ClusterLabels, Gauge>,
}

#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ClusterLabels {
    counter: &'static str,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut registry = Registry::with_prefix("fleetslam");
        let requests = Family::<RequestLabels, Counter>::default();
        registry.register(
            "http_requests",
            "HTTP requests by method, route and status",
            requests.clone(),
        );
        let latency = Histogram::new(exponential_buckets(0.0005, 2.0, 16));
        registry.register(
            "http_request_duration_seconds",
            "Time to answer an HTTP request",
            latency.clone(),
        );
        let runs_active = Gauge::default();
        registry.register(
            "runs_active",
            "Runs running in this server",
            runs_active.clone(),
        );
        let queue_depth = Family::<RunLabels, Gauge>::default();
        registry.register(
            "run_queue_depth",
            "Requests waiting in a run's coordinator queue",
            queue_depth.clone(),
        );
        let particles = Family::<RunLabels, Gauge>::default();
        registry.register(
            "run_particles",
            "Particles of a run's filter",
            particles.clone(),
        );
        let ess = Family::<RunLabels, FloatGauge>::default();
        registry.register(
            "run_ess",
            "Effective sample size of a run's filter",
            ess.clone(),
        );
        let applied = Family::<RunLabels, Gauge>::default();
        registry.register(
            "run_records_applied",
            "Records a run's filter has applied",
            applied.clone(),
        );
        let step_seconds = Family::<RunLabels, FloatGauge>::default();
        registry.register(
            "run_step_seconds",
            "Median filter step time over the last state publication interval",
            step_seconds.clone(),
        );
        let cluster = Family::<ClusterLabels, Gauge>::default();
        registry.register(
            "cluster",
            "Cluster mode, since this replica started: records it published (published), \
             repeats JetStream deduplicated (duplicate), runs it took (takeovers), runs it owns \
             (owned), and records the stream acknowledged that a run it owns refused as too \
             old (refused_after_ack)",
            cluster.clone(),
        );
        Self {
            registry,
            cluster,
            requests,
            latency,
            runs_active,
            queue_depth,
            particles,
            ess,
            applied,
            step_seconds,
        }
    }
}

/// Counts and times every request.
pub async fn track(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let started = Instant::now();
    // Methods outside the standard set share one label, so clients cannot grow the series.
    let method = match *req.method() {
        Method::GET
        | Method::HEAD
        | Method::POST
        | Method::PUT
        | Method::DELETE
        | Method::PATCH
        | Method::OPTIONS => req.method().as_str().to_string(),
        _ => "other".to_string(),
    };
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_string(), |p| p.as_str().to_string());
    let resp = next.run(req).await;
    let m = &state.metrics;
    m.requests
        .get_or_create(&RequestLabels {
            method,
            route,
            status: resp.status().as_u16(),
        })
        .inc();
    m.latency.observe(started.elapsed().as_secs_f64());
    resp
}

/// `GET /metrics`
#[utoipa::path(get, path = "/metrics", tag = "server",
    responses((status = 200, description = "Prometheus metrics (OpenMetrics text)")))]
pub async fn metrics(State(state): State<AppState>) -> Response {
    let m = &state.metrics;
    let runs = state.runs.read().await;
    for f in [&m.queue_depth, &m.particles, &m.applied] {
        f.clear();
    }
    m.ess.clear();
    m.step_seconds.clear();
    m.runs_active.set(runs.len() as i64);
    for (id, live) in runs.iter() {
        let l = RunLabels { run: id.clone() };
        let s = live.handle.current_state();
        m.queue_depth
            .get_or_create(&l)
            .set(live.handle.queue_depth() as i64);
        m.particles.get_or_create(&l).set(s.particles as i64);
        m.ess.get_or_create(&l).set(s.ess);
        m.applied.get_or_create(&l).set(s.applied as i64);
        m.step_seconds.get_or_create(&l).set(s.step_ms / 1e3);
    }
    drop(runs);
    if let Some(c) = &state.cluster {
        use std::sync::atomic::Ordering::Relaxed;
        let st = &c.stats;
        for (counter, v) in [
            ("published", st.published.load(Relaxed)),
            ("duplicate", st.duplicates.load(Relaxed)),
            ("takeovers", st.takeovers.load(Relaxed)),
            ("refused_after_ack", st.refused_after_ack.load(Relaxed)),
            ("owned", c.owned_runs().await as u64),
        ] {
            m.cluster
                .get_or_create(&ClusterLabels { counter })
                .set(v as i64);
        }
    }
    let mut body = String::new();
    if let Err(e) = encode(&mut body, &m.registry) {
        return crate::error::ApiError::internal(anyhow::anyhow!("encoding metrics: {e}"))
            .into_response();
    }
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        body,
    )
        .into_response()
}
