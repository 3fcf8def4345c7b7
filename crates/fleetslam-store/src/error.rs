//! The store's error type.

use sqlx::error::ErrorKind;

/// Everything that can go wrong in the store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The run (or other object) named does not exist.
    #[error("not found: {0}")]
    NotFound(String),
    /// The object already exists (a run id or a robot id used twice).
    #[error("conflict: {0}")]
    Conflict(String),
    /// The request itself is malformed (empty id, unknown status, non-finite time, ...).
    #[error("invalid request: {0}")]
    Invalid(String),
    /// The database refused or failed the operation.
    #[error("database error: {0}")]
    Database(#[from] sqlx::Error),
    /// Applying the schema migrations failed.
    #[error("migration failed: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    /// A JSON document could not be written or a stored one could not be read back.
    #[error("malformed JSON: {0}")]
    Json(#[from] serde_json::Error),
    /// The data directory or database file could not be created.
    #[error("I/O error: {0}")]
    Io(#[from] std::io::Error),
    /// The store's writer task has stopped (the runtime that opened the store shut down).
    #[error("the store's writer task has stopped")]
    Closed,
}

impl StoreError {
    /// Turns constraint violations into [`StoreError::Conflict`] (unique key) and
    /// [`StoreError::NotFound`] (foreign key: the run does not exist); other errors stay
    /// [`StoreError::Database`]. `what` names the object for the message.
    pub(crate) fn from_db(err: sqlx::Error, what: impl FnOnce() -> String) -> Self {
        if let sqlx::Error::Database(db) = &err {
            match db.kind() {
                ErrorKind::UniqueViolation => {
                    return StoreError::Conflict(format!("{} already exists", what()));
                }
                ErrorKind::ForeignKeyViolation => {
                    return StoreError::NotFound(format!("run of {}", what()));
                }
                _ => {}
            }
        }
        StoreError::Database(err)
    }
}
