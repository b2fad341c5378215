//! `PatternSpec`: a validated, canonical declaration of a session's patterns.

use serde::{Deserialize, Serialize};

use super::hadamard::HadamardOrdering;

/// Largest accepted width or height.
pub const MAX_SIDE: u32 = 4096;
/// Largest accepted number of pattern pixels k = width * height (2048 x 2048).
pub const MAX_PIXELS: u64 = 1 << 22;
/// Largest accepted number of patterns in one session (correlation GI needs ~1e6).
pub const MAX_COUNT: u64 = 10_000_000;
/// Bernoulli fill is quantised to multiples of 2^-FILL_BITS.
pub const FILL_BITS: u32 = 16;

/// The pattern family and its parameters.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "family", rename_all = "snake_case", deny_unknown_fields)]
pub enum Family {
    Raster {
        #[serde(default = "one")]
        block: u32,
        /// How many times the block scan may repeat (e.g. to average noise): `count` is at most
        /// `scans * BW * BH`. One scan by default, so a count beyond the blocks is refused unless
        /// the repeat is declared.
        #[serde(default = "one")]
        scans: u32,
    },
    Bernoulli {
        #[serde(default = "half")]
        fill: f64,
    },
    Hadamard {
        #[serde(default)]
        ordering: HadamardOrdering,
    },
    Speckle {
        #[serde(default = "one")]
        grain: u32,
    },
}

fn one() -> u32 {
    1
}
fn half() -> f64 {
    0.5
}

impl Family {
    pub fn name(&self) -> &'static str {
        match self {
            Family::Raster { .. } => "raster",
            Family::Bernoulli { .. } => "bernoulli",
            Family::Hadamard { .. } => "hadamard",
            Family::Speckle { .. } => "speckle",
        }
    }

    /// Raster with block `block` declaring just enough scans for `count` patterns on a
    /// `width x height` image (at least one).
    pub fn raster_covering(block: u32, width: u32, height: u32, count: u64) -> Family {
        let b = block.max(1);
        let blocks = (width.div_ceil(b) as u64 * height.div_ceil(b) as u64).max(1);
        let scans = count.div_ceil(blocks).clamp(1, u32::MAX as u64) as u32;
        Family::Raster { block, scans }
    }

    /// True when every pattern value is 0 or 1.
    pub fn is_binary(&self) -> bool {
        !matches!(self, Family::Speckle { .. })
    }
}

/// Why a spec was refused; `field` names the offending field as it appears in JSON.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct SpecError {
    pub field: &'static str,
    pub message: String,
}

fn err(field: &'static str, message: impl Into<String>) -> SpecError {
    SpecError {
        field,
        message: message.into(),
    }
}

/// A pattern declaration that has been validated and canonicalised (defaults filled in, Bernoulli
/// fill quantised). Specs compare field by field: two Bernoulli fills that quantise alike are
/// equal, but the seed is kept as declared even for raster and Hadamard, which do not use it.
///
/// JSON form: `{"family": "bernoulli", "width": 64, "height": 64, "count": 4096, "seed": 7,
/// "fill": 0.5}`; family parameters sit beside the common fields.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawSpec", into = "RawSpec")]
pub struct PatternSpec {
    family: Family,
    width: u32,
    height: u32,
    count: u64,
    seed: u64,
}

#[derive(Clone, Serialize, Deserialize)]
struct RawSpec {
    #[serde(flatten)]
    family: Family,
    width: u32,
    height: u32,
    count: u64,
    #[serde(default)]
    seed: u64,
}

impl TryFrom<RawSpec> for PatternSpec {
    type Error = SpecError;
    fn try_from(raw: RawSpec) -> Result<Self, SpecError> {
        PatternSpec::new(raw.family, raw.width, raw.height, raw.count, raw.seed)
    }
}

impl From<PatternSpec> for RawSpec {
    fn from(s: PatternSpec) -> Self {
        RawSpec {
            family: s.family,
            width: s.width,
            height: s.height,
            count: s.count,
            seed: s.seed,
        }
    }
}

impl PatternSpec {
    pub fn new(
        family: Family,
        width: u32,
        height: u32,
        count: u64,
        seed: u64,
    ) -> Result<Self, SpecError> {
        if width == 0 || width > MAX_SIDE {
            return Err(err("width", format!("must be 1..={MAX_SIDE}, got {width}")));
        }
        if height == 0 || height > MAX_SIDE {
            return Err(err(
                "height",
                format!("must be 1..={MAX_SIDE}, got {height}"),
            ));
        }
        let pixels = width as u64 * height as u64;
        if pixels > MAX_PIXELS {
            return Err(err(
                "width",
                format!("width * height = {pixels} exceeds the limit of {MAX_PIXELS} pixels"),
            ));
        }
        if count == 0 || count > MAX_COUNT {
            return Err(err(
                "count",
                format!("must be 1..={MAX_COUNT}, got {count}"),
            ));
        }
        let family = match family {
            Family::Raster { block, scans } => {
                if block == 0 || block > width.max(height) {
                    return Err(err(
                        "block",
                        format!(
                            "must be 1..={} (the larger side), got {block}",
                            width.max(height)
                        ),
                    ));
                }
                let blocks = width.div_ceil(block) as u64 * height.div_ceil(block) as u64;
                let max_scans = MAX_COUNT.div_ceil(blocks);
                if scans == 0 || scans as u64 > max_scans {
                    return Err(err(
                        "scans",
                        format!(
                            "must be 1..={max_scans} (up to {MAX_COUNT} patterns), got {scans}"
                        ),
                    ));
                }
                if count > scans as u64 * blocks {
                    let needed = count.div_ceil(blocks);
                    return Err(err(
                        "count",
                        format!(
                            "a raster of {width}x{height} with block {block} has {blocks} patterns \
                             per scan, so {scans} scan(s) hold at most {}, got {count}; to repeat \
                             the scan (e.g. to average noise) declare \"scans\": {needed}",
                            scans as u64 * blocks
                        ),
                    ));
                }
                Family::Raster { block, scans }
            }
            Family::Bernoulli { fill } => {
                if !(fill > 0.0 && fill < 1.0) {
                    return Err(err("fill", format!("must be in (0, 1), got {fill}")));
                }
                let q = fill_quantum(fill);
                Family::Bernoulli {
                    fill: q as f64 / (1u64 << FILL_BITS) as f64,
                }
            }
            Family::Hadamard { ordering } => {
                if !width.is_power_of_two() {
                    return Err(err(
                        "width",
                        format!("hadamard needs a power of two, got {width}"),
                    ));
                }
                if !height.is_power_of_two() {
                    return Err(err(
                        "height",
                        format!("hadamard needs a power of two, got {height}"),
                    ));
                }
                if !count.is_multiple_of(2) || count > 2 * pixels {
                    return Err(err(
                        "count",
                        format!(
                            "hadamard frames come in P+/P- pairs: an even count up to 2 * width * height = {}, got {count}",
                            2 * pixels
                        ),
                    ));
                }
                Family::Hadamard { ordering }
            }
            Family::Speckle { grain } => {
                if grain == 0 || grain > width.max(height) {
                    return Err(err(
                        "grain",
                        format!(
                            "must be 1..={} (the larger side), got {grain}",
                            width.max(height)
                        ),
                    ));
                }
                Family::Speckle { grain }
            }
        };
        Ok(PatternSpec {
            family,
            width,
            height,
            count,
            seed,
        })
    }

    pub fn family(&self) -> &Family {
        &self.family
    }
    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    /// Number of frames shown.
    pub fn count(&self) -> u64 {
        self.count
    }
    pub fn seed(&self) -> u64 {
        self.seed
    }
    /// Number of pattern pixels k = width * height.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// The same patterns with another count (e.g. a prefix of the session's rows).
    pub fn with_count(&self, count: u64) -> Result<Self, SpecError> {
        PatternSpec::new(
            self.family.clone(),
            self.width,
            self.height,
            count,
            self.seed,
        )
    }

    /// Raster: blocks per row and per column.
    pub fn raster_grid(&self) -> Option<(u32, u32, u32)> {
        match self.family {
            Family::Raster { block, .. } => Some((
                block,
                self.width.div_ceil(block),
                self.height.div_ceil(block),
            )),
            _ => None,
        }
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("spec serialises")
    }
}

/// `round(fill * 2^16)` clamped to 1..=65535.
pub fn fill_quantum(fill: f64) -> u32 {
    let q = (fill * (1u64 << FILL_BITS) as f64).round();
    q.clamp(1.0, ((1u64 << FILL_BITS) - 1) as f64) as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_round_trip_and_defaults() {
        let s: PatternSpec = serde_json::from_str(
            r#"{"family":"bernoulli","width":64,"height":32,"count":100,"seed":9}"#,
        )
        .unwrap();
        assert_eq!(s.family(), &Family::Bernoulli { fill: 0.5 });
        let back: PatternSpec = serde_json::from_str(&s.to_json()).unwrap();
        assert_eq!(back, s);
        let h: PatternSpec = serde_json::from_str(
            r#"{"family":"hadamard","width":8,"height":8,"count":128,"ordering":"russian_doll"}"#,
        )
        .unwrap();
        assert_eq!(
            h.family(),
            &Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll
            }
        );
    }

    #[test]
    fn absurd_specs_name_their_field() {
        let cases = [
            (
                r#"{"family":"raster","width":0,"height":8,"count":8}"#,
                "width",
            ),
            (
                r#"{"family":"raster","width":8,"height":8,"count":1000000000}"#,
                "count",
            ),
            (
                r#"{"family":"raster","width":8,"height":8,"count":0}"#,
                "count",
            ),
            // More patterns than the 64 blocks of one scan, with no repeat declared.
            (
                r#"{"family":"raster","width":8,"height":8,"count":65}"#,
                "count",
            ),
            (
                r#"{"family":"raster","width":10,"height":7,"block":3,"scans":2,"count":25}"#,
                "count",
            ),
            (
                r#"{"family":"raster","width":8,"height":8,"count":64,"scans":0}"#,
                "scans",
            ),
            (
                r#"{"family":"bernoulli","width":8,"height":8,"count":8,"fill":1.5}"#,
                "fill",
            ),
            (
                r#"{"family":"hadamard","width":12,"height":8,"count":8}"#,
                "width",
            ),
            (
                r#"{"family":"hadamard","width":8,"height":8,"count":7}"#,
                "count",
            ),
            (
                r#"{"family":"hadamard","width":8,"height":8,"count":130}"#,
                "count",
            ),
            (
                r#"{"family":"speckle","width":8,"height":8,"count":8,"grain":0}"#,
                "grain",
            ),
            (
                r#"{"family":"raster","width":4096,"height":4096,"count":8}"#,
                "width",
            ),
        ];
        for (json, field) in cases {
            let raw: RawSpec = serde_json::from_str(json).unwrap();
            let e = PatternSpec::try_from(raw).unwrap_err();
            assert_eq!(e.field, field, "{json}: {e}");
        }
    }

    #[test]
    fn fill_is_canonical() {
        let a = PatternSpec::new(Family::Bernoulli { fill: 0.3 }, 4, 4, 4, 0).unwrap();
        let b = PatternSpec::new(Family::Bernoulli { fill: 0.300001 }, 4, 4, 4, 0).unwrap();
        assert_eq!(a, b);
        assert_eq!(
            a.family(),
            &Family::Bernoulli {
                fill: 19661.0 / 65536.0
            }
        );
    }

    #[test]
    fn raster_repeats_only_when_declared() {
        // 10 x 7 with block 3: 12 blocks per scan.
        let one: PatternSpec = serde_json::from_str(
            r#"{"family":"raster","width":10,"height":7,"block":3,"count":12}"#,
        )
        .unwrap();
        assert_eq!(one.family(), &Family::Raster { block: 3, scans: 1 });
        let e = one.with_count(13).unwrap_err();
        assert_eq!(e.field, "count");
        assert!(e.message.contains(r#""scans": 2"#), "{e}");
        // Two and a half scans, declared as three.
        let rep = PatternSpec::new(Family::Raster { block: 3, scans: 3 }, 10, 7, 30, 0).unwrap();
        assert_eq!(rep.count(), 30);
        let back: PatternSpec = serde_json::from_str(&rep.to_json()).unwrap();
        assert_eq!(back, rep);
        assert!(rep.to_json().contains(r#""scans":3"#));
        // The scan count is bounded by MAX_COUNT patterns.
        let e = PatternSpec::new(
            Family::Raster {
                block: 1,
                scans: u32::MAX,
            },
            8,
            8,
            64,
            0,
        )
        .unwrap_err();
        assert_eq!(e.field, "scans");
    }
}
