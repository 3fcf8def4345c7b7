//! fleetslam-server: the central agent of the multi-robot FastSLAM.
//!
//! Robots post records over HTTP ([`app::app`]); one coordinator task per run
//! ([`coordinator`]) stores them (acknowledged means committed), merges the k robots'
//! streams in a deterministic order ([`merge::Merger`]) and steps the run's filter off the
//! async runtime; the state is served as JSON and streamed over a websocket.
//!
//! Every run's snapshots, result and log stay in the store ([`history`], [`api_history`]):
//! a restarted server recovers its active runs bit for bit ([`recovery`]), and finished runs
//! can be scrubbed through, exported, re-run with another configuration and deleted.
//!
//! Several servers can share the runs as replicas of a cluster ([`cluster`]): records go
//! through NATS JetStream, each run is owned by one replica at a time through a lease, and
//! a replica that dies hands its runs to another, which recovers them from PostgreSQL.

pub mod api_history;
pub mod app;
pub mod auth;
pub mod cluster;
pub mod compact;
pub mod config;
pub mod coordinator;
pub mod error;
pub mod foxglove_live;
pub mod history;
pub mod limits;
pub mod merge;
pub mod metrics;
pub mod openapi;
pub mod poison;
pub mod recovery;
pub mod server;
pub mod track;
pub mod ws_limit;
