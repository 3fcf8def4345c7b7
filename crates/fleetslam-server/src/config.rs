//! Server configuration: defaults, then a TOML file, then `FLEETSLAM_*` environment
//! variables, then command-line flags. Unknown keys in the file are an error.
//! `fleetslam.example.toml` at the repository root is a commented example.

use crate::app::ApiConfig;
use crate::coordinator::CoordinatorConfig;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::time::Duration;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServerConfig {
    /// Address to listen on. Default `127.0.0.1:8080`.
    pub bind: String,
    /// Directory of the embedded SQLite store (created on first start). Default `data`.
    pub data_dir: PathBuf,
    /// A `postgres://` (or `sqlite://`) URL; when set it replaces the embedded store.
    pub database_url: Option<String>,
    /// Token required to create and end runs (`Authorization: Bearer ...`). Default none:
    /// anyone who can reach the server may create runs, fine on loopback only.
    pub admin_token: Option<String>,
    /// Largest request body [bytes]. Default 16 MiB.
    pub body_limit_bytes: usize,
    /// Requests queued per run before the server answers 503 + Retry-After. Default 256.
    pub queue_capacity: usize,
    /// How long a silent robot holds the others back in the merge [ms]. Default 2000.
    /// Longer tolerates slower robots; shorter applies records sooner.
    pub reorder_window_ms: u64,
    /// Most state publications per second per run (websocket and GET state). Default 10.
    pub state_rate_hz: f64,
    /// Particles per robot in the published state. Default 100.
    pub particle_sample: usize,
    /// Records applied between two stored snapshots. Default 2000. Recovery after a crash
    /// and scrubbing replay at most this many records; each snapshot costs a serialization
    /// of every particle.
    pub snapshot_every: u64,
    /// Directory of the dashboard's files, served at `/`. Default: the `web/` directory of
    /// the source tree the server was built from.
    pub web_dir: Option<PathBuf>,
    /// Websocket clients (`GET /v1/runs/{id}/live`) of one run at a time; one more gets a
    /// JSON 503 before the upgrade. Default 32. Each costs a task and a state serialization
    /// per publication.
    pub ws_max_per_run: usize,
    /// Websocket clients of all runs together; one more gets a JSON 503. Default 256.
    pub ws_max_total: usize,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            bind: "127.0.0.1:8080".into(),
            data_dir: PathBuf::from("data"),
            database_url: None,
            admin_token: None,
            body_limit_bytes: 16 << 20,
            queue_capacity: 256,
            reorder_window_ms: 2000,
            state_rate_hz: 10.0,
            particle_sample: 100,
            snapshot_every: 2000,
            web_dir: None,
            ws_max_per_run: crate::ws_limit::DEFAULT_WS_MAX_PER_RUN,
            ws_max_total: crate::ws_limit::DEFAULT_WS_MAX_TOTAL,
        }
    }
}

/// The environment variables read, each overriding the field of the same name.
pub const ENV_KEYS: [&str; 13] = [
    "bind",
    "data_dir",
    "database_url",
    "admin_token",
    "body_limit_bytes",
    "queue_capacity",
    "reorder_window_ms",
    "state_rate_hz",
    "particle_sample",
    "snapshot_every",
    "web_dir",
    "ws_max_per_run",
    "ws_max_total",
];

impl ServerConfig {
    /// Defaults, then `file` (TOML), then `FLEETSLAM_<FIELD>` variables from `env`.
    pub fn load(
        file: Option<&std::path::Path>,
        env: impl Fn(&str) -> Option<String>,
    ) -> Result<Self, String> {
        let mut v = serde_json::to_value(Self::default()).map_err(|e| e.to_string())?;
        if let Some(path) = file {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("reading {}: {e}", path.display()))?;
            let t: toml::Value =
                toml::from_str(&text).map_err(|e| format!("parsing {}: {e}", path.display()))?;
            let patch = serde_json::to_value(t).map_err(|e| e.to_string())?;
            let serde_json::Value::Object(p) = patch else {
                return Err(format!("{}: expected a table", path.display()));
            };
            for (k, val) in p {
                v[k] = val;
            }
            // Unknown keys are reported by the typed parse below.
        }
        for key in ENV_KEYS {
            let name = format!("FLEETSLAM_{}", key.to_uppercase());
            // An empty variable is unset (compose files pass `${VAR:-}` through).
            if let Some(raw) = env(&name).filter(|v| !v.is_empty()) {
                let default_is_string = matches!(
                    key,
                    "bind" | "data_dir" | "database_url" | "admin_token" | "web_dir"
                );
                v[key] = if default_is_string {
                    serde_json::Value::String(raw)
                } else {
                    serde_json::from_str(&raw)
                        .map_err(|_| format!("{name}={raw:?} is not a number"))?
                };
            }
        }
        serde_path_to_error::deserialize(v)
            .map_err(|e| format!("configuration: field `{}`: {}", e.path(), e.inner()))
    }

    pub fn validate(&self) -> Result<(), String> {
        if self.queue_capacity == 0 {
            return Err("queue_capacity must be at least 1".into());
        }
        if !(self.state_rate_hz.is_finite() && self.state_rate_hz > 0.0) {
            return Err(format!(
                "state_rate_hz must be > 0, got {}",
                self.state_rate_hz
            ));
        }
        if self.snapshot_every == 0 {
            return Err("snapshot_every must be at least 1".into());
        }
        if self.ws_max_per_run == 0 || self.ws_max_total == 0 {
            return Err("ws_max_per_run and ws_max_total must be at least 1".into());
        }
        if self.body_limit_bytes < 1024 {
            return Err(format!(
                "body_limit_bytes must be at least 1024, got {}",
                self.body_limit_bytes
            ));
        }
        Ok(())
    }

    pub fn api(&self) -> ApiConfig {
        ApiConfig {
            admin_token: self.admin_token.clone(),
            body_limit: self.body_limit_bytes,
            web_dir: self
                .web_dir
                .clone()
                .unwrap_or_else(crate::app::default_web_dir),
            coordinator: CoordinatorConfig {
                queue_capacity: self.queue_capacity,
                reorder_window: Duration::from_millis(self.reorder_window_ms),
                state_rate_hz: self.state_rate_hz,
                particle_sample: self.particle_sample,
                snapshot_every: self.snapshot_every,
                ws_max_per_run: self.ws_max_per_run,
                ws_max_total: self.ws_max_total,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layers_file_then_env() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("c.toml");
        std::fs::write(&f, "bind = \"0.0.0.0:9000\"\nqueue_capacity = 8\n").unwrap();
        let env = |k: &str| (k == "FLEETSLAM_QUEUE_CAPACITY").then(|| "16".to_string());
        let c = ServerConfig::load(Some(&f), env).unwrap();
        assert_eq!(c.bind, "0.0.0.0:9000");
        assert_eq!(c.queue_capacity, 16);
        assert_eq!(c.state_rate_hz, 10.0);
        let c =
            ServerConfig::load(None, |k| (k == "FLEETSLAM_ADMIN_TOKEN").then(String::new)).unwrap();
        assert_eq!(c.admin_token, None, "an empty variable is unset");
    }

    #[test]
    fn unknown_keys_and_bad_values_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("c.toml");
        std::fs::write(&f, "colour = 1\n").unwrap();
        let e = ServerConfig::load(Some(&f), |_| None).unwrap_err();
        assert!(e.contains("colour"), "{e}");
        let e = ServerConfig::load(None, |k| {
            (k == "FLEETSLAM_STATE_RATE_HZ").then(|| "fast".into())
        })
        .unwrap_err();
        assert!(e.contains("FLEETSLAM_STATE_RATE_HZ"), "{e}");
    }

    #[test]
    fn example_config_parses() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fleetslam.example.toml");
        let c = ServerConfig::load(Some(&path), |_| None).unwrap();
        c.validate().unwrap();
    }
}
