//! Validation of what rigs declare; every error names its field.

use std::collections::{BTreeMap, HashSet};

use helmholtz_proto::{PatternSpec, v1};

use super::ApiError;
use crate::limits::Limits;
use crate::store::NewSession;

pub const MAX_ID_LEN: usize = 128;
pub const MAX_CHANNELS: usize = 64;
pub const MAX_METADATA_ENTRIES: usize = 64;
pub const MAX_METADATA_VALUE: usize = 4096;

pub fn session_id(id: &str, field: &str) -> Result<(), ApiError> {
    if id.is_empty() || id.len() > MAX_ID_LEN {
        return Err(ApiError::invalid(field, format!("must be 1-{MAX_ID_LEN} characters, got {}", id.len())));
    }
    if let Some(c) = id.chars().find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))) {
        return Err(ApiError::invalid(field, format!("may hold only A-Z a-z 0-9 . _ - (found {c:?})")));
    }
    Ok(())
}

fn name(value: &str, field: &str, max: usize) -> Result<(), ApiError> {
    if value.is_empty() || value.len() > max {
        return Err(ApiError::invalid(field, format!("must be 1-{max} characters")));
    }
    if value.chars().any(|c| c.is_control()) {
        return Err(ApiError::invalid(field, "must not contain control characters"));
    }
    Ok(())
}

/// Validates a session declaration for `lab` against the server's `limits`.
pub fn new_session(req: &v1::CreateSessionRequest, lab: &str, limits: &Limits) -> Result<NewSession, ApiError> {
    session_id(&req.session_id, "session_id")?;
    name(&req.rig, "rig", MAX_ID_LEN)?;
    let spec_msg = req.patterns.as_ref().ok_or_else(|| ApiError::invalid("patterns", "is required"))?;
    let spec = PatternSpec::try_from(spec_msg)
        .map_err(|e| ApiError::invalid(format!("patterns.{}", e.field), e.message))?;
    if spec.count() > limits.max_patterns {
        return Err(ApiError::invalid(
            "patterns.count",
            format!("{} patterns exceed this server's limit of {} per session (max_patterns)", spec.count(), limits.max_patterns),
        ));
    }
    if spec.pixels() as u64 > limits.max_pixels {
        return Err(ApiError::invalid(
            "patterns.width",
            format!(
                "{}x{} = {} pixels exceed this server's limit of {} per pattern (max_pixels)",
                spec.width(),
                spec.height(),
                spec.pixels(),
                limits.max_pixels
            ),
        ));
    }
    let channels = req.detector.as_ref().map(|d| d.channels.clone()).unwrap_or_default();
    if channels.is_empty() || channels.len() > MAX_CHANNELS {
        return Err(ApiError::invalid(
            "detector.channels",
            format!("must name 1-{MAX_CHANNELS} channels, got {}", channels.len()),
        ));
    }
    let mut seen = HashSet::new();
    for (i, c) in channels.iter().enumerate() {
        session_id(c, &format!("detector.channels[{i}]"))?;
        if !seen.insert(c) {
            return Err(ApiError::invalid(format!("detector.channels[{i}]"), format!("duplicate channel {c:?}")));
        }
    }
    if req.metadata.len() > MAX_METADATA_ENTRIES {
        return Err(ApiError::invalid("metadata", format!("at most {MAX_METADATA_ENTRIES} entries")));
    }
    for (k, v) in &req.metadata {
        name(k, "metadata", MAX_ID_LEN)?;
        if v.len() > MAX_METADATA_VALUE {
            return Err(ApiError::invalid(format!("metadata.{k}"), format!("at most {MAX_METADATA_VALUE} bytes")));
        }
    }
    let ground_truth = match &req.ground_truth {
        None => None,
        Some(gt) => {
            if gt.width != spec.width() || gt.height != spec.height() {
                return Err(ApiError::invalid(
                    "ground_truth",
                    format!(
                        "is {}x{} but the patterns are {}x{}",
                        gt.width,
                        gt.height,
                        spec.width(),
                        spec.height()
                    ),
                ));
            }
            if gt.transport.len() != spec.pixels() {
                return Err(ApiError::invalid(
                    "ground_truth.transport",
                    format!("must hold width * height = {} values, got {}", spec.pixels(), gt.transport.len()),
                ));
            }
            if let Some(i) = gt.transport.iter().position(|v| !v.is_finite()) {
                return Err(ApiError::invalid("ground_truth.transport", format!("value {i} is not finite")));
            }
            Some((gt.width, gt.height, gt.transport.clone()))
        }
    };
    Ok(NewSession {
        id: req.session_id.clone(),
        lab: lab.to_string(),
        rig: req.rig.clone(),
        spec,
        channels,
        metadata: req.metadata.iter().map(|(k, v)| (k.clone(), v.clone())).collect::<BTreeMap<_, _>>(),
        ground_truth,
    })
}
