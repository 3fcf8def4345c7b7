//! fleetslam-data: everything around the filter that reads or writes files.

pub mod evaluate;
pub mod formats;
pub mod import;
pub mod mcap;
pub mod run;
pub mod sim;
