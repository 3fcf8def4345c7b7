//! Rebuilds the crate when a migration changes: `sqlx::migrate!` embeds the SQL files of the
//! workspace's top-level `migrations/` directory at compile time.

fn main() {
    println!("cargo:rerun-if-changed=../../migrations");
}
