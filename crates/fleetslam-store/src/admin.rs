//! Creating and dropping PostgreSQL databases: for deployments that give each environment
//! its own database, and for tests that need an empty one.

use crate::StoreError;
use sqlx::Connection;

/// The URL of database `name` on the server of `url` (any database path and query of `url`
/// are replaced and kept, respectively).
pub fn with_database(url: &str, name: &str) -> String {
    let (base, query) = match url.split_once('?') {
        Some((base, query)) => (base, Some(query)),
        None => (url, None),
    };
    let host_start = base.find("://").map_or(0, |i| i + 3);
    let base = match base[host_start..].find('/') {
        Some(slash) => &base[..host_start + slash],
        None => base,
    };
    match query {
        Some(q) => format!("{base}/{name}?{q}"),
        None => format!("{base}/{name}"),
    }
}

fn check_name(name: &str) -> Result<(), StoreError> {
    if name.is_empty()
        || name.len() > 63
        || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
    {
        return Err(StoreError::Invalid(format!(
            "database name must be 1-63 ASCII letters, digits or underscores, got {name:?}"
        )));
    }
    Ok(())
}

/// Creates database `name` on the PostgreSQL server of `url`; returns its URL.
pub async fn create_postgres_database(url: &str, name: &str) -> Result<String, StoreError> {
    check_name(name)?;
    let mut admin = sqlx::PgConnection::connect(url).await?;
    sqlx::query(&format!("CREATE DATABASE \"{name}\""))
        .execute(&mut admin)
        .await?;
    admin.close().await?;
    Ok(with_database(url, name))
}

/// Drops database `name` on the PostgreSQL server of `url`, closing its connections.
pub async fn drop_postgres_database(url: &str, name: &str) -> Result<(), StoreError> {
    check_name(name)?;
    let mut admin = sqlx::PgConnection::connect(url).await?;
    sqlx::query(&format!("DROP DATABASE IF EXISTS \"{name}\" WITH (FORCE)"))
        .execute(&mut admin)
        .await?;
    admin.close().await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn database_urls() {
        assert_eq!(
            with_database("postgres://u@h:5432/test?sslmode=disable", "x"),
            "postgres://u@h:5432/x?sslmode=disable"
        );
        assert_eq!(with_database("postgres://h", "x"), "postgres://h/x");
        assert!(check_name("a-b").is_err());
        assert!(check_name("fleetslam_test_1").is_ok());
    }
}
