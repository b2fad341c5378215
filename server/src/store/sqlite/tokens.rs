//! Access tokens in SQLite (only their SHA-256 is stored).

use async_trait::async_trait;
use sqlx::Row;
use subtle::ConstantTimeEq;

use super::Sqlite;
use crate::auth::{self, Principal, Roles};
use crate::store::tokens::token_from_row;
use crate::store::{StoreError, TokenInfo, Tokens, now_ms};

#[async_trait]
impl Tokens for Sqlite {
    async fn create_token(
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

    async fn authenticate(&self, secret: &str) -> Result<Option<Principal>, StoreError> {
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

    async fn list_tokens(&self, lab: Option<&str>) -> Result<Vec<TokenInfo>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, lab, roles, note, created_ms, revoked_ms FROM tokens \
             WHERE $1 IS NULL OR lab = $1 ORDER BY id",
        )
        .bind(lab)
        .fetch_all(&self.pool)
        .await?;
        Ok(rows.iter().map(token_from_row).collect())
    }

    async fn revoke_token(
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
