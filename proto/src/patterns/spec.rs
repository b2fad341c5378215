//! `PatternSpec`: a validated, canonical declaration of a session's patterns.

use std::sync::Arc;

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
    /// Adaptive scan of the 2D orthonormal Haar basis (`proto/PATTERNS.md`, adaptive_haar): the
    /// server chooses which Haar functions to show, batch by batch, from the values so far.
    AdaptiveHaar {
        /// Split pairs per batch; 0 = automatic sizing.
        #[serde(default)]
        batch: u32,
        /// Stop once the planner's estimated relative error is below this; 0 = whole budget.
        #[serde(default)]
        target_error: f64,
        /// Weight of a measured parent detail in its children's scores (PATTERNS.md, "The
        /// planner"): a child ranks as if its coefficient were at least `persistence` times its
        /// parent's. Absent in a new declaration: [`HAAR_PERSISTENCE`]; absent in a session stored
        /// before the parameter existed: 0 (the rule it was planned with).
        #[serde(default = "haar_persistence")]
        persistence: f64,
        /// What `target_error` is compared with (PATTERNS.md, "The planner"). Absent in a new
        /// declaration: [`ErrorEstimate::Measured`]; absent in a session stored before the
        /// parameter existed: [`ErrorEstimate::Prediction`] (the rule it was planned with).
        #[serde(default)]
        error_estimate: ErrorEstimate,
        /// How many frames show an index (PATTERNS.md, "Single frames"); absent: pairs (also
        /// every session stored before the parameter existed), and not written when pairs.
        #[serde(default, skip_serializing_if = "AdaptiveFrames::is_pairs")]
        frames: AdaptiveFrames,
    },
    /// Adaptive scan of the 2D Walsh-Hadamard basis (natural index, as the hadamard family).
    AdaptiveHadamard {
        #[serde(default)]
        batch: u32,
        #[serde(default)]
        target_error: f64,
        /// As for `adaptive_haar`; absent: [`HADAMARD_PERSISTENCE`].
        #[serde(default = "hadamard_persistence")]
        persistence: f64,
        /// As for `adaptive_haar`.
        #[serde(default)]
        error_estimate: ErrorEstimate,
        /// Only [`AdaptiveFrames::Pairs`] (single frames need Haar's blocks).
        #[serde(default, skip_serializing_if = "AdaptiveFrames::is_pairs")]
        frames: AdaptiveFrames,
    },
}

/// How an adaptive session shows its basis functions (`proto/PATTERNS.md`, "Single frames").
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AdaptiveFrames {
    /// Every index a split pair, `P+` then `P-`: two frames.
    #[default]
    Pairs,
    /// `adaptive_haar` only: index 0 as its pair (all on, all off), every other index its `P+`
    /// alone, `y-` following from the light on its block, which the planner keeps known by
    /// splitting whole blocks.
    Single,
}

impl AdaptiveFrames {
    pub fn name(self) -> &'static str {
        match self {
            AdaptiveFrames::Pairs => "pairs",
            AdaptiveFrames::Single => "single",
        }
    }
    pub fn is_pairs(&self) -> bool {
        *self == AdaptiveFrames::Pairs
    }
}

/// How an adaptive planner estimates the relative error of its zero-filled image, the number its
/// `target_error` stop compares with (`proto/PATTERNS.md`, "The planner").
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorEstimate {
    /// The predicted energy of the coefficients not yet shown, alone: a median 0.23-0.40 of the
    /// true error noise-free and blind to noise (what sessions stored before 2026-11-29 were
    /// planned with).
    Prediction,
    /// The predicted energy plus, per level, the mean squared miss of the predictions where the
    /// coefficient was measured, and the noise of every coefficient shown, as the pair sums of
    /// equal supports measure it.
    #[default]
    Measured,
}

impl ErrorEstimate {
    pub fn name(self) -> &'static str {
        match self {
            ErrorEstimate::Prediction => "prediction",
            ErrorEstimate::Measured => "measured",
        }
    }
}

fn one() -> u32 {
    1
}
fn half() -> f64 {
    0.5
}

/// `adaptive_haar`'s `persistence` when a new declaration leaves it out: along a step edge the
/// orthonormal Haar detail of a child is half its parent's (`docs/benchmark-notes.md` has the
/// measurements that chose it).
pub const HAAR_PERSISTENCE: f64 = 0.5;
/// `adaptive_hadamard`'s `persistence` when a new declaration leaves it out.
pub const HADAMARD_PERSISTENCE: f64 = 0.0;

fn haar_persistence() -> f64 {
    HAAR_PERSISTENCE
}
fn hadamard_persistence() -> f64 {
    HADAMARD_PERSISTENCE
}

impl Family {
    pub fn name(&self) -> &'static str {
        match self {
            Family::Raster { .. } => "raster",
            Family::Bernoulli { .. } => "bernoulli",
            Family::Hadamard { .. } => "hadamard",
            Family::Speckle { .. } => "speckle",
            Family::AdaptiveHaar { .. } => "adaptive_haar",
            Family::AdaptiveHadamard { .. } => "adaptive_hadamard",
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

    /// `adaptive_haar` (`haar`) or `adaptive_hadamard` with these parameters; `persistence`
    /// `None` takes the family's default ([`HAAR_PERSISTENCE`], [`HADAMARD_PERSISTENCE`]).
    pub fn adaptive(haar: bool, batch: u32, target_error: f64, persistence: Option<f64>) -> Family {
        if haar {
            Family::AdaptiveHaar {
                batch,
                target_error,
                persistence: persistence.unwrap_or(HAAR_PERSISTENCE),
                error_estimate: ErrorEstimate::default(),
                frames: AdaptiveFrames::Pairs,
            }
        } else {
            Family::AdaptiveHadamard {
                batch,
                target_error,
                persistence: persistence.unwrap_or(HADAMARD_PERSISTENCE),
                error_estimate: ErrorEstimate::default(),
                frames: AdaptiveFrames::Pairs,
            }
        }
    }

    /// This adaptive family showing its indices as `how` (other families unchanged; the spec's
    /// validation refuses single frames on `adaptive_hadamard`).
    pub fn with_frames(mut self, how: AdaptiveFrames) -> Family {
        if let Family::AdaptiveHaar { frames, .. } | Family::AdaptiveHadamard { frames, .. } =
            &mut self
        {
            *frames = how;
        }
        self
    }

    /// How an adaptive family shows its indices.
    pub fn adaptive_frames(&self) -> Option<AdaptiveFrames> {
        match *self {
            Family::AdaptiveHaar { frames, .. } | Family::AdaptiveHadamard { frames, .. } => {
                Some(frames)
            }
            _ => None,
        }
    }

    /// This adaptive family with `estimate` as its error estimate (other families unchanged).
    pub fn with_error_estimate(mut self, estimate: ErrorEstimate) -> Family {
        if let Family::AdaptiveHaar { error_estimate, .. }
        | Family::AdaptiveHadamard { error_estimate, .. } = &mut self
        {
            *error_estimate = estimate;
        }
        self
    }

    /// The planner's error estimate of an adaptive family.
    pub fn adaptive_error_estimate(&self) -> Option<ErrorEstimate> {
        match *self {
            Family::AdaptiveHaar { error_estimate, .. }
            | Family::AdaptiveHadamard { error_estimate, .. } => Some(error_estimate),
            _ => None,
        }
    }

    /// True for the adaptive families, whose pattern indices the server chooses during the
    /// session.
    pub fn is_adaptive(&self) -> bool {
        matches!(
            self,
            Family::AdaptiveHaar { .. } | Family::AdaptiveHadamard { .. }
        )
    }

    /// `(batch, target_error)` of an adaptive family.
    pub fn adaptive_params(&self) -> Option<(u32, f64)> {
        match *self {
            Family::AdaptiveHaar {
                batch,
                target_error,
                ..
            }
            | Family::AdaptiveHadamard {
                batch,
                target_error,
                ..
            } => Some((batch, target_error)),
            _ => None,
        }
    }

    /// The planner's `persistence` of an adaptive family.
    pub fn adaptive_persistence(&self) -> Option<f64> {
        match *self {
            Family::AdaptiveHaar { persistence, .. }
            | Family::AdaptiveHadamard { persistence, .. } => Some(persistence),
            _ => None,
        }
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
///
/// An adaptive spec (`adaptive_haar`, `adaptive_hadamard`) may also carry the basis indices the
/// session showed, in order ([`PatternSpec::with_indices`]): a *resolved* spec, which the pattern
/// generator and the operators need. The indices are not part of the declaration: they never go
/// to JSON or protobuf, and `==` ignores them.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(try_from = "RawSpec", into = "RawSpec")]
pub struct PatternSpec {
    family: Family,
    width: u32,
    height: u32,
    count: u64,
    seed: u64,
    indices: Option<Arc<[u32]>>,
}

/// Declarations compare; the resolved indices of an adaptive session do not.
impl PartialEq for PatternSpec {
    fn eq(&self, other: &Self) -> bool {
        self.family == other.family
            && self.width == other.width
            && self.height == other.height
            && self.count == other.count
            && self.seed == other.seed
    }
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
            Family::AdaptiveHaar {
                batch,
                target_error,
                persistence,
                frames,
                ..
            }
            | Family::AdaptiveHadamard {
                batch,
                target_error,
                persistence,
                frames,
                ..
            } => {
                let name = family.name();
                if frames == AdaptiveFrames::Single
                    && matches!(family, Family::AdaptiveHadamard { .. })
                {
                    return Err(err(
                        "frames",
                        "single frames are for adaptive_haar (a Walsh-Hadamard session shows pairs)",
                    ));
                }
                if !width.is_power_of_two() {
                    return Err(err(
                        "width",
                        format!("{name} needs a power of two, got {width}"),
                    ));
                }
                if height != width {
                    return Err(err(
                        "height",
                        format!(
                            "{name} needs a square image (height = width = {width}), got {height}"
                        ),
                    ));
                }
                if frames == AdaptiveFrames::Single {
                    if !(2..=pixels + 1).contains(&count) {
                        return Err(err(
                            "count",
                            format!(
                                "{name} with single frames shows index 0 as two frames and every other index as one: a budget of 2..={} frames (width * height + 1), got {count}",
                                pixels + 1
                            ),
                        ));
                    }
                } else if !count.is_multiple_of(2) || count > 2 * pixels {
                    return Err(err(
                        "count",
                        format!(
                            "{name} frames come in P+/P- pairs: an even budget up to 2 * width * height = {}, got {count}",
                            2 * pixels
                        ),
                    ));
                }
                if batch as u64 > pixels {
                    return Err(err(
                        "batch",
                        format!("must be 0 (automatic) or 1..={pixels} split pairs, got {batch}"),
                    ));
                }
                if !(target_error.is_finite() && target_error >= 0.0) {
                    return Err(err(
                        "target_error",
                        format!(
                            "must be a finite number >= 0 (0 = use the whole budget), got {target_error}"
                        ),
                    ));
                }
                if !(persistence.is_finite() && persistence >= 0.0) {
                    return Err(err(
                        "persistence",
                        format!(
                            "must be a finite number >= 0 (0 = rank by the prediction alone), got {persistence}"
                        ),
                    ));
                }
                family
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
            indices: None,
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

    /// The same patterns with another count (e.g. a prefix of the session's rows). A resolved
    /// adaptive spec keeps the indices of the pairs that fit in the new count.
    pub fn with_count(&self, count: u64) -> Result<Self, SpecError> {
        let mut spec = PatternSpec::new(
            self.family.clone(),
            self.width,
            self.height,
            count,
            self.seed,
        )?;
        if let Some(indices) = &self.indices {
            let keep = indices
                .len()
                .min(spec.adaptive_budget().unwrap_or(0) as usize);
            spec.indices = Some(if keep == indices.len() {
                indices.clone()
            } else {
                indices[..keep].into()
            });
        }
        Ok(spec)
    }

    /// True for `adaptive_haar` and `adaptive_hadamard` specs (resolved or not).
    pub fn is_adaptive(&self) -> bool {
        self.family.is_adaptive()
    }

    /// The basis indices of a resolved adaptive spec: pair `r` (frames `2r`, `2r + 1`) shows
    /// basis function `indices[r]` (single frames: [`PatternSpec::adaptive_rows`]). `None` for
    /// an unresolved or non-adaptive spec.
    pub fn adaptive_indices(&self) -> Option<&[u32]> {
        self.indices.as_deref()
    }

    /// True for an adaptive spec showing single frames (PATTERNS.md, "Single frames").
    pub fn adaptive_single(&self) -> bool {
        self.family.adaptive_frames() == Some(AdaptiveFrames::Single)
    }

    /// The most indices an adaptive spec's budget shows: `count / 2` pairs, or with single
    /// frames `count - 1` (index 0 takes two frames). `None` for other families.
    pub fn adaptive_budget(&self) -> Option<u64> {
        self.is_adaptive().then(|| {
            if self.adaptive_single() {
                self.count - 1
            } else {
                self.count / 2
            }
        })
    }

    /// Frames the first `indices` indices of an adaptive session take: `2 indices`, or with
    /// single frames `indices + 1` (and 0 for none). `None` for other families.
    pub fn adaptive_rows(&self, indices: u64) -> Option<u64> {
        self.is_adaptive().then(|| {
            if !self.adaptive_single() {
                2 * indices
            } else if indices == 0 {
                0
            } else {
                indices + 1
            }
        })
    }

    /// Indices whose frames are all within the first `rows` frames (the inverse of
    /// [`PatternSpec::adaptive_rows`], rounding down). `None` for other families.
    pub fn adaptive_indices_in(&self, rows: u64) -> Option<u64> {
        self.is_adaptive().then(|| {
            if !self.adaptive_single() {
                rows / 2
            } else {
                rows.saturating_sub(1)
            }
        })
    }

    /// The adaptive spec resolved with the indices the session showed, in order. Errors on a
    /// non-adaptive spec (field `family`), and on an index out of `0..width*height`, a repeated
    /// index or more indices than `count / 2` pairs (field `indices`). Fewer indices than
    /// `count / 2` is a session that stopped early (or is still running).
    pub fn with_indices(&self, indices: Arc<[u32]>) -> Result<PatternSpec, SpecError> {
        if !self.is_adaptive() {
            return Err(err(
                "family",
                format!(
                    "only adaptive families take pattern indices, not {}",
                    self.family.name()
                ),
            ));
        }
        let pairs = self.adaptive_budget().expect("adaptive");
        if indices.len() as u64 > pairs {
            return Err(err(
                "indices",
                format!(
                    "{} indices, but a budget of {} frames holds {pairs} {}",
                    indices.len(),
                    self.count,
                    if self.adaptive_single() {
                        "single-frame indices"
                    } else {
                        "split pairs"
                    }
                ),
            ));
        }
        if self.adaptive_single() && indices.first().is_some_and(|&n| n != 0) {
            return Err(err(
                "indices",
                "a single-frame session starts with index 0 (its pair measures the light and the dark level)",
            ));
        }
        let k = self.pixels();
        let mut seen = vec![false; k];
        for (r, &n) in indices.iter().enumerate() {
            let Some(slot) = seen.get_mut(n as usize) else {
                return Err(err(
                    "indices",
                    format!("index {n} of pair {r} is out of range 0..{k}"),
                ));
            };
            if std::mem::replace(slot, true) {
                return Err(err(
                    "indices",
                    format!("index {n} of pair {r} was already shown"),
                ));
            }
        }
        let mut spec = self.clone();
        spec.indices = Some(indices);
        Ok(spec)
    }

    /// The declaration alone (an adaptive spec without its indices).
    pub fn unresolved(&self) -> PatternSpec {
        PatternSpec {
            indices: None,
            ..self.clone()
        }
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
            (
                r#"{"family":"adaptive_haar","width":12,"height":12,"count":8}"#,
                "width",
            ),
            (
                r#"{"family":"adaptive_hadamard","width":16,"height":8,"count":8}"#,
                "height",
            ),
            (
                r#"{"family":"adaptive_hadamard","width":8,"height":8,"count":7}"#,
                "count",
            ),
            (
                r#"{"family":"adaptive_haar","width":8,"height":8,"count":130}"#,
                "count",
            ),
            (
                r#"{"family":"adaptive_haar","width":8,"height":8,"count":8,"batch":65}"#,
                "batch",
            ),
            (
                r#"{"family":"adaptive_haar","width":8,"height":8,"count":8,"target_error":-1}"#,
                "target_error",
            ),
            (
                r#"{"family":"adaptive_hadamard","width":8,"height":8,"count":8,"persistence":-0.5}"#,
                "persistence",
            ),
        ];
        // An unknown error estimate is refused by the parser, naming the value.
        let e = serde_json::from_str::<PatternSpec>(
            r#"{"family":"adaptive_haar","width":8,"height":8,"count":8,"error_estimate":"oracle"}"#,
        )
        .unwrap_err();
        assert!(e.to_string().contains("oracle"), "{e}");
        for (json, field) in cases {
            let raw: RawSpec = serde_json::from_str(json).unwrap();
            let e = PatternSpec::try_from(raw).unwrap_err();
            assert_eq!(e.field, field, "{json}: {e}");
        }
    }

    #[test]
    fn adaptive_specs_validate_and_resolve() {
        let s: PatternSpec = serde_json::from_str(
            r#"{"family":"adaptive_haar","width":8,"height":8,"count":40,"target_error":0.05}"#,
        )
        .unwrap();
        // An absent persistence is the family's default, and the canonical form states it.
        assert_eq!(
            s.family(),
            &Family::AdaptiveHaar {
                batch: 0,
                target_error: 0.05,
                persistence: HAAR_PERSISTENCE,
                error_estimate: ErrorEstimate::Measured,
                frames: AdaptiveFrames::Pairs,
            }
        );
        assert!(s.is_adaptive() && s.adaptive_indices().is_none());
        assert_eq!(
            s.to_json(),
            r#"{"family":"adaptive_haar","batch":0,"target_error":0.05,"persistence":0.5,"error_estimate":"measured","width":8,"height":8,"count":40,"seed":0}"#
        );
        let prediction: PatternSpec = serde_json::from_str(
            r#"{"family":"adaptive_haar","width":8,"height":8,"count":40,"target_error":0.05,"error_estimate":"prediction"}"#,
        )
        .unwrap();
        assert_eq!(
            prediction.family().adaptive_error_estimate(),
            Some(ErrorEstimate::Prediction)
        );
        assert_ne!(prediction, s);
        let h: PatternSpec = serde_json::from_str(
            r#"{"family":"adaptive_hadamard","width":8,"height":8,"count":40}"#,
        )
        .unwrap();
        assert_eq!(
            h.family().adaptive_persistence(),
            Some(HADAMARD_PERSISTENCE)
        );
        let zero: PatternSpec = serde_json::from_str(
            r#"{"family":"adaptive_haar","width":8,"height":8,"count":40,"target_error":0.05,"persistence":0}"#,
        )
        .unwrap();
        assert_eq!(zero.family().adaptive_persistence(), Some(0.0));
        assert_ne!(zero, s);
        let r = s.with_indices(Arc::from(vec![0u32, 9, 63])).unwrap();
        assert_eq!(r.adaptive_indices(), Some(&[0u32, 9, 63][..]));
        // The indices are not part of the declaration.
        assert_eq!(r, s);
        assert_eq!(r.to_json(), s.to_json());
        assert_eq!(r.unresolved().adaptive_indices(), None);
        // A shorter count keeps the pairs that fit.
        assert_eq!(
            r.with_count(4).unwrap().adaptive_indices(),
            Some(&[0u32, 9][..])
        );
        for (indices, what) in [
            (vec![0u32, 64], "out of range"),
            (vec![5, 1, 5], "already shown"),
            ((0..21).collect(), "holds 20 split pairs"),
        ] {
            let e = s.with_indices(Arc::from(indices)).unwrap_err();
            assert_eq!(e.field, "indices");
            assert!(e.message.contains(what), "{e}");
        }
        let bernoulli = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 8, 8, 8, 0).unwrap();
        assert_eq!(
            bernoulli
                .with_indices(Arc::from(vec![0u32]))
                .unwrap_err()
                .field,
            "family"
        );
        assert!(!bernoulli.is_adaptive());
        // Another family's parameter is refused.
        assert!(
            serde_json::from_str::<PatternSpec>(
                r#"{"family":"adaptive_haar","width":8,"height":8,"count":8,"ordering":"natural"}"#
            )
            .is_err()
        );
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

    #[test]
    fn single_frame_specs_state_frames_count_their_frames_and_refuse_what_they_cannot_show() {
        let json =
            r#"{"family":"adaptive_haar","width":8,"height":8,"count":65,"frames":"single"}"#;
        let s: PatternSpec = serde_json::from_str(json).unwrap();
        assert!(s.adaptive_single());
        assert_eq!(
            s.to_json(),
            r#"{"family":"adaptive_haar","batch":0,"target_error":0.0,"persistence":0.5,"error_estimate":"measured","frames":"single","width":8,"height":8,"count":65,"seed":0}"#
        );
        let back: PatternSpec = serde_json::from_str(&s.to_json()).unwrap();
        assert_eq!(back, s);
        assert!(back.adaptive_single());
        // Pairs, stated or not, keep the canonical form every spec had before the field.
        let pairs: PatternSpec = serde_json::from_str(
            r#"{"family":"adaptive_haar","width":8,"height":8,"count":64,"frames":"pairs"}"#,
        )
        .unwrap();
        assert!(!pairs.to_json().contains("frames"));
        assert!(!pairs.adaptive_single());
        // Index 0 takes two frames, every other index one: k + 1 frames show all k.
        assert_eq!(s.adaptive_budget(), Some(64));
        assert_eq!(pairs.adaptive_budget(), Some(32));
        assert_eq!(
            (0..4)
                .map(|j| s.adaptive_rows(j).unwrap())
                .collect::<Vec<_>>(),
            [0, 2, 3, 4]
        );
        assert_eq!(
            (0..5)
                .map(|r| s.adaptive_indices_in(r).unwrap())
                .collect::<Vec<_>>(),
            [0, 0, 1, 2, 3]
        );
        assert_eq!(pairs.adaptive_rows(3), Some(6));
        let family = |count: u64, haar: bool| {
            PatternSpec::new(
                Family::adaptive(haar, 0, 0.0, None).with_frames(AdaptiveFrames::Single),
                8,
                8,
                count,
                0,
            )
        };
        assert!(family(2, true).is_ok() && family(33, true).is_ok());
        assert_eq!(family(1, true).unwrap_err().field, "count");
        assert_eq!(family(66, true).unwrap_err().field, "count");
        assert_eq!(family(64, false).unwrap_err().field, "frames");
        // A resolved single-frame spec starts at index 0 and holds at most count - 1 indices.
        let r = s.with_indices(Arc::from(vec![0u32, 1, 8, 9])).unwrap();
        assert_eq!(r.adaptive_indices(), Some(&[0u32, 1, 8, 9][..]));
        assert_eq!(
            s.with_indices(Arc::from(vec![1u32, 0])).unwrap_err().field,
            "indices"
        );
        let small = family(3, true).unwrap();
        assert_eq!(
            small
                .with_indices(Arc::from(vec![0u32, 1, 8]))
                .unwrap_err()
                .field,
            "indices"
        );
        assert_eq!(
            r.with_count(3).unwrap().adaptive_indices(),
            Some(&[0u32, 1][..])
        );
        // Protobuf: single survives the round trip, pairs travel as unset.
        let m = crate::v1::PatternSpec::from(&s);
        assert_eq!(PatternSpec::try_from(&m).unwrap(), s);
        match m.params {
            Some(crate::v1::pattern_spec::Params::Adaptive(p)) => {
                assert_eq!(p.frames, crate::v1::AdaptiveFrames::Single as i32)
            }
            other => panic!("{other:?}"),
        }
        match crate::v1::PatternSpec::from(&pairs).params {
            Some(crate::v1::pattern_spec::Params::Adaptive(p)) => assert_eq!(p.frames, 0),
            other => panic!("{other:?}"),
        }
    }
}
