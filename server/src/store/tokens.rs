//! Access tokens: created (the secret is returned once, only its SHA-256 is stored), looked up,
//! listed and revoked.

use async_trait::async_trait;

use super::StoreRow;

use super::StoreError;
use crate::auth::{Principal, Roles};

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

/// Tokens as a backend stores them.
#[async_trait]
pub trait Tokens: Send + Sync {
    /// Creates a token for `lab` with `roles`; returns it and its secret (shown once).
    async fn create_token(
        &self,
        lab: &str,
        roles: Roles,
        note: &str,
    ) -> Result<(TokenInfo, String), StoreError>;

    /// The valid (unrevoked) token with this secret, if any (compared in constant time).
    async fn authenticate(&self, secret: &str) -> Result<Option<Principal>, StoreError>;

    /// Tokens, oldest first; only `lab`'s when given.
    async fn list_tokens(&self, lab: Option<&str>) -> Result<Vec<TokenInfo>, StoreError>;

    /// Revokes a token (of `lab` only, when given). Returns the token, or None if there is no
    /// such token (in that lab). Revoking twice keeps the first time.
    async fn revoke_token(
        &self,
        id: i64,
        lab: Option<&str>,
    ) -> Result<Option<TokenInfo>, StoreError>;
}

/// A token row of either backend.
pub(crate) fn token_from_row(row: &impl StoreRow) -> TokenInfo {
    TokenInfo {
        id: row.int("id"),
        lab: row.text("lab"),
        roles: row.text("roles"),
        note: row.text("note"),
        created_unix_ms: row.int("created_ms"),
        revoked_unix_ms: row.int_or_null("revoked_ms"),
    }
}
