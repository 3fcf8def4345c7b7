//! The two backends behind a [`Store`](crate::Store) and the macro that runs one piece of
//! code against either.
//!
//! Both SQLite and PostgreSQL accept `$1, $2, ...` placeholders, so every statement is
//! written once; [`with_pool!`] expands the code that runs it once per backend, so that each
//! expansion is checked with that backend's native types.

use sqlx::{PgPool, SqlitePool};

/// The connection pool of one backend.
#[derive(Debug, Clone)]
pub(crate) enum Pool {
    /// The embedded SQLite database.
    Sqlite(SqlitePool),
    /// A PostgreSQL server.
    Postgres(PgPool),
}

impl Pool {
    /// The backend's name.
    pub(crate) fn backend(&self) -> &'static str {
        match self {
            Pool::Sqlite(_) => "sqlite",
            Pool::Postgres(_) => "postgres",
        }
    }
}

/// The statement that begins a write transaction on a backend.
pub(crate) trait BeginStatement {
    /// `BEGIN IMMEDIATE` for SQLite, plain `BEGIN` elsewhere.
    const BEGIN: &'static str;
}

impl BeginStatement for SqlitePool {
    const BEGIN: &'static str = "BEGIN IMMEDIATE";
}

impl BeginStatement for PgPool {
    const BEGIN: &'static str = "BEGIN";
}

/// Runs `$body` with `$p` bound to the concrete pool (`&SqlitePool` or `&PgPool`) of
/// `$pool`; the body is expanded once per backend.
macro_rules! with_pool {
    ($pool:expr, $p:ident => $body:expr) => {
        match $pool {
            $crate::pool::Pool::Sqlite($p) => $body,
            $crate::pool::Pool::Postgres($p) => $body,
        }
    };
}

pub(crate) use with_pool;
