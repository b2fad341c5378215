//! Photometric stereo from the dual images of several bucket detectors (Woodham 1980; Sun et al.
//! 2013, "3D computational imaging with single-pixel detectors").
//!
//! By Helmholtz reciprocity, channel `c`'s dual image is the scene seen from the projector and lit
//! from detector `c`'s direction `l_c` (a unit vector in scene coordinates: x right along the
//! image rows, y down the image, z toward the projector). A Lambertian scene gives
//!
//! ```text
//! I_c(x) = g_c * albedo(x) * max(0, n(x) . l_c)
//! ```
//!
//! with `g_c` the detector's gain. Dividing by the gains and writing `b = albedo * n`, every lit
//! channel is one linear equation `I_c / g_c = b . l_c`; three or more lit channels with
//! directions spanning 3-D give `b` by least squares, `albedo = |b|`, `n = b / |b|`.
//!
//! # Shadows
//! A channel whose (gain-corrected) value at a pixel is at most `shadow_threshold` times that
//! pixel's brightest channel is taken as shadowed there (attached shadow, `n . l_c <= 0`, or a cast
//! shadow) and dropped: it carries an inequality, not an equation. A pixel left with fewer than
//! three lit channels, or whose lit directions are nearly coplanar, or whose brightest channel is
//! below `dark_threshold` times the image's 99th-percentile pixel, gets no normal: `[0, 0, 0]`,
//! albedo and residual NaN, and is counted by reason in the report.
//!
//! # Gains
//! [`Gains::Equal`] assumes matched detectors; [`Gains::Given`] divides by known gains (e.g. the
//! dual images of a flat white card facing the projector). With unknown gains and three detectors
//! nothing pins them: any gains `G` fit the data with the normals `normalise(L^-1 G^-1 L n)`, a
//! linear ambiguity. With four or more detectors the model itself fixes the gains up to one common
//! factor (absorbed in the albedo): at pixels lit by every detector, `(I_c / g_c)_c` must lie in
//! the 3-D column space of `L`, so `h = 1/g` solves `P (h o I(x)) = 0` for all such `x`, where `P`
//! projects onto the null space of `L^T` ([`Gains::Estimate`]: the smallest eigenvector of
//! `P o sum_x I(x) I(x)^T`, refitted once without the worst-fitting 10 % of pixels, normalised to
//! mean gain 1). This assumes the scene is Lambertian at those pixels, the gains are uniform over
//! the scene, and the normals there vary in all three dimensions: a flat scene cannot tell a gain
//! from a direction, and the estimate is refused. [`Gains::Auto`] (the default) estimates when it
//! can and otherwise assumes equal gains; the report says which it did and why.
//!
//! # Where the Lambertian model fails
//! The report lists these (`lambertian_fails_where`) and the per-pixel `residual` shows them: the
//! relative misfit `||I' - albedo max(0, L n)|| / ||I'||` over all of the pixel's channels
//! (gain-corrected), including the dropped ones, so a cast shadow (a channel dark where the normal
//! faces its detector) shows up even though its normal is still fitted from the other channels.
//! - Specular highlights: one channel far brighter than the cosine law allows; it tilts the normal
//!   toward that detector and raises the residual.
//! - Interreflections in concave regions: light bounced from nearby surfaces adds to every channel,
//!   flattening the recovered shape.
//! - Detectors near the scene: `l_c` then varies over the scene (and so does the irradiance with
//!   distance); one direction per detector is only right for distant detectors.
//! - Cast shadows: handled by dropping the channel when three remain, but a shadow only partly
//!   darker than the threshold biases the normal.
//! - Non-uniform gains (vignetting of the detector's field of view, projector fall-off): act like a
//!   spatially varying albedo per channel and bias the normals.
//! - Pixels fitted with exactly three channels have no redundancy: their residual checks only the
//!   dropped channels.

use std::collections::HashMap;

use rayon::prelude::*;
use serde_json::{Value, json};

/// At most this many channels (lit sets are kept as a 64-bit mask).
pub const MAX_CHANNELS: usize = 64;
/// Directions are unit vectors within this tolerance (then normalised exactly).
pub const UNIT_TOLERANCE: f64 = 1e-3;
/// Direction sets (all of them, or the lit subset of a pixel) with `sigma_min / sigma_max` of `L`
/// below this are degenerate (nearly coplanar): `n` is then poorly determined along one axis.
pub const MIN_DIRECTION_CONDITION: f64 = 0.02;

/// How the detector gains `g_c` are obtained.
#[derive(Clone, Debug, PartialEq)]
pub enum Gains {
    /// All detectors equally sensitive (`g_c = 1`).
    Equal,
    /// Known gains, one per channel, finite and > 0.
    Given(Vec<f64>),
    /// Estimated from the images (four or more channels, a scene with normals varying in 3-D);
    /// refused with [`PhotometricError::GainsUndetermined`] when the data do not fix them.
    Estimate,
    /// [`Gains::Estimate`] when the data fix the gains, else [`Gains::Equal`] (the report says).
    Auto,
}

#[derive(Clone, Debug, PartialEq)]
pub struct PhotometricOptions {
    /// A channel at most this fraction of the pixel's brightest channel is shadowed there.
    pub shadow_threshold: f64,
    /// A pixel whose brightest channel is at most this fraction of the image's 99th-percentile
    /// pixel is too dark to fit. It must sit well above the noise: a pixel whose channels are
    /// noise around 0 gets a random normal (and a large residual when 4+ channels are lit).
    pub dark_threshold: f64,
    pub gains: Gains,
}

impl Default for PhotometricOptions {
    fn default() -> Self {
        PhotometricOptions {
            shadow_threshold: 0.05,
            dark_threshold: 0.05,
            gains: Gains::Auto,
        }
    }
}

impl PhotometricOptions {
    /// Options from request parameters: `{"shadow_threshold": 0.05, "dark_threshold": 0.05,
    /// "gains": "auto" | "equal" | "estimate" | [g_0, g_1, ...]}`, every key optional (the
    /// defaults above), unknown keys refused. Gains given as numbers are checked against the
    /// channels by [`photometric_stereo`].
    pub fn from_params(params: &Value) -> Result<Self, PhotometricError> {
        let mut options = PhotometricOptions::default();
        let map = match params {
            Value::Null => return Ok(options),
            Value::Object(map) => map,
            other => {
                return Err(PhotometricError::BadOption {
                    field: "params",
                    message: format!("must be an object, got {other}"),
                });
            }
        };
        for (key, value) in map {
            match key.as_str() {
                "shadow_threshold" | "dark_threshold" => {
                    let field = if key == "shadow_threshold" {
                        "shadow_threshold"
                    } else {
                        "dark_threshold"
                    };
                    let v = value.as_f64().ok_or_else(|| PhotometricError::BadOption {
                        field,
                        message: format!("must be a number in [0, 1), got {value}"),
                    })?;
                    *(if field == "shadow_threshold" {
                        &mut options.shadow_threshold
                    } else {
                        &mut options.dark_threshold
                    }) = v;
                }
                "gains" => {
                    options.gains = match value {
                        Value::String(s) if s == "auto" => Gains::Auto,
                        Value::String(s) if s == "equal" => Gains::Equal,
                        Value::String(s) if s == "estimate" => Gains::Estimate,
                        Value::Array(items) => Gains::Given(
                            items
                                .iter()
                                .enumerate()
                                .map(|(c, v)| {
                                    v.as_f64().ok_or_else(|| {
                                        PhotometricError::BadGains(format!(
                                            "gain of channel {c} must be a number, got {v}"
                                        ))
                                    })
                                })
                                .collect::<Result<_, _>>()?,
                        ),
                        other => {
                            return Err(PhotometricError::BadGains(format!(
                                "must be \"auto\", \"equal\", \"estimate\" or one number per channel, got {other}"
                            )));
                        }
                    }
                }
                _ => {
                    return Err(PhotometricError::BadOption {
                        field: "params",
                        message: format!(
                            "unknown parameter {key:?}; known: shadow_threshold, dark_threshold, gains"
                        ),
                    });
                }
            }
        }
        Ok(options)
    }
}

/// Per-pixel results, row-major `width x height`.
#[derive(Clone, Debug)]
pub struct NormalMap {
    pub width: u32,
    pub height: u32,
    /// Unit normals with `z >= 0`; `[0, 0, 0]` where undetermined.
    pub normals: Vec<[f32; 3]>,
    /// In units of the gain-corrected images; NaN where undetermined.
    pub albedo: Vec<f32>,
    /// Relative misfit of the Lambertian model over all channels; NaN where undetermined.
    pub residual: Vec<f32>,
    /// Channels used per pixel (shadowed ones dropped); 0 for dark pixels, below 3 where too few
    /// channels were lit.
    pub lit: Vec<u8>,
}

impl NormalMap {
    pub fn is_determined(&self, pixel: usize) -> bool {
        self.normals[pixel] != [0.0; 3]
    }

    /// The normals interleaved `(height, width, 3)`, for the server's NPY writer.
    pub fn normals_interleaved(&self) -> Vec<f32> {
        self.normals.iter().flatten().copied().collect()
    }
}

/// Bad input to [`photometric_stereo`]; [`PhotometricError::field`] names the offending input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PhotometricError {
    #[error("photometric stereo needs at least 3 channels, got {channels}")]
    TooFewChannels { channels: usize },
    #[error("at most {MAX_CHANNELS} channels, got {channels}")]
    TooManyChannels { channels: usize },
    #[error("image size {width}x{height} is empty or too large")]
    BadSize { width: u32, height: u32 },
    #[error("channel {channel} has {got} values, expected width x height = {expected}")]
    SizeMismatch {
        channel: usize,
        expected: usize,
        got: usize,
    },
    #[error("{got} directions for {expected} channels (one per channel)")]
    DirectionCount { expected: usize, got: usize },
    #[error("direction of channel {channel} is not a unit vector (norm {norm})")]
    NonUnitDirection { channel: usize, norm: f64 },
    #[error(
        "directions are (nearly) coplanar: sigma_min/sigma_max = {condition:.3e} < {MIN_DIRECTION_CONDITION}; \
         photometric stereo needs directions spanning 3-D"
    )]
    CoplanarDirections { condition: f64 },
    #[error("gains: {0}")]
    BadGains(String),
    #[error("gains cannot be estimated: {0}")]
    GainsUndetermined(String),
    #[error("{field}: {message}")]
    BadOption {
        field: &'static str,
        message: String,
    },
}

impl PhotometricError {
    /// The input at fault: `images`, `images[2]`, `width`, `directions`, `directions[1]`, `gains`,
    /// `shadow_threshold`, ...
    pub fn field(&self) -> String {
        match self {
            Self::TooFewChannels { .. } | Self::TooManyChannels { .. } => "images".into(),
            Self::BadSize { width, .. } => if *width == 0 { "width" } else { "height" }.into(),
            Self::SizeMismatch { channel, .. } => format!("images[{channel}]"),
            Self::DirectionCount { .. } | Self::CoplanarDirections { .. } => "directions".into(),
            Self::NonUnitDirection { channel, .. } => format!("directions[{channel}]"),
            Self::BadGains(_) | Self::GainsUndetermined(_) => "gains".into(),
            Self::BadOption { field, .. } => (*field).into(),
        }
    }
}

/// Normals, albedo and residual per pixel from `images` (one dual image per channel, row-major
/// `width x height`) lit from `directions` (unit vectors, one per channel), and a JSON report.
pub fn photometric_stereo(
    images: &[&[f32]],
    directions: &[[f64; 3]],
    width: u32,
    height: u32,
    options: &PhotometricOptions,
) -> Result<(NormalMap, Value), PhotometricError> {
    let k = images.len();
    let dirs = validate(images, directions, width, height, options)?;
    let pixels = width as usize * height as usize;

    let (gains, gain_report) = resolve_gains(images, &dirs, options)?;
    let inv_gain: Vec<f64> = gains.iter().map(|g| 1.0 / g).collect();

    // The reference brightness for "dark": the 99th percentile of the pixels' brightest channel.
    let brightest = |p: usize| {
        (0..k)
            .map(|c| images[c][p] as f64 * inv_gain[c])
            .filter(|v| v.is_finite())
            .fold(f64::NEG_INFINITY, f64::max)
    };
    let finite_max: Vec<f64> = (0..pixels)
        .into_par_iter()
        .map(brightest)
        .filter(|v| v.is_finite())
        .collect();
    let reference = percentile(finite_max, 0.99);
    let dark_level = if reference > 0.0 {
        options.dark_threshold * reference
    } else {
        f64::INFINITY
    };

    // Blocks of pixels over the rayon threads, each with its own cache of lit-set solvers.
    let fitter = PixelFitter {
        images,
        dirs: &dirs,
        inv_gain: &inv_gain,
        shadow_threshold: options.shadow_threshold,
        dark_level,
    };
    let blocks: Vec<Block> = (0..pixels.div_ceil(BLOCK))
        .into_par_iter()
        .map(|b| fitter.fit(b * BLOCK..((b + 1) * BLOCK).min(pixels)))
        .collect();
    let mut map = NormalMap {
        width,
        height,
        normals: Vec::with_capacity(pixels),
        albedo: Vec::with_capacity(pixels),
        residual: Vec::with_capacity(pixels),
        lit: Vec::with_capacity(pixels),
    };
    let mut counts = Counts {
        dropped: vec![0; k],
        by_lit: vec![0; k + 1],
        ..Counts::default()
    };
    for block in blocks {
        map.normals.extend(block.normals);
        map.albedo.extend(block.albedo);
        map.residual.extend(block.residual);
        map.lit.extend(block.lit);
        counts.add(&block.counts);
    }

    let report = report(&map, &counts, k, &dirs, gain_report, options, dark_level);
    Ok((map, report))
}

/// Pixels per parallel block.
const BLOCK: usize = 16 * 1024;

#[derive(Default)]
struct Counts {
    determined: usize,
    dark: usize,
    too_few_lit: usize,
    degenerate: usize,
    facing_away: usize,
    non_finite: usize,
    dropped: Vec<usize>,
    by_lit: Vec<usize>,
}

impl Counts {
    fn add(&mut self, other: &Counts) {
        self.determined += other.determined;
        self.dark += other.dark;
        self.too_few_lit += other.too_few_lit;
        self.degenerate += other.degenerate;
        self.facing_away += other.facing_away;
        self.non_finite += other.non_finite;
        self.dropped
            .iter_mut()
            .zip(&other.dropped)
            .for_each(|(a, b)| *a += b);
        self.by_lit
            .iter_mut()
            .zip(&other.by_lit)
            .for_each(|(a, b)| *a += b);
    }
}

/// The results for a range of pixels.
struct Block {
    normals: Vec<[f32; 3]>,
    albedo: Vec<f32>,
    residual: Vec<f32>,
    lit: Vec<u8>,
    counts: Counts,
}

/// What every pixel's fit shares.
struct PixelFitter<'a> {
    images: &'a [&'a [f32]],
    dirs: &'a [[f64; 3]],
    inv_gain: &'a [f64],
    shadow_threshold: f64,
    dark_level: f64,
}

/// The fit of one pixel.
struct PixelFit {
    normal: [f64; 3],
    albedo: f64,
    residual: f64,
}

impl PixelFitter<'_> {
    fn fit(&self, pixels: std::ops::Range<usize>) -> Block {
        let k = self.images.len();
        let len = pixels.len();
        let mut block = Block {
            normals: vec![[0.0; 3]; len],
            albedo: vec![f32::NAN; len],
            residual: vec![f32::NAN; len],
            lit: vec![0; len],
            counts: Counts {
                dropped: vec![0; k],
                by_lit: vec![0; k + 1],
                ..Counts::default()
            },
        };
        let mut solvers: HashMap<u64, Option<[[f64; 3]; 3]>> = HashMap::new();
        let mut last: Option<(u64, Option<[[f64; 3]; 3]>)> = None;
        let mut value = vec![0f64; k];
        let counts = &mut block.counts;
        for (i, p) in pixels.enumerate() {
            for (c, v) in value.iter_mut().enumerate() {
                *v = self.images[c][p] as f64 * self.inv_gain[c];
            }
            if value.iter().any(|v| !v.is_finite()) {
                counts.non_finite += 1;
            }
            let top = value
                .iter()
                .copied()
                .filter(|v| v.is_finite())
                .fold(f64::NEG_INFINITY, f64::max);
            if !(top.is_finite() && top > self.dark_level) {
                counts.dark += 1;
                continue;
            }
            let mut mask = 0u64;
            for (c, &v) in value.iter().enumerate() {
                if v > self.shadow_threshold * top {
                    mask |= 1 << c;
                } else if v.is_finite() {
                    counts.dropped[c] += 1;
                }
            }
            let used = mask.count_ones() as usize;
            block.lit[i] = used as u8;
            counts.by_lit[used] += 1;
            if used < 3 {
                counts.too_few_lit += 1;
                continue;
            }
            // Neighbouring pixels mostly share their lit set.
            let inverse = match last {
                Some((m, inverse)) if m == mask => inverse,
                _ => {
                    let inverse = *solvers
                        .entry(mask)
                        .or_insert_with(|| lit_inverse(self.dirs, mask));
                    last = Some((mask, inverse));
                    inverse
                }
            };
            let Some(inverse) = inverse else {
                counts.degenerate += 1;
                continue;
            };
            let Some((fit, clamped)) = self.solve(&value, mask, &inverse) else {
                counts.degenerate += 1;
                continue;
            };
            counts.facing_away += usize::from(clamped);
            counts.determined += 1;
            block.normals[i] = fit.normal.map(|v| v as f32);
            block.albedo[i] = fit.albedo as f32;
            block.residual[i] = fit.residual as f32;
        }
        block
    }

    /// Least squares over the lit set `mask` (`inverse` = `(L_S^T L_S)^-1`); whether the normal
    /// was clamped to z = 0. None when the fit gives no direction.
    fn solve(&self, value: &[f64], mask: u64, inverse: &[[f64; 3]; 3]) -> Option<(PixelFit, bool)> {
        let lit = || (0..value.len()).filter(move |c| mask >> c & 1 == 1);
        // b = (L_S^T L_S)^-1 L_S^T I_S
        let mut rhs = [0f64; 3];
        for c in lit() {
            for (r, l) in rhs.iter_mut().zip(&self.dirs[c]) {
                *r += l * value[c];
            }
        }
        let b = mat_vec(inverse, &rhs);
        let mut albedo = norm(&b);
        if !is_positive(albedo) {
            return None;
        }
        let mut n = b.map(|v| v / albedo);
        let clamped = n[2] < 0.0;
        if clamped {
            // A visible surface cannot face away from the projector: project onto z = 0 and refit
            // the albedo along it.
            let h = n[0].hypot(n[1]);
            if h == 0.0 {
                return None;
            }
            n = [n[0] / h, n[1] / h, 0.0];
            let (mut num, mut den) = (0.0, 0.0);
            for c in lit() {
                let s = dot(&n, &self.dirs[c]);
                num += s * value[c];
                den += s * s;
            }
            albedo = if den > 0.0 { num / den } else { 0.0 };
            if !is_positive(albedo) {
                return None;
            }
        }
        let (mut misfit, mut energy) = (0.0, 0.0);
        for (v, l) in value.iter().zip(self.dirs).filter(|(v, _)| v.is_finite()) {
            let predicted = albedo * dot(&n, l).max(0.0);
            misfit += (v - predicted).powi(2);
            energy += v * v;
        }
        Some((
            PixelFit {
                normal: n,
                albedo,
                residual: (misfit / energy).sqrt(),
            },
            clamped,
        ))
    }
}

fn validate(
    images: &[&[f32]],
    directions: &[[f64; 3]],
    width: u32,
    height: u32,
    options: &PhotometricOptions,
) -> Result<Vec<[f64; 3]>, PhotometricError> {
    let k = images.len();
    if k < 3 {
        return Err(PhotometricError::TooFewChannels { channels: k });
    }
    if k > MAX_CHANNELS {
        return Err(PhotometricError::TooManyChannels { channels: k });
    }
    let pixels = (width as usize)
        .checked_mul(height as usize)
        .filter(|&p| p > 0 && p <= isize::MAX as usize / 16);
    let Some(pixels) = pixels else {
        return Err(PhotometricError::BadSize { width, height });
    };
    for (channel, image) in images.iter().enumerate() {
        if image.len() != pixels {
            return Err(PhotometricError::SizeMismatch {
                channel,
                expected: pixels,
                got: image.len(),
            });
        }
    }
    if directions.len() != k {
        return Err(PhotometricError::DirectionCount {
            expected: k,
            got: directions.len(),
        });
    }
    let mut dirs = Vec::with_capacity(k);
    for (channel, d) in directions.iter().enumerate() {
        let n = norm(d);
        if !n.is_finite() || (n - 1.0).abs() > UNIT_TOLERANCE {
            return Err(PhotometricError::NonUnitDirection { channel, norm: n });
        }
        dirs.push([d[0] / n, d[1] / n, d[2] / n]);
    }
    let condition = direction_condition(&dirs, u64::MAX);
    if condition.is_nan() || condition < MIN_DIRECTION_CONDITION {
        return Err(PhotometricError::CoplanarDirections { condition });
    }
    for (field, v) in [
        ("shadow_threshold", options.shadow_threshold),
        ("dark_threshold", options.dark_threshold),
    ] {
        if !(v.is_finite() && (0.0..1.0).contains(&v)) {
            return Err(PhotometricError::BadOption {
                field,
                message: format!("must be in [0, 1), got {v}"),
            });
        }
    }
    match &options.gains {
        Gains::Given(g) if g.len() != k => {
            return Err(PhotometricError::BadGains(format!(
                "{} gains for {k} channels (one per channel)",
                g.len()
            )));
        }
        Gains::Given(g) => {
            if let Some((c, v)) = g
                .iter()
                .enumerate()
                .find(|(_, v)| !(v.is_finite() && **v > 0.0))
            {
                return Err(PhotometricError::BadGains(format!(
                    "gain of channel {c} must be finite and > 0, got {v}"
                )));
            }
        }
        Gains::Estimate if k < 4 => {
            return Err(PhotometricError::GainsUndetermined(format!(
                "with {k} detectors any gains fit the data (the normals are then only known up to a linear map); \
                 give the gains or use at least 4 detectors"
            )));
        }
        _ => {}
    }
    Ok(dirs)
}

/// `sigma_min / sigma_max` of the rows of `dirs` selected by `mask`.
fn direction_condition(dirs: &[[f64; 3]], mask: u64) -> f64 {
    let (values, _) = symmetric_eigen(gram(dirs, mask).concat(), 3);
    if values[2] > 0.0 {
        (values[0].max(0.0) / values[2]).sqrt()
    } else {
        0.0
    }
}

/// `L_S^T L_S` for the channels in `mask`.
fn gram(dirs: &[[f64; 3]], mask: u64) -> [[f64; 3]; 3] {
    let mut a = [[0f64; 3]; 3];
    for (_, d) in dirs.iter().enumerate().filter(|(c, _)| mask >> c & 1 == 1) {
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] += d[i] * d[j];
            }
        }
    }
    a
}

/// `(L_S^T L_S)^-1` for the lit set `mask`, or None when those directions are degenerate.
fn lit_inverse(dirs: &[[f64; 3]], mask: u64) -> Option<[[f64; 3]; 3]> {
    let (values, vectors) = symmetric_eigen(gram(dirs, mask).concat(), 3);
    if !(values[2] > 0.0 && (values[0] / values[2]).sqrt() >= MIN_DIRECTION_CONDITION) {
        return None;
    }
    let mut inverse = [[0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            inverse[i][j] = (0..3)
                .map(|e| vectors[i * 3 + e] * vectors[j * 3 + e] / values[e])
                .sum();
        }
    }
    Some(inverse)
}

/// The gains to divide by, and what the report says about them.
fn resolve_gains(
    images: &[&[f32]],
    dirs: &[[f64; 3]],
    options: &PhotometricOptions,
) -> Result<(Vec<f64>, Value), PhotometricError> {
    let k = images.len();
    match &options.gains {
        Gains::Equal => Ok((
            vec![1.0; k],
            json!({"mode": "equal", "values": vec![1.0; k]}),
        )),
        Gains::Given(g) => Ok((g.clone(), json!({"mode": "given", "values": g}))),
        Gains::Estimate => {
            let e = estimate_gains(images, dirs, options.shadow_threshold)
                .map_err(PhotometricError::GainsUndetermined)?;
            Ok((e.gains.clone(), e.report("estimated")))
        }
        Gains::Auto if k < 4 => Ok((
            vec![1.0; k],
            json!({"mode": "equal", "values": vec![1.0; k],
                   "reason": format!("assumed equal: with {k} detectors the gains cannot be estimated \
                                      (any gains fit; the normals are then known only up to a linear map)")}),
        )),
        Gains::Auto => match estimate_gains(images, dirs, options.shadow_threshold) {
            Ok(e) => Ok((e.gains.clone(), e.report("estimated"))),
            Err(why) => Ok((
                vec![1.0; k],
                json!({"mode": "equal", "values": vec![1.0; k],
                       "reason": format!("assumed equal: the gains cannot be estimated: {why}")}),
            )),
        },
    }
}

struct GainEstimate {
    gains: Vec<f64>,
    pixels_used: usize,
    /// Smallest over second-smallest eigenvalue: small when the data fix the gains.
    eigen_ratio: f64,
    /// Second-smallest eigenvalue over the trace: how strongly other gains are ruled out.
    separation: f64,
}

impl GainEstimate {
    fn report(&self, mode: &str) -> Value {
        json!({
            "mode": mode,
            "values": self.gains,
            "normalised": "mean gain 1 (the common factor is absorbed in the albedo)",
            "pixels_used": self.pixels_used,
            "eigen_ratio": self.eigen_ratio,
            "separation": self.separation,
            "assumes": "Lambertian at the pixels lit by every detector, gains uniform over the scene",
        })
    }
}

/// Smallest over second-smallest eigenvalue above which the gains count as undetermined.
const MAX_GAIN_EIGEN_RATIO: f64 = 0.1;
/// Second-smallest eigenvalue over the trace below which the gains count as undetermined.
const MIN_GAIN_SEPARATION: f64 = 1e-4;

/// Gains from the Lambertian constraint at pixels lit by every detector (see the module docs).
fn estimate_gains(
    images: &[&[f32]],
    dirs: &[[f64; 3]],
    shadow_threshold: f64,
) -> Result<GainEstimate, String> {
    let k = images.len();
    let pixels = images[0].len();
    // P = I - L (L^T L)^-1 L^T: the projector onto the null space of L^T.
    let inverse = lit_inverse(dirs, u64::MAX).ok_or("degenerate directions")?;
    let mut projector = vec![0f64; k * k];
    for a in 0..k {
        for b in 0..k {
            let lal = mat_vec(&inverse, &dirs[b]);
            projector[a * k + b] = f64::from(u8::from(a == b)) - dot(&dirs[a], &lal);
        }
    }
    let all_lit: Vec<usize> = (0..pixels)
        .into_par_iter()
        .filter(|&p| {
            let top = (0..k)
                .map(|c| images[c][p] as f64)
                .fold(f64::NEG_INFINITY, f64::max);
            top > 0.0
                && (0..k).all(|c| {
                    images[c][p].is_finite() && images[c][p] as f64 > shadow_threshold * top
                })
        })
        .collect();
    // Scale the images so the sums stay well inside f64 range whatever their units.
    let scale = all_lit
        .par_iter()
        .map(|&p| {
            (0..k)
                .map(|c| images[c][p].abs() as f64)
                .fold(0.0, f64::max)
        })
        .reduce(|| 0.0, f64::max);
    if all_lit.len() < 4 * k || !is_positive(scale) {
        return Err(format!(
            "only {} pixels are lit by all {k} detectors (need {})",
            all_lit.len(),
            4 * k
        ));
    }
    let fit = |use_pixel: &(dyn Fn(usize) -> bool + Sync)| -> (Vec<f64>, [f64; 3]) {
        // M = P o sum_x I(x) I(x)^T; the gains' reciprocals are its null vector.
        let mut m = all_lit
            .par_iter()
            .enumerate()
            .filter(|&(i, _)| use_pixel(i))
            .fold(
                || vec![0f64; k * k],
                |mut m, (_, &p)| {
                    let mut v = [0f64; MAX_CHANNELS];
                    for (c, v) in v[..k].iter_mut().enumerate() {
                        *v = images[c][p] as f64 / scale;
                    }
                    for a in 0..k {
                        for b in 0..k {
                            m[a * k + b] += v[a] * v[b];
                        }
                    }
                    m
                },
            )
            .reduce(
                || vec![0f64; k * k],
                |mut a, b| {
                    a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                    a
                },
            );
        for (e, pr) in m.iter_mut().zip(&projector) {
            *e *= pr;
        }
        let trace: f64 = (0..k).map(|a| m[a * k + a]).sum();
        let (values, vectors) = symmetric_eigen(m, k);
        let h: Vec<f64> = (0..k).map(|c| vectors[c * k]).collect();
        (h, [values[0], values[1], trace])
    };
    let (h, _) = fit(&|_| true);
    // Refit without the worst-fitting 10 % of pixels (specular highlights, cast shadows above the
    // threshold): the misfit of pixel x is ||P (h o I(x))|| / ||h o I(x)||.
    let misfit: Vec<f64> = all_lit
        .par_iter()
        .map(|&p| {
            let mut w = [0f64; MAX_CHANNELS];
            for (c, w) in w[..k].iter_mut().enumerate() {
                *w = h[c] * images[c][p] as f64;
            }
            let w = &w[..k];
            let pw: f64 = (0..k)
                .map(|a| {
                    (0..k)
                        .map(|b| projector[a * k + b] * w[b])
                        .sum::<f64>()
                        .powi(2)
                })
                .sum();
            (pw / w.iter().map(|x| x * x).sum::<f64>()).sqrt()
        })
        .collect();
    let cut = percentile(misfit.clone(), 0.9);
    let kept = misfit.iter().filter(|&&e| e <= cut).count();
    let (mut h, figures) = fit(&|i| misfit[i] <= cut);
    let (eigen_ratio, separation) = (figures[0].max(0.0) / figures[1], figures[1] / figures[2]);
    if !(separation >= MIN_GAIN_SEPARATION && eigen_ratio <= MAX_GAIN_EIGEN_RATIO) {
        return Err(format!(
            "the scene does not fix them (eigenvalue ratio {eigen_ratio:.2e}, separation {separation:.2e}): \
             the pixels lit by every detector need normals varying in 3-D, e.g. not a flat scene"
        ));
    }
    if h.iter().sum::<f64>() < 0.0 {
        h.iter_mut().for_each(|x| *x = -*x);
    }
    if !h.iter().all(|&x| is_positive(x)) {
        return Err(format!(
            "the fit gives a non-positive gain ({h:?} as 1/gain): the scene is not Lambertian enough or the directions are wrong"
        ));
    }
    let mut gains: Vec<f64> = h.iter().map(|x| 1.0 / x).collect();
    let mean = gains.iter().sum::<f64>() / k as f64;
    gains.iter_mut().for_each(|g| *g /= mean);
    Ok(GainEstimate {
        gains,
        pixels_used: kept,
        eigen_ratio,
        separation,
    })
}

fn report(
    map: &NormalMap,
    counts: &Counts,
    k: usize,
    dirs: &[[f64; 3]],
    gains: Value,
    options: &PhotometricOptions,
    dark_level: f64,
) -> Value {
    let residuals: Vec<f64> = map
        .residual
        .iter()
        .filter(|r| r.is_finite())
        .map(|&r| r as f64)
        .collect();
    let n = residuals.len();
    let residual = if n == 0 {
        Value::Null
    } else {
        json!({
            "mean": residuals.iter().sum::<f64>() / n as f64,
            "median": percentile(residuals.clone(), 0.5),
            "p95": percentile(residuals.clone(), 0.95),
            "fraction_above_0.1": residuals.iter().filter(|&&r| r > 0.1).count() as f64 / n as f64,
        })
    };
    json!({
        "model": "lambertian: I_c = g_c * albedo * max(0, n . l_c)",
        "channels": k,
        "pixels": map.normals.len(),
        "determined": counts.determined,
        "undetermined": {
            "dark": counts.dark,
            "fewer_than_3_lit": counts.too_few_lit,
            "degenerate_lit_directions": counts.degenerate,
        },
        "pixels_by_lit_channels": counts.by_lit,
        "shadowed_pixels_per_channel": counts.dropped,
        "normals_clamped_to_z_0": counts.facing_away,
        "pixels_with_non_finite_values": counts.non_finite,
        "gains": gains,
        "directions": dirs,
        "direction_condition": direction_condition(dirs, u64::MAX),
        "options": {
            "shadow_threshold": options.shadow_threshold,
            "dark_threshold": options.dark_threshold,
            "dark_level": if dark_level.is_finite() { json!(dark_level) } else { Value::Null },
        },
        "residual": residual,
        "residual_definition": "||I' - albedo max(0, L n)|| / ||I'|| over all of the pixel's channels, I' the gain-corrected values; \
                                pixels fitted with exactly 3 channels are checked only by their dropped ones",
        "lambertian_fails_where": [
            "specular highlights: one channel brighter than the cosine law allows tilts the normal toward that detector",
            "interreflections in concave regions: bounced light adds to every channel and flattens the shape",
            "detectors near the scene: the direction (and distance fall-off) varies over the scene, one direction per detector is only right far away",
            "cast shadows: dropped when three channels remain, but a partial shadow above the threshold biases the normal",
            "non-uniform gains (detector field of view, projector fall-off) act as a per-channel albedo and bias the normals",
        ],
    })
}

/// The `q`-quantile (nearest rank) of `values`; NaN when empty.
fn percentile(mut values: Vec<f64>, q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let at = ((values.len() - 1) as f64 * q).round() as usize;
    *values.select_nth_unstable_by(at, |a, b| a.total_cmp(b)).1
}

/// `x > 0` (false for NaN).
fn is_positive(x: f64) -> bool {
    x > 0.0
}

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: &[f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn mat_vec(m: &[[f64; 3]; 3], v: &[f64; 3]) -> [f64; 3] {
    [dot(&m[0], v), dot(&m[1], v), dot(&m[2], v)]
}

/// Eigen-decomposition of a symmetric `n x n` matrix (row-major) by cyclic Jacobi rotations:
/// eigenvalues ascending, eigenvectors as the columns of a row-major `n x n` matrix.
fn symmetric_eigen(mut a: Vec<f64>, n: usize) -> (Vec<f64>, Vec<f64>) {
    debug_assert_eq!(a.len(), n * n);
    let mut v = vec![0f64; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    let total: f64 = a.iter().map(|x| x * x).sum();
    for _sweep in 0..64 {
        let off: f64 = (0..n)
            .flat_map(|p| (0..n).filter(move |&q| q != p).map(move |q| (p, q)))
            .map(|(p, q)| a[p * n + q].powi(2))
            .sum();
        if off <= 1e-30 * total || off == 0.0 {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                // Numerical Recipes' rotation zeroing a[p][q].
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = if theta.abs() > 1e150 {
                    0.5 / theta
                } else {
                    theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt())
                };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for r in 0..n {
                    let (x, y) = (a[r * n + p], a[r * n + q]);
                    a[r * n + p] = c * x - s * y;
                    a[r * n + q] = s * x + c * y;
                }
                for r in 0..n {
                    let (x, y) = (a[p * n + r], a[q * n + r]);
                    a[p * n + r] = c * x - s * y;
                    a[q * n + r] = s * x + c * y;
                }
                for r in 0..n {
                    let (x, y) = (v[r * n + p], v[r * n + q]);
                    v[r * n + p] = c * x - s * y;
                    v[r * n + q] = s * x + c * y;
                }
            }
        }
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| a[i * n + i].total_cmp(&a[j * n + j]));
    let values = order.iter().map(|&i| a[i * n + i]).collect();
    let mut vectors = vec![0f64; n * n];
    for (col, &i) in order.iter().enumerate() {
        for r in 0..n {
            vectors[r * n + col] = v[r * n + i];
        }
    }
    (values, vectors)
}

#[cfg(test)]
mod tests;
