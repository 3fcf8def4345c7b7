//! Server configuration: defaults, then a TOML file, then `FLEETSLAM_<FIELD>` environment
//! variables, then command-line flags, layered with figment ([`ServerConfig::load`]; the
//! variables read follow the struct's fields). Unknown keys in the file are an error.
//! `fleetslam.example.toml` at the repository root is a commented example.

use crate::app::ApiConfig;
use crate::auth::{AuthConfig, MIN_TOKEN_LEN, ReadAccess};
use crate::coordinator::CoordinatorConfig;
use crate::limits::Limits;
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
    /// Token required to create, end, delete and re-run runs, upload truth, and register
    /// robots in any run (`Authorization: Bearer ...`; at least 16 characters). Default none:
    /// anyone who can reach the server may do so, which `serve` allows on a loopback address
    /// only.
    pub admin_token: Option<String>,
    /// Token that grants reading (state, live, runs, trajectories, truth, evaluation,
    /// export, models, metrics) when reads need one; the admin token always does. At least
    /// 16 characters.
    pub read_token: Option<String>,
    /// Who may read: `auto` (default: anyone on a loopback address, the read or admin token
    /// elsewhere), `token` (always a token) or `open` (anyone; only behind a proxy that
    /// authenticates).
    pub read_access: ReadAccess,
    /// Origins (`scheme://host:port`) whose web pages may change state or open the live
    /// websocket, besides the server's own loopback origins (in `FLEETSLAM_ALLOWED_ORIGINS`,
    /// comma-separated). Requests without an `Origin`
    /// header (robots, scripts) are not affected.
    #[serde(deserialize_with = "comma_list")]
    pub allowed_origins: Vec<String>,
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
    /// Records applied between two stored snapshots at most. Default 20,000. Recovery after
    /// a crash and scrubbing replay at most this many records; each snapshot costs a
    /// serialization of every particle.
    pub snapshot_every: u64,
    /// The filter's stepping time [ms] (its steps' own time, not the wall clock's) after
    /// which a snapshot falls due, when that comes before `snapshot_every` records. Default
    /// 500: a recovery or a scrub replays about this much filter work at most, and snapshots
    /// take a bounded share of the filter's time.
    pub snapshot_every_work_ms: u64,
    /// Directory of the dashboard's files, served at `/`. Default: the `web/` directory of
    /// the source tree the server was built from.
    pub web_dir: Option<PathBuf>,
    /// How far a record's time may lie ahead of the run's clock (the time it has applied,
    /// or before that its robots' start times and earliest record) [s]. Default 3600.
    pub max_future_s: f64,
    /// Longest motion (sum of segment durations) in one record [s]. Default 600.
    pub max_motion_s: f64,
    /// Most motion segments in one record. Default 10000.
    pub max_motion_segments: usize,
    /// Most records in one request. Default 10000.
    pub max_records_per_request: usize,
    /// Most landmark observations in one record. Default 1000.
    pub max_landmarks_per_record: usize,
    /// Most robot sightings in one record. Default 64.
    pub max_sightings_per_record: usize,
    /// Most robots in one run. Default 256.
    pub max_robots_per_run: usize,
    /// Most runs running at once in this server. Default 64.
    pub max_active_runs: usize,
    /// Longest run name, robot id or model id [bytes]. Default 128.
    pub max_name_bytes: usize,
    /// Websocket clients (`GET /v1/runs/{id}/live`) of one run at a time; one more gets a
    /// JSON 503 before the upgrade. Default 32. Each costs a task and a state serialization
    /// per publication.
    pub ws_max_per_run: usize,
    /// Websocket clients of all runs together; one more gets a JSON 503. Default 256.
    pub ws_max_total: usize,
    /// Period of a live websocket's heartbeat [ms]: the server pings the client and sends a
    /// `{"type":"heartbeat"}` message, closes a connection whose client answered nothing
    /// for three periods, and the dashboard treats one silent for three periods as lost.
    /// Default 5000.
    pub ws_heartbeat_ms: u64,
    /// Also serve live runs to Foxglove over its WebSocket protocol on this address
    /// (`host:port`, e.g. `127.0.0.1:8765`; [`crate::foxglove_live`]). Default none. The
    /// protocol has no authentication: a non-loopback address needs `read_access = "open"`
    /// (behind a proxy that authenticates).
    pub foxglove_bind: Option<String>,
    /// Run as one replica of a cluster ([`crate::cluster`]): records go through NATS
    /// JetStream (`nats_url`), runs are owned by lease, the store must be PostgreSQL
    /// (`database_url`), shared by every replica. Default false.
    pub cluster: bool,
    /// NATS servers, comma-separated (`nats://host:4222,...`); cluster mode only.
    pub nats_url: Option<String>,
    /// This replica's name in the cluster; default a random one per start.
    pub replica_id: Option<String>,
    /// Replicas of the record stream and the lease buckets in JetStream (3 on a 3-node NATS
    /// cluster, 1 on a single node). Default 3.
    pub stream_replicas: usize,
    /// How long a run's lease lasts unless its owner renews it [ms]: the longest a killed
    /// owner's runs wait for another replica. Default 3000.
    pub lease_ttl_ms: u64,
}

/// A list of strings, or (as an environment variable gives it) one comma-separated string.
fn comma_list<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum List {
        One(String),
        Many(Vec<String>),
    }
    Ok(match List::deserialize(d)? {
        List::One(s) => s
            .split(',')
            .map(str::trim)
            .filter(|o| !o.is_empty())
            .map(str::to_string)
            .collect(),
        List::Many(v) => v,
    })
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            bind: "127.0.0.1:8080".into(),
            data_dir: PathBuf::from("data"),
            database_url: None,
            admin_token: None,
            read_token: None,
            read_access: ReadAccess::Auto,
            allowed_origins: Vec::new(),
            body_limit_bytes: 16 << 20,
            queue_capacity: 256,
            reorder_window_ms: 2000,
            state_rate_hz: 10.0,
            particle_sample: 100,
            snapshot_every: crate::coordinator::DEFAULT_SNAPSHOT_EVERY,
            snapshot_every_work_ms: crate::coordinator::DEFAULT_SNAPSHOT_EVERY_WORK.as_millis()
                as u64,
            web_dir: None,
            max_future_s: Limits::default().max_future_s,
            max_motion_s: Limits::default().max_motion_s,
            max_motion_segments: Limits::default().max_motion_segments,
            max_records_per_request: Limits::default().max_records_per_request,
            max_landmarks_per_record: Limits::default().max_landmarks_per_record,
            max_sightings_per_record: Limits::default().max_sightings_per_record,
            max_robots_per_run: Limits::default().max_robots_per_run,
            max_active_runs: Limits::default().max_active_runs,
            max_name_bytes: Limits::default().max_name_bytes,
            ws_max_per_run: crate::ws_limit::DEFAULT_WS_MAX_PER_RUN,
            ws_max_total: crate::ws_limit::DEFAULT_WS_MAX_TOTAL,
            ws_heartbeat_ms: crate::ws_limit::DEFAULT_WS_HEARTBEAT.as_millis() as u64,
            foxglove_bind: None,
            cluster: false,
            nats_url: None,
            replica_id: None,
            stream_replicas: 3,
            lease_ttl_ms: 3000,
        }
    }
}

/// The prefix of the environment variables: `FLEETSLAM_<FIELD>` sets a field.
pub const ENV_PREFIX: &str = "FLEETSLAM_";

/// `FLEETSLAM_<FIELD>` variables for the fields of [`ServerConfig`], kept as the strings
/// they are: figment's own `Env` provider reads a token of digits as a number and drops its
/// leading zeros. The lossy extraction of [`ServerConfig::load`] makes numbers and booleans
/// of the variables of number and boolean fields. An empty variable is unset (compose files
/// pass `${VAR:-}` through).
struct EnvStrings(figment::providers::Env);

impl EnvStrings {
    fn new() -> Self {
        // The fields, from the defaults: the variables read follow the struct by themselves.
        let fields: Vec<String> = match serde_json::to_value(ServerConfig::default()) {
            Ok(serde_json::Value::Object(m)) => m.keys().cloned().collect(),
            _ => Vec::new(),
        };
        Self(
            figment::providers::Env::prefixed(ENV_PREFIX)
                .filter(move |k| fields.iter().any(|f| k == f.as_str())),
        )
    }
}

impl figment::Provider for EnvStrings {
    fn metadata(&self) -> figment::Metadata {
        figment::Metadata::named("environment variable").interpolater(
            |_: &figment::Profile, k: &[&str]| {
                format!("{ENV_PREFIX}{}", k.join(".").to_ascii_uppercase())
            },
        )
    }

    fn data(
        &self,
    ) -> Result<figment::value::Map<figment::Profile, figment::value::Dict>, figment::Error> {
        let dict = self
            .0
            .iter()
            .filter(|(_, v)| !v.is_empty())
            .map(|(k, v)| (k.to_string(), figment::value::Value::from(v)))
            .collect();
        Ok(figment::Profile::Default.collect(dict))
    }
}

impl ServerConfig {
    /// The layers, each over the one before: the defaults, the TOML `file`, the
    /// `FLEETSLAM_<FIELD>` environment variables, then `flags` (the fields a command line
    /// gave: any serializable struct or map whose absent fields leave the layers below).
    /// Unknown keys are an error, and an error names the layer and field.
    pub fn load(file: Option<&std::path::Path>, flags: impl Serialize) -> Result<Self, String> {
        use figment::providers::{Format, Serialized, Toml};
        let mut fig = figment::Figment::from(Serialized::defaults(Self::default()));
        if let Some(path) = file {
            if !path.is_file() {
                return Err(format!("reading {}: no such file", path.display()));
            }
            fig = fig.merge(Toml::file_exact(path));
        }
        fig.merge(EnvStrings::new())
            .merge(Serialized::defaults(flags))
            .extract_lossy()
            .map_err(|e| {
                e.into_iter()
                    .map(|e| format!("configuration: {e}"))
                    .collect::<Vec<_>>()
                    .join("; ")
            })
    }

    pub fn validate(&self) -> Result<(), String> {
        if self.cluster {
            if self.nats_url.as_deref().is_none_or(str::is_empty) {
                return Err("cluster mode needs nats_url (--nats URL)".into());
            }
            if !self
                .database_url
                .as_deref()
                .is_some_and(|u| u.starts_with("postgres://") || u.starts_with("postgresql://"))
            {
                return Err(
                    "cluster mode needs a PostgreSQL database_url (--database-url \
                     postgres://...) that every replica shares"
                        .into(),
                );
            }
            if self.stream_replicas == 0 || self.stream_replicas > 5 {
                return Err(format!(
                    "stream_replicas must be 1 to 5 (JetStream's limit), got {}",
                    self.stream_replicas
                ));
            }
            if self.lease_ttl_ms < 300 {
                return Err(format!(
                    "lease_ttl_ms must be at least 300, got {}",
                    self.lease_ttl_ms
                ));
            }
        }
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
        if self.snapshot_every_work_ms == 0 {
            return Err("snapshot_every_work_ms must be at least 1".into());
        }
        if self.ws_max_per_run == 0 || self.ws_max_total == 0 {
            return Err("ws_max_per_run and ws_max_total must be at least 1".into());
        }
        if self.ws_heartbeat_ms < 50 {
            return Err(format!(
                "ws_heartbeat_ms must be at least 50, got {}",
                self.ws_heartbeat_ms
            ));
        }
        if self.body_limit_bytes < 1024 {
            return Err(format!(
                "body_limit_bytes must be at least 1024, got {}",
                self.body_limit_bytes
            ));
        }
        for (name, token) in [
            ("admin_token", &self.admin_token),
            ("read_token", &self.read_token),
        ] {
            if let Some(t) = token
                && t.chars().count() < MIN_TOKEN_LEN
            {
                return Err(format!(
                    "{name} must be at least {MIN_TOKEN_LEN} characters (generate one with \
                     `openssl rand -hex 24`)"
                ));
            }
        }
        for o in &self.allowed_origins {
            crate::auth::parse_origin(o).map_err(|e| format!("allowed_origins: {e}"))?;
        }
        if let Some(addr) = self.foxglove_addr()? {
            let ip = addr.ip();
            if !ip.is_loopback() && self.read_access != ReadAccess::Open {
                return Err(format!(
                    "refusing to serve Foxglove on {addr}: the Foxglove WebSocket protocol \
                     has no authentication, so anyone who reaches it reads every live run; \
                     bind a loopback address (and tunnel to it), or set read_access = \
                     \"open\" behind a proxy that authenticates"
                ));
            }
        }
        self.limits().validate()?;
        Ok(())
    }

    /// The Foxglove server's address, when one is set.
    pub fn foxglove_addr(&self) -> Result<Option<std::net::SocketAddr>, String> {
        self.foxglove_bind
            .as_deref()
            .map(|b| {
                b.parse().map_err(|_| {
                    format!("foxglove_bind must be host:port with an IP host (127.0.0.1:8765), got {b:?}")
                })
            })
            .transpose()
    }

    /// Refuses to serve a non-loopback address without an admin token: anyone on the network
    /// could otherwise create runs and register robots. `addr` is the address bound.
    pub fn check_exposure(&self, addr: &std::net::SocketAddr) -> Result<(), String> {
        if !addr.ip().is_loopback() && self.admin_token.is_none() {
            return Err(format!(
                "refusing to serve {addr} without an admin token: set admin_token \
                 (FLEETSLAM_ADMIN_TOKEN or --admin-token, at least {MIN_TOKEN_LEN} characters), \
                 or bind a loopback address such as 127.0.0.1:8080"
            ));
        }
        Ok(())
    }

    /// The input bounds.
    pub fn limits(&self) -> Limits {
        Limits {
            max_future_s: self.max_future_s,
            max_motion_s: self.max_motion_s,
            max_motion_segments: self.max_motion_segments,
            max_records_per_request: self.max_records_per_request,
            max_landmarks_per_record: self.max_landmarks_per_record,
            max_sightings_per_record: self.max_sightings_per_record,
            max_robots_per_run: self.max_robots_per_run,
            max_active_runs: self.max_active_runs,
            max_name_bytes: self.max_name_bytes,
        }
    }

    /// The cluster settings, when in cluster mode.
    pub fn cluster(&self) -> Option<crate::cluster::ClusterConfig> {
        if !self.cluster {
            return None;
        }
        let mut c = crate::cluster::ClusterConfig {
            nats_urls: self
                .nats_url
                .iter()
                .flat_map(|u| u.split(','))
                .map(str::trim)
                .filter(|u| !u.is_empty())
                .map(str::to_string)
                .collect(),
            stream_replicas: self.stream_replicas,
            lease_ttl: std::time::Duration::from_millis(self.lease_ttl_ms),
            ..Default::default()
        };
        if let Some(id) = &self.replica_id {
            c.replica_id = id.clone();
        }
        Some(c)
    }

    pub fn api(&self) -> ApiConfig {
        ApiConfig {
            auth: AuthConfig {
                admin_token: self.admin_token.clone(),
                read_token: self.read_token.clone(),
                read_access: self.read_access,
                allowed_origins: self.allowed_origins.clone(),
                loopback: true,
            },
            limits: self.limits(),
            body_limit: self.body_limit_bytes,
            web_dir: self
                .web_dir
                .clone()
                .unwrap_or_else(crate::app::default_web_dir),
            coordinator: CoordinatorConfig {
                queue_capacity: self.queue_capacity,
                max_backlog: crate::coordinator::DEFAULT_MAX_BACKLOG,
                reorder_window: Duration::from_millis(self.reorder_window_ms),
                state_rate_hz: self.state_rate_hz,
                particle_sample: self.particle_sample,
                snapshot_every: self.snapshot_every,
                snapshot_every_work: Duration::from_millis(self.snapshot_every_work_ms),
                max_future_s: self.max_future_s,
                ws_max_per_run: self.ws_max_per_run,
                ws_max_total: self.ws_max_total,
                ws_heartbeat: Duration::from_millis(self.ws_heartbeat_ms),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use figment::Jail;

    /// No flags.
    fn none() -> serde_json::Value {
        serde_json::json!({})
    }

    #[test]
    #[allow(clippy::result_large_err)] // figment's Jail takes closures returning its error
    fn layers_defaults_file_env_then_flags() {
        Jail::expect_with(|jail| {
            jail.create_file(
                "c.toml",
                "bind = \"0.0.0.0:9000\"\nqueue_capacity = 8\nstate_rate_hz = 4.0\n",
            )?;
            jail.set_env("FLEETSLAM_QUEUE_CAPACITY", "16");
            jail.set_env("FLEETSLAM_STATE_RATE_HZ", "5");
            // A token of digits stays the string it is (leading zero and all).
            jail.set_env("FLEETSLAM_ADMIN_TOKEN", "0123456789012345678");
            jail.set_env("FLEETSLAM_ALLOWED_ORIGINS", "http://a:1, http://b:2");
            jail.set_env("FLEETSLAM_CLUSTER", "true");
            // Not a field: ignored (the tests' own variables share the prefix).
            jail.set_env("FLEETSLAM_REQUIRE_DATA", "1");
            let path = jail.directory().join("c.toml");
            let c =
                ServerConfig::load(Some(&path), serde_json::json!({"state_rate_hz": 7.5})).unwrap();
            assert_eq!(c.bind, "0.0.0.0:9000");
            assert_eq!(c.queue_capacity, 16);
            assert_eq!(c.state_rate_hz, 7.5);
            assert_eq!(c.admin_token.as_deref(), Some("0123456789012345678"));
            assert_eq!(c.allowed_origins, ["http://a:1", "http://b:2"]);
            assert!(c.cluster);
            assert_eq!(c.snapshot_every, ServerConfig::default().snapshot_every);
            // An empty variable is unset.
            jail.set_env("FLEETSLAM_ADMIN_TOKEN", "");
            let c = ServerConfig::load(None, none()).unwrap();
            assert_eq!(c.admin_token, None);
            assert_eq!(c.state_rate_hz, 5.0);
            Ok(())
        });
    }

    #[test]
    #[allow(clippy::result_large_err)] // figment's Jail takes closures returning its error
    fn unknown_keys_and_bad_values_are_errors() {
        Jail::expect_with(|jail| {
            jail.create_file("c.toml", "colour = 1\n")?;
            let path = jail.directory().join("c.toml");
            let e = ServerConfig::load(Some(&path), none()).unwrap_err();
            assert!(e.contains("colour") && e.contains("c.toml"), "{e}");
            let e =
                ServerConfig::load(Some(&jail.directory().join("none.toml")), none()).unwrap_err();
            assert!(e.contains("none.toml"), "{e}");
            jail.set_env("FLEETSLAM_STATE_RATE_HZ", "fast");
            let e = ServerConfig::load(None, none()).unwrap_err();
            assert!(
                e.contains("FLEETSLAM_STATE_RATE_HZ") && e.contains("fast"),
                "{e}"
            );
            Ok(())
        });
    }

    #[test]
    #[allow(clippy::result_large_err)] // figment's Jail takes closures returning its error
    fn cluster_mode_needs_nats_and_a_shared_postgres() {
        Jail::expect_with(|jail| {
            jail.set_env("FLEETSLAM_CLUSTER", "true");
            let c = ServerConfig::load(None, none()).unwrap();
            assert!(c.validate().unwrap_err().contains("nats_url"));
            jail.set_env("FLEETSLAM_NATS_URL", "nats://a:4222");
            let c = ServerConfig::load(None, none()).unwrap();
            assert!(c.validate().unwrap_err().contains("PostgreSQL"));
            jail.set_env("FLEETSLAM_NATS_URL", "nats://a:4222, nats://b:4222");
            jail.set_env("FLEETSLAM_DATABASE_URL", "postgres://db/fleetslam");
            jail.set_env("FLEETSLAM_REPLICA_ID", "7");
            let c = ServerConfig::load(None, none()).unwrap();
            c.validate().unwrap();
            let cc = c.cluster().unwrap();
            assert_eq!(cc.nats_urls, ["nats://a:4222", "nats://b:4222"]);
            assert_eq!(cc.replica_id, "7");
            assert!(ServerConfig::default().cluster().is_none());
            Ok(())
        });
    }

    #[test]
    #[allow(clippy::result_large_err)] // figment's Jail takes closures returning its error
    fn example_config_parses() {
        // In a Jail too: the other tests set FLEETSLAM_* variables in theirs, and a load
        // outside one would read them (FLEETSLAM_CLUSTER=true) while they run.
        Jail::expect_with(|_| {
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../fleetslam.example.toml");
            let c = ServerConfig::load(Some(&path), none()).unwrap();
            c.validate().unwrap();
            Ok(())
        });
    }
}
