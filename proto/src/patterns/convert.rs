//! Conversions between the gRPC `PatternSpec` message and the validated [`PatternSpec`].

use super::{Family, HadamardOrdering, PatternSpec, SpecError};
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
            Ok(v1::PatternFamily::Unspecified) | Err(_) => {
                return Err(SpecError {
                    field: "family",
                    message: format!(
                        "must be raster, bernoulli, hadamard or speckle (got enum value {})",
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
