//! Conversions between the gRPC `PatternSpec` message and the validated [`PatternSpec`].

use super::{AdaptiveFrames, ErrorEstimate, Family, HadamardOrdering, PatternSpec, SpecError};
use crate::v1;

/// Why a protobuf spec could not be accepted.
pub type ProtoSpecError = SpecError;

impl TryFrom<&v1::PatternSpec> for PatternSpec {
    type Error = SpecError;

    fn try_from(m: &v1::PatternSpec) -> Result<Self, SpecError> {
        use v1::pattern_spec::Params;
        let family = match v1::PatternFamily::try_from(m.family) {
            Ok(v1::PatternFamily::Raster) => {
                let (block, scans) = match &m.params {
                    Some(Params::Raster(p)) => (p.block.max(1), p.scans.max(1)),
                    None => (1, 1),
                    Some(_) => return Err(params_mismatch("raster")),
                };
                Family::Raster { block, scans }
            }
            Ok(v1::PatternFamily::Bernoulli) => {
                let fill = match &m.params {
                    Some(Params::Bernoulli(p)) => p.fill.unwrap_or(0.5),
                    None => 0.5,
                    Some(_) => return Err(params_mismatch("bernoulli")),
                };
                Family::Bernoulli { fill }
            }
            Ok(v1::PatternFamily::Hadamard) => {
                let ordering = match &m.params {
                    Some(Params::Hadamard(p)) => ordering_from_proto(p.ordering)?,
                    None => HadamardOrdering::Natural,
                    Some(_) => return Err(params_mismatch("hadamard")),
                };
                Family::Hadamard { ordering }
            }
            Ok(v1::PatternFamily::Speckle) => {
                let grain = match &m.params {
                    Some(Params::Speckle(p)) if p.grain > 0 => p.grain,
                    Some(Params::Speckle(_)) | None => 1,
                    Some(_) => return Err(params_mismatch("speckle")),
                };
                Family::Speckle { grain }
            }
            Ok(f @ (v1::PatternFamily::AdaptiveHaar | v1::PatternFamily::AdaptiveHadamard)) => {
                let (batch, target_error, persistence, estimate, frames) = match &m.params {
                    Some(Params::Adaptive(p)) => (
                        p.batch,
                        p.target_error,
                        p.persistence,
                        p.error_estimate,
                        p.frames,
                    ),
                    None => (0, 0.0, None, 0, 0),
                    Some(_) => return Err(params_mismatch("an adaptive family")),
                };
                let error_estimate = match v1::AdaptiveErrorEstimate::try_from(estimate) {
                    Ok(v1::AdaptiveErrorEstimate::Prediction) => ErrorEstimate::Prediction,
                    Ok(
                        v1::AdaptiveErrorEstimate::Measured
                        | v1::AdaptiveErrorEstimate::Unspecified,
                    ) => ErrorEstimate::Measured,
                    Err(_) => {
                        return Err(SpecError {
                            field: "error_estimate",
                            message: format!(
                                "unknown AdaptiveErrorEstimate {estimate}: 1 (prediction) or 2 (measured)"
                            ),
                        });
                    }
                };
                let frames = match v1::AdaptiveFrames::try_from(frames) {
                    Ok(v1::AdaptiveFrames::Single) => AdaptiveFrames::Single,
                    Ok(v1::AdaptiveFrames::Pairs | v1::AdaptiveFrames::Unspecified) => {
                        AdaptiveFrames::Pairs
                    }
                    Err(_) => {
                        return Err(SpecError {
                            field: "frames",
                            message: format!(
                                "unknown AdaptiveFrames {frames}: 1 (pairs) or 2 (single)"
                            ),
                        });
                    }
                };
                Family::adaptive(
                    f == v1::PatternFamily::AdaptiveHaar,
                    batch,
                    target_error,
                    persistence,
                )
                .with_error_estimate(error_estimate)
                .with_frames(frames)
            }
            Ok(v1::PatternFamily::Unspecified) | Err(_) => {
                return Err(SpecError {
                    field: "family",
                    message: format!(
                        "must be raster, bernoulli, hadamard, speckle, adaptive_haar or adaptive_hadamard (got enum value {})",
                        m.family
                    ),
                });
            }
        };
        PatternSpec::new(family, m.width, m.height, m.count, m.seed)
    }
}

fn params_mismatch(family: &str) -> SpecError {
    SpecError {
        field: "params",
        message: format!("parameters of another family given for {family}"),
    }
}

fn ordering_from_proto(value: i32) -> Result<HadamardOrdering, SpecError> {
    use v1::HadamardOrdering as P;
    Ok(match P::try_from(value) {
        Ok(P::Unspecified | P::Natural) => HadamardOrdering::Natural,
        Ok(P::Sequency) => HadamardOrdering::Sequency,
        Ok(P::Zigzag) => HadamardOrdering::Zigzag,
        Ok(P::RussianDoll) => HadamardOrdering::RussianDoll,
        Ok(P::CakeCutting) => HadamardOrdering::CakeCutting,
        Err(_) => {
            return Err(SpecError {
                field: "ordering",
                message: format!("unknown hadamard ordering enum value {value}"),
            });
        }
    })
}

impl From<&PatternSpec> for v1::PatternSpec {
    fn from(s: &PatternSpec) -> Self {
        use v1::pattern_spec::Params;
        let (family, params) = match *s.family() {
            Family::Raster { block, scans } => (
                v1::PatternFamily::Raster,
                Params::Raster(v1::RasterParams { block, scans }),
            ),
            Family::Bernoulli { fill } => (
                v1::PatternFamily::Bernoulli,
                Params::Bernoulli(v1::BernoulliParams { fill: Some(fill) }),
            ),
            Family::Hadamard { ordering } => {
                use v1::HadamardOrdering as P;
                let o = match ordering {
                    HadamardOrdering::Natural => P::Natural,
                    HadamardOrdering::Sequency => P::Sequency,
                    HadamardOrdering::Zigzag => P::Zigzag,
                    HadamardOrdering::RussianDoll => P::RussianDoll,
                    HadamardOrdering::CakeCutting => P::CakeCutting,
                };
                (
                    v1::PatternFamily::Hadamard,
                    Params::Hadamard(v1::HadamardParams { ordering: o as i32 }),
                )
            }
            Family::Speckle { grain } => (
                v1::PatternFamily::Speckle,
                Params::Speckle(v1::SpeckleParams { grain }),
            ),
            Family::AdaptiveHaar {
                batch,
                target_error,
                persistence,
                error_estimate,
                frames,
            } => (
                v1::PatternFamily::AdaptiveHaar,
                Params::Adaptive(v1::AdaptiveParams {
                    batch,
                    target_error,
                    persistence: Some(persistence),
                    error_estimate: proto_estimate(error_estimate) as i32,
                    frames: proto_frames(frames) as i32,
                }),
            ),
            Family::AdaptiveHadamard {
                batch,
                target_error,
                persistence,
                error_estimate,
                frames,
            } => (
                v1::PatternFamily::AdaptiveHadamard,
                Params::Adaptive(v1::AdaptiveParams {
                    batch,
                    target_error,
                    persistence: Some(persistence),
                    error_estimate: proto_estimate(error_estimate) as i32,
                    frames: proto_frames(frames) as i32,
                }),
            ),
        };
        v1::PatternSpec {
            family: family as i32,
            width: s.width(),
            height: s.height(),
            count: s.count(),
            seed: s.seed(),
            params: Some(params),
        }
    }
}

/// Pairs as unset (0): the form of every spec declared before the field existed.
fn proto_frames(f: AdaptiveFrames) -> v1::AdaptiveFrames {
    match f {
        AdaptiveFrames::Pairs => v1::AdaptiveFrames::Unspecified,
        AdaptiveFrames::Single => v1::AdaptiveFrames::Single,
    }
}

fn proto_estimate(e: ErrorEstimate) -> v1::AdaptiveErrorEstimate {
    match e {
        ErrorEstimate::Prediction => v1::AdaptiveErrorEstimate::Prediction,
        ErrorEstimate::Measured => v1::AdaptiveErrorEstimate::Measured,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adaptive_specs_round_trip_through_protobuf() {
        for family in [
            Family::AdaptiveHaar {
                batch: 32,
                target_error: 0.02,
                persistence: 0.25,
                error_estimate: ErrorEstimate::Measured,
                frames: AdaptiveFrames::Pairs,
            },
            Family::AdaptiveHadamard {
                batch: 0,
                target_error: 0.0,
                persistence: 0.0,
                error_estimate: ErrorEstimate::Prediction,
                frames: AdaptiveFrames::Pairs,
            },
        ] {
            let spec = PatternSpec::new(family, 16, 16, 100, 3).unwrap();
            let m = v1::PatternSpec::from(&spec);
            assert_eq!(PatternSpec::try_from(&m).unwrap(), spec);
        }
        // No params: the defaults (automatic batches, the whole budget, the family's
        // persistence); an unset persistence is the default too, an explicit 0 is kept.
        let m = v1::PatternSpec {
            family: v1::PatternFamily::AdaptiveHadamard as i32,
            width: 8,
            height: 8,
            count: 16,
            seed: 0,
            params: None,
        };
        assert_eq!(
            PatternSpec::try_from(&m).unwrap().family(),
            &Family::AdaptiveHadamard {
                batch: 0,
                target_error: 0.0,
                persistence: crate::patterns::HADAMARD_PERSISTENCE,
                error_estimate: ErrorEstimate::Measured,
                frames: AdaptiveFrames::Pairs,
            }
        );
        let haar = |persistence| v1::PatternSpec {
            family: v1::PatternFamily::AdaptiveHaar as i32,
            params: Some(v1::pattern_spec::Params::Adaptive(v1::AdaptiveParams {
                batch: 0,
                target_error: 0.0,
                persistence,
                error_estimate: 0,
                frames: 0,
            })),
            ..m
        };
        for (set, expect) in [
            (None, crate::patterns::HAAR_PERSISTENCE),
            (Some(0.0), 0.0),
            (Some(2.0), 2.0),
        ] {
            let spec = PatternSpec::try_from(&haar(set)).unwrap();
            assert_eq!(spec.family().adaptive_persistence(), Some(expect));
        }
        assert_eq!(
            PatternSpec::try_from(&haar(Some(f64::NAN)))
                .unwrap_err()
                .field,
            "persistence"
        );
        let wrong = v1::PatternSpec {
            params: Some(v1::pattern_spec::Params::Speckle(v1::SpeckleParams {
                grain: 2,
            })),
            ..m
        };
        assert_eq!(PatternSpec::try_from(&wrong).unwrap_err().field, "params");
    }
}
