//! fleetslam-server: the central agent of the multi-robot FastSLAM.
//!
//! Robots post records over HTTP ([`app::app`]); one coordinator task per run
//! ([`coordinator`]) stores them (acknowledged means committed), merges the k robots'
//! streams in a deterministic order ([`merge::Merger`]) and steps the run's filter off the
//! async runtime; the state is served as JSON and streamed over a websocket.
//!
//! In progress (issue 3): run creation, robot registration with tokens, record ingest
//! (single, array, NDJSON) with per-record acknowledgements, state and live streaming work;
//! the OpenAPI document, metrics, crash recovery, replay and the demo are still to come.

pub mod app;
pub mod config;
pub mod coordinator;
pub mod error;
pub mod merge;
pub mod server;
