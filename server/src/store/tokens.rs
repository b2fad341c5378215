//! Access tokens: created (the secret is returned once, only its SHA-256 is stored), looked up,
//! listed and revoked.

use sqlx::Row;
use sqlx::sqlite::SqliteRow;
use subtle::ConstantTimeEq;

use super::{Store, StoreError, now_ms};
use crate::auth::{self, Principal, Roles};

/// A stored token, without its secret.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TokenInfo {
    pub id: i64,
    pub lab: String,
    pub roles: String,
    pub note: String,
    pub created_unix_ms: i64,
    pub revoked_unix_ms: Option<i64>,
}

fn token_from_row(row: &SqliteRow) -> TokenInfo {
    TokenInfo {
        id: row.get("id"),
        lab: row.get("lab"),
        roles: row.get("roles"),
        note: row.get("note"),
        created_unix_ms: row.get("created_ms"),
        revoked_unix_ms: row.get("revoked_ms"),
    }
}

impl Store {
    /// Creates a token for `lab` with `roles`; returns it and its secret (shown once).
    pub async fn create_token(
        &self,
        lab: &str,
        roles: Roles,
        note: &str,
    ) -> Result<(TokenInfo, String), StoreError> {
        let secret = auth::generate_token();
        let hash = auth::token_hash(&secret);
        let row = sqlx::query(
            "INSERT INTO tokens (lab, roles, sha256, note, created_ms) VALUES ($1, $2, $3, $4, $5) \
             RETURNING id, lab, roles, note, created_ms, revoked_ms",
        )
        .bind(lab)
        .bind(roles.to_string())
        .bind(&hash[..])
        .bind(note)
        .bind(now_ms())
        .fetch_one(&self.pool)
        .await?;
        Ok((token_from_row(&row), secret))
    }

    /// The valid (unrevoked) token with this secret, if any.
    pub async fn authenticate(&self, secret: &str) -> Result<Option<Principal>, StoreError> {
        let hash = auth::token_hash(secret);
        let row = sqlx::query(
            "SELECT id, lab, roles, sha256 FROM tokens WHERE sha256 = $1 AND revoked_ms IS NULL",
        )
        .bind(&hash[..])
        .fetch_optional(&self.pool)
        .await?;
        let Some(row) = row else { return Ok(None) };
        let stored: Vec<u8> = row.get("sha256");
        if !bool::from(stored.as_slice().ct_eq(&hash[..])) {
            return Ok(None);
        }
        let roles = Roles::parse(row.get("roles"))
            .map_err(|e| StoreError::Corrupt(format!("token roles: {e}")))?;
        Ok(Some(Principal {
            token_id: row.get("id"),
            lab: row.get("lab"),
            roles,
        }))
    }

    /// Tokens, oldest first; only `lab`'s when given.
    pub async fn list_tokens(&self, lab: Option<&str>) -> Result<Vec<TokenInfo>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, lab, roles, note, created_ms, revoked_ms FROM tokens \
             WHERE $1 IS NULL OR lab = $1 ORDER BY id",
        )
        .bind(lab)
        .fetch_all(&self.pool)
        .await?;
        Ok(rows.iter().map(token_from_row).collect())
    }

    /// Revokes a token (of `lab` only, when given). Returns the token, or None if there is no
    /// such token (in that lab). Revoking twice keeps the first time.
    pub async fn revoke_token(
        &self,
        id: i64,
        lab: Option<&str>,
    ) -> Result<Option<TokenInfo>, StoreError> {
        let row = sqlx::query(
            "UPDATE tokens SET revoked_ms = COALESCE(revoked_ms, $3) WHERE id = $1 AND ($2 IS NULL OR lab = $2) \
             RETURNING id, lab, roles, note, created_ms, revoked_ms",
        )
        .bind(id)
        .bind(lab)
        .bind(now_ms())
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.as_ref().map(token_from_row))
    }
}
