//! fleetslam-data: everything around the filter that reads or writes files.

pub mod formats;
