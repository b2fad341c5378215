//! Validation of what rigs declare; every error names its field.

use std::collections::{BTreeMap, HashSet};

use helmholtz_proto::{PatternSpec, v1};

use super::ApiError;
use crate::limits::Limits;
use crate::store::{CameraLayout, NewSession, SampleFormat, SessionRow};

pub const MAX_ID_LEN: usize = 128;
pub const MAX_CHANNELS: usize = 64;
pub const MAX_METADATA_ENTRIES: usize = 64;
pub const MAX_METADATA_VALUE: usize = 4096;

pub fn session_id(id: &str, field: &str) -> Result<(), ApiError> {
    if id.is_empty() || id.len() > MAX_ID_LEN {
        return Err(ApiError::invalid(
            field,
            format!("must be 1-{MAX_ID_LEN} characters, got {}", id.len()),
        ));
    }
    if let Some(c) = id
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')))
    {
        return Err(ApiError::invalid(
            field,
            format!("may hold only A-Z a-z 0-9 . _ - (found {c:?})"),
        ));
    }
    if id == "." || id == ".." {
        // Path segments of their own: URLs, file names and spool directories would misread them.
        return Err(ApiError::invalid(
            field,
            format!("{id:?} is not a usable id (it names a directory)"),
        ));
    }
    Ok(())
}

/// An upload's writer id (the `x-helmholtz-writer` header; empty when not sent): 1-64
/// characters of `A-Z a-z 0-9 _ -`. One id for every stream or request of one client upload.
pub fn writer_id(value: Option<&[u8]>) -> Result<String, ApiError> {
    let Some(value) = value else {
        return Ok(String::new());
    };
    if value.is_empty()
        || value.len() > 64
        || !value
            .iter()
            .all(|b| b.is_ascii_alphanumeric() || *b == b'_' || *b == b'-')
    {
        return Err(ApiError::invalid(
            super::grpc::WRITER_HEADER,
            "must be 1-64 characters of A-Z a-z 0-9 _ -",
        ));
    }
    Ok(String::from_utf8(value.to_vec()).expect("ascii"))
}

/// Checks uploaded rows, already in the session's sample format and checksum-checked: whole
/// rows (`field` names where they came from) and, for floats, every value finite. The same rule
/// for a gRPC chunk and a REST upload body.
pub fn stored_rows(field: &str, bytes: &[u8], session: &SessionRow) -> Result<(), ApiError> {
    let format = session.sample_format();
    let row_bytes = session.row_bytes();
    let per_row = session.row_values();
    if row_bytes == 0 || !bytes.len().is_multiple_of(row_bytes) {
        let whole = match session.camera {
            Some(c) => format!(
                "whole frames of {} x {} {} pixels",
                c.width,
                c.height,
                format.name()
            ),
            None => format!("whole rows of {per_row} f64 values (one per channel)"),
        };
        return Err(ApiError::invalid(
            field,
            format!(
                "{} bytes are not {whole} ({row_bytes} bytes each)",
                bytes.len()
            ),
        ));
    }
    let unit = if session.camera.is_some() {
        "pixel"
    } else {
        "channel"
    };
    let not_finite = match format {
        SampleFormat::F64 => bytes
            .chunks_exact(8)
            .position(|b| !f64::from_le_bytes(b.try_into().expect("8")).is_finite()),
        SampleFormat::F32 => bytes
            .chunks_exact(4)
            .position(|b| !f32::from_le_bytes(b.try_into().expect("4")).is_finite()),
        SampleFormat::U16 => None,
    };
    if let Some(i) = not_finite {
        return Err(ApiError::invalid(
            field,
            format!(
                "value at row {}, {unit} {} is not finite",
                i / per_row,
                i % per_row
            ),
        ));
    }
    Ok(())
}

fn name(value: &str, field: &str, max: usize) -> Result<(), ApiError> {
    if value.is_empty() || value.len() > max {
        return Err(ApiError::invalid(
            field,
            format!("must be 1-{max} characters"),
        ));
    }
    if value.chars().any(|c| c.is_control()) {
        return Err(ApiError::invalid(
            field,
            "must not contain control characters",
        ));
    }
    Ok(())
}

/// Validates a session declaration for `lab` against the server's `limits`.
pub fn new_session(
    req: &v1::CreateSessionRequest,
    lab: &str,
    limits: &Limits,
) -> Result<NewSession, ApiError> {
    session_id(&req.session_id, "session_id")?;
    name(&req.rig, "rig", MAX_ID_LEN)?;
    let spec_msg = req
        .patterns
        .as_ref()
        .ok_or_else(|| ApiError::invalid("patterns", "is required"))?;
    let spec = PatternSpec::try_from(spec_msg)
        .map_err(|e| ApiError::invalid(format!("patterns.{}", e.field), e.message))?;
    if spec.count() > limits.max_patterns {
        return Err(ApiError::invalid(
            "patterns.count",
            format!(
                "{} patterns exceed this server's limit of {} per session (max_patterns)",
                spec.count(),
                limits.max_patterns
            ),
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
    let detector = req.detector.clone().unwrap_or_default();
    let (channels, directions, camera) = detector_layout(&detector, limits)?;
    if req.metadata.len() > MAX_METADATA_ENTRIES {
        return Err(ApiError::invalid(
            "metadata",
            format!("at most {MAX_METADATA_ENTRIES} entries"),
        ));
    }
    for (k, v) in &req.metadata {
        name(k, "metadata", MAX_ID_LEN)?;
        if v.len() > MAX_METADATA_VALUE {
            return Err(ApiError::invalid(
                format!("metadata.{k}"),
                format!("at most {MAX_METADATA_VALUE} bytes"),
            ));
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
            let k = spec.pixels();
            let allowed: Vec<usize> = match &camera {
                Some(c) => vec![c.pixels() * k],
                None if channels.len() > 1 => vec![k, channels.len() * k],
                None => vec![k],
            };
            if !allowed.contains(&gt.transport.len()) {
                let what = match &camera {
                    Some(c) => format!("camera pixels x pattern pixels = {} x {k}", c.pixels()),
                    None if channels.len() > 1 => format!(
                        "width * height = {k}, or channels * width * height = {}",
                        channels.len() * k
                    ),
                    None => format!("width * height = {k}"),
                };
                return Err(ApiError::invalid(
                    "ground_truth.transport",
                    format!("must hold {what} values, got {}", gt.transport.len()),
                ));
            }
            if gt.transport.len() as u64 > limits.max_ground_truth_values {
                return Err(ApiError::invalid(
                    "ground_truth.transport",
                    format!(
                        "{} values exceed this server's limit of {} (max_ground_truth_values); send no ground truth",
                        gt.transport.len(),
                        limits.max_ground_truth_values
                    ),
                ));
            }
            if let Some(i) = gt.transport.iter().position(|v| !v.is_finite()) {
                return Err(ApiError::invalid(
                    "ground_truth.transport",
                    format!("value {i} is not finite"),
                ));
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
        directions,
        camera,
        metadata: req
            .metadata
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect::<BTreeMap<_, _>>(),
        ground_truth,
    })
}

type Detector = (Vec<String>, Vec<[f64; 3]>, Option<CameraLayout>);

/// Bucket channels (with optional detector directions), or a camera.
fn detector_layout(d: &v1::DetectorLayout, limits: &Limits) -> Result<Detector, ApiError> {
    if let Some(cam) = &d.camera {
        if !d.channels.is_empty() || !d.directions.is_empty() {
            return Err(ApiError::invalid(
                "detector.camera",
                "a camera session has no bucket channels or directions; leave detector.channels and detector.directions empty",
            ));
        }
        if cam.width == 0 || cam.height == 0 {
            return Err(ApiError::invalid(
                "detector.camera.width",
                format!(
                    "camera must be at least 1x1, got {}x{}",
                    cam.width, cam.height
                ),
            ));
        }
        let pixels = cam.width as u64 * cam.height as u64;
        if pixels > limits.max_frame_pixels {
            return Err(ApiError::invalid(
                "detector.camera.width",
                format!(
                    "{}x{} = {pixels} pixels per frame exceed this server's limit of {} (max_frame_pixels)",
                    cam.width, cam.height, limits.max_frame_pixels
                ),
            ));
        }
        let format = match v1::SampleFormat::try_from(cam.format) {
            Ok(v1::SampleFormat::F32) => SampleFormat::F32,
            Ok(v1::SampleFormat::U16) => SampleFormat::U16,
            _ => {
                return Err(ApiError::invalid(
                    "detector.camera.format",
                    format!(
                        "must be SAMPLE_FORMAT_F32 or SAMPLE_FORMAT_U16, got {}",
                        cam.format
                    ),
                ));
            }
        };
        return Ok((
            Vec::new(),
            Vec::new(),
            Some(CameraLayout {
                width: cam.width,
                height: cam.height,
                format,
            }),
        ));
    }
    let channels = d.channels.clone();
    if channels.is_empty() || channels.len() > MAX_CHANNELS {
        return Err(ApiError::invalid(
            "detector.channels",
            format!(
                "must name 1-{MAX_CHANNELS} channels (or set detector.camera), got {}",
                channels.len()
            ),
        ));
    }
    let mut seen = HashSet::new();
    for (i, c) in channels.iter().enumerate() {
        session_id(c, &format!("detector.channels[{i}]"))?;
        if !seen.insert(c) {
            return Err(ApiError::invalid(
                format!("detector.channels[{i}]"),
                format!("duplicate channel {c:?}"),
            ));
        }
    }
    if !d.directions.is_empty() && d.directions.len() != channels.len() {
        return Err(ApiError::invalid(
            "detector.directions",
            format!(
                "give one direction per channel ({}) or none, got {}",
                channels.len(),
                d.directions.len()
            ),
        ));
    }
    let mut directions = Vec::with_capacity(d.directions.len());
    for (i, v) in d.directions.iter().enumerate() {
        let n = (v.x * v.x + v.y * v.y + v.z * v.z).sqrt();
        if !n.is_finite() || (n - 1.0).abs() > 1e-3 {
            return Err(ApiError::invalid(
                format!("detector.directions[{i}]"),
                format!(
                    "must be a unit vector, got ({}, {}, {}) of length {n}",
                    v.x, v.y, v.z
                ),
            ));
        }
        if v.z <= 0.0 {
            return Err(ApiError::invalid(
                format!("detector.directions[{i}]"),
                format!(
                    "must point toward the projector's side of the scene (z > 0), got z = {}",
                    v.z
                ),
            ));
        }
        directions.push([v.x / n, v.y / n, v.z / n]);
    }
    Ok((channels, directions, None))
}
