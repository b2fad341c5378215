//! Access control: per-lab bearer tokens with roles.
//!
//! A token is `hz_` followed by 32 random bytes in unpadded base64url (256 bits). Only its SHA-256
//! is stored (a high-entropy secret needs no slow KDF); the presented token's hash is looked up
//! by index and then compared in constant time. Requests carry it as `Authorization: Bearer
//! <token>` (REST and gRPC metadata) or as the password (or user name) of HTTP Basic auth, so
//! `http://hz_...@host:port` URLs work with ordinary HTTP tools.

use std::fmt;

use base64::Engine;
use base64::engine::general_purpose::{STANDARD, URL_SAFE_NO_PAD};
use sha2::{Digest, Sha256};

/// What a token may do (a set; a token may carry several).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Role {
    /// Create sessions and upload to them (its own lab).
    Rig,
    /// Read the lab's sessions, reconstructions and images; request and cancel reconstructions.
    Reader,
    /// Manage the lab's tokens.
    Admin,
    /// Scrape the server's Prometheus metrics (`GET /metrics` on the main port): counts over
    /// the whole server, nothing of any lab's sessions or images.
    Metrics,
}

impl Role {
    pub const ALL: [Role; 4] = [Role::Rig, Role::Reader, Role::Admin, Role::Metrics];

    pub fn name(self) -> &'static str {
        match self {
            Role::Rig => "rig",
            Role::Reader => "reader",
            Role::Admin => "admin",
            Role::Metrics => "metrics",
        }
    }

    fn bit(self) -> u8 {
        match self {
            Role::Rig => 1,
            Role::Reader => 2,
            Role::Admin => 4,
            Role::Metrics => 8,
        }
    }

    pub fn parse(s: &str) -> Result<Role, String> {
        match s.trim() {
            "rig" => Ok(Role::Rig),
            "reader" => Ok(Role::Reader),
            "admin" => Ok(Role::Admin),
            "metrics" => Ok(Role::Metrics),
            other => Err(format!(
                "unknown role {other:?}; roles are rig, reader, admin and metrics"
            )),
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A non-empty set of roles.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Roles(u8);

impl Roles {
    pub fn of(roles: &[Role]) -> Roles {
        Roles(roles.iter().fold(0, |acc, r| acc | r.bit()))
    }

    pub fn contains(self, role: Role) -> bool {
        self.0 & role.bit() != 0
    }

    pub fn is_empty(self) -> bool {
        self.0 == 0
    }

    pub fn list(self) -> Vec<Role> {
        Role::ALL
            .into_iter()
            .filter(|r| self.contains(*r))
            .collect()
    }

    /// Parses `rig,reader` (the stored form; also what the CLI and REST accept).
    pub fn parse(s: &str) -> Result<Roles, String> {
        let mut roles = Roles::default();
        for part in s.split(',').filter(|p| !p.trim().is_empty()) {
            roles.0 |= Role::parse(part)?.bit();
        }
        if roles.is_empty() {
            return Err("at least one role is required (rig, reader, admin, metrics)".into());
        }
        Ok(roles)
    }
}

impl fmt::Display for Roles {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let names: Vec<&str> = self.list().into_iter().map(Role::name).collect();
        f.write_str(&names.join(","))
    }
}

/// Who is calling: the token's id, lab and roles.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Principal {
    pub token_id: i64,
    pub lab: String,
    pub roles: Roles,
}

pub const TOKEN_PREFIX: &str = "hz_";

/// A fresh 256-bit token.
pub fn generate_token() -> String {
    let bytes: [u8; 32] = rand::random();
    format!("{TOKEN_PREFIX}{}", URL_SAFE_NO_PAD.encode(bytes))
}

pub fn token_hash(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

/// Why a request carries no usable credential.
#[derive(Debug, PartialEq, Eq)]
pub enum CredentialError {
    Missing,
    Malformed(&'static str),
}

/// The token in an `Authorization` header value: `Bearer <token>`, or HTTP Basic with the token
/// as password (or as user name when the password is empty).
pub fn token_from_authorization(value: Option<&[u8]>) -> Result<String, CredentialError> {
    let Some(value) = value else {
        return Err(CredentialError::Missing);
    };
    let value = std::str::from_utf8(value)
        .map_err(|_| CredentialError::Malformed("not ASCII"))?
        .trim();
    let (scheme, rest) = value
        .split_once(' ')
        .ok_or(CredentialError::Malformed("expected \"Bearer <token>\""))?;
    let token = if scheme.eq_ignore_ascii_case("bearer") {
        rest.trim().to_string()
    } else if scheme.eq_ignore_ascii_case("basic") {
        let decoded = STANDARD
            .decode(rest.trim())
            .map_err(|_| CredentialError::Malformed("Basic credentials are not base64"))?;
        let decoded = String::from_utf8(decoded)
            .map_err(|_| CredentialError::Malformed("Basic credentials are not UTF-8"))?;
        let (user, password) = decoded.split_once(':').unwrap_or((decoded.as_str(), ""));
        if password.is_empty() {
            user.to_string()
        } else {
            password.to_string()
        }
    } else {
        return Err(CredentialError::Malformed(
            "expected the Bearer or Basic scheme",
        ));
    };
    if !token.starts_with(TOKEN_PREFIX) || token.len() > 256 {
        return Err(CredentialError::Malformed("not a Helmholtz token (hz_...)"));
    }
    Ok(token)
}

/// Lab names: 1-64 characters of A-Z a-z 0-9 . _ -
pub fn valid_lab(lab: &str) -> Result<(), String> {
    if lab.is_empty() || lab.len() > 64 {
        return Err(format!(
            "a lab name must be 1-64 characters, got {}",
            lab.len()
        ));
    }
    if let Some(c) = lab
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')))
    {
        return Err(format!(
            "a lab name may hold only A-Z a-z 0-9 . _ - (found {c:?})"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_are_256_bit_and_distinct() {
        let a = generate_token();
        let b = generate_token();
        assert_ne!(a, b);
        assert!(a.starts_with("hz_"));
        assert_eq!(URL_SAFE_NO_PAD.decode(&a[3..]).unwrap().len(), 32);
        assert_ne!(token_hash(&a), token_hash(&b));
    }

    #[test]
    fn authorization_headers() {
        let t = generate_token();
        assert_eq!(
            token_from_authorization(Some(format!("Bearer {t}").as_bytes())),
            Ok(t.clone())
        );
        assert_eq!(
            token_from_authorization(Some(format!("bearer  {t} ").as_bytes())),
            Ok(t.clone())
        );
        let basic = STANDARD.encode(format!("x:{t}"));
        assert_eq!(
            token_from_authorization(Some(format!("Basic {basic}").as_bytes())),
            Ok(t.clone())
        );
        let basic_user = STANDARD.encode(format!("{t}:"));
        assert_eq!(
            token_from_authorization(Some(format!("Basic {basic_user}").as_bytes())),
            Ok(t.clone())
        );
        assert_eq!(
            token_from_authorization(None),
            Err(CredentialError::Missing)
        );
        assert!(token_from_authorization(Some(b"Bearer abc")).is_err());
        assert!(token_from_authorization(Some(b"Token hz_abc")).is_err());
        assert!(token_from_authorization(Some(b"Basic !!!")).is_err());
        assert!(token_from_authorization(Some(&[0xff, 0x20, 0x41])).is_err());
    }

    #[test]
    fn roles_parse_and_print() {
        let r = Roles::parse("reader,rig").unwrap();
        assert!(r.contains(Role::Rig) && r.contains(Role::Reader) && !r.contains(Role::Admin));
        assert_eq!(r.to_string(), "rig,reader");
        assert!(Roles::parse("").is_err());
        assert!(Roles::parse("root").is_err());
    }
}
