//! Method names and parameters: parsed and validated once, before a job is queued.

use helmholtz_proto::Family;
use serde_json::{Value, json};

use super::transforms::TransformKind;
use super::{Problem, ReconError};

/// A validated method with its parameters.
#[derive(Clone, Debug, PartialEq)]
pub enum MethodConfig {
    /// `G(x) = <c p(x)> - <c><p(x)>` (Bernoulli(q): E[G] = q(1-q) t).
    Gi,
    /// Differential GI (Ferri et al. 2010): `<c p(x)> - (<c>/<R>) <R p(x)>`, R_i = sum of pattern i.
    Dgi,
    /// Normalised GI (Sun et al. 2012): `<(c_i/R_i - <c>/<R>) p(x)>`.
    Ngi,
    /// Exact inverse of a complete raster or Hadamard (split-pair) set.
    Direct,
    /// Hadamard split pairs, any subset: the zero-filled inverse `H^T d` (unmeasured
    /// coefficients set to zero; the minimum-norm least-squares image).
    ZeroFilled,
    /// Hadamard `russian_doll` ordering: the exact block-averaged image at a complete 4^j level
    /// (`level` = j; default the finest complete level the rows reach).
    Levels { level: Option<u32> },
    /// Compressed sensing: `min 1/2 ||A t - c||^2 + lambda ||Psi t||_1`, `t >= 0`, Psi an orthonormal
    /// transform; `lambda` is a fraction of lambda_max (scale-free).
    Cs {
        transform: TransformKind,
        lambda: f64,
        max_iter: usize,
        fit: Fit,
    },
    /// `min 1/2 ||A t - c||^2 + lambda TV(t)`, `t >= 0`; `lambda` a fraction of lambda_max.
    Tv {
        lambda: f64,
        max_iter: usize,
        fit: Fit,
    },
    /// Least squares / Tikhonov `min ||A t - c||^2 + mu ||t||^2` by CGLS (unconstrained).
    Lsq { mu: f64, max_iter: usize, fit: Fit },
    /// The data choose the model: each candidate regulariser along a warm-started lambda path,
    /// fitted without the held-out rows and scored on them; the winner (and the resolution the
    /// rows support) is refitted on all rows.
    Auto {
        models: Vec<Model>,
        max_iter: usize,
        fit: Fit,
        /// The detector's read noise as the user declares it: the standard deviation of one
        /// frame's value in bucket units (e.g. the spread of dark frames), constant for every
        /// frame. Where given, it replaces the noise the session's own data would give
        /// (`details.noise_declared` reports both); a single-frame session has no estimate of
        /// its own and needs it on a noisy rig.
        read_noise: Option<ReadNoise>,
        /// Folds of all the rows on which the race's weight is checked where random-pattern
        /// rows show noise ([`crate::auto::cross_validate`]); 0 skips the check, and the Stein
        /// risk check of Hadamard pairs ([`crate::auto::sure_check`]) too (faster, the race's
        /// single held-out set alone chooses).
        folds: usize,
    },
}

/// A read noise the request declares (`auto`'s `read_noise`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReadNoise {
    /// Standard deviation of one frame's value, bucket units.
    pub sigma: f64,
    /// The split pairs `auto` runs on were decoded from single frames (set by
    /// [`crate::reconstruct`], not by the request): each pair's noise then follows
    /// [`crate::adaptive::single_frame_pair_variances`] instead of two frames'.
    pub single_frames: bool,
}

/// A regulariser `auto` can choose.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Model {
    /// Isotropic total variation.
    Tv,
    /// l1 of the coefficients in an orthonormal transform.
    L1(TransformKind),
}

impl Model {
    pub fn name(self) -> &'static str {
        match self {
            Model::Tv => "tv",
            Model::L1(kind) => kind.name(),
        }
    }
    /// What the model's "kept" count counts.
    pub fn kept_meaning(self) -> &'static str {
        match self {
            Model::Tv => "pixels with a nonzero gradient (edges kept)",
            Model::L1(TransformKind::Identity) => "nonzero pixels",
            Model::L1(TransformKind::Dct) => "nonzero DCT coefficients",
            Model::L1(_) => "nonzero wavelet coefficients",
        }
    }
    pub const DEFAULT: [Model; 3] = [
        Model::Tv,
        Model::L1(TransformKind::Db4),
        Model::L1(TransformKind::Dct),
    ];
}

/// The data term and the hold-out shared by the iterative methods.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fit {
    /// Fraction of the rows held out for the error estimate (and `auto`'s choice); `None`:
    /// [`super::holdout::default_fraction`] of the row count.
    pub holdout: Option<f64>,
    pub noise: Noise,
    /// An unknown constant added to every bucket (detector dark level, ambient light):
    /// `None` = the family's default ([`Fit::fits_offset`]).
    pub offset: Option<bool>,
}

impl Default for Fit {
    fn default() -> Self {
        Fit {
            holdout: None,
            noise: Noise::Gaussian,
            offset: None,
        }
    }
}

impl Fit {
    /// Whether the buckets are modelled as `A t + d` with an unknown `d` (fitted, reported):
    /// only on request (`"offset": "fit"`) and only for families whose pattern sums vary
    /// (Bernoulli, speckle): never for raster (every row has the same pattern sum, so `d` and
    /// the image mean cannot be told apart), never for Hadamard (split pairs cancel `d`), never
    /// under the Poisson data term (counts are absolute). Not the default: with few rows the
    /// image mean is then pinned only by the spread of the pattern sums (about `sqrt(k)/2`
    /// against their mean `k/2`), which costs accuracy when there is no offset (measured: 41
    /// rows of a 64x64 scene, the fit's raw residual rises from 6e-4 to 0.6).
    pub fn fits_offset(&self, family: &Family) -> bool {
        matches!(family, Family::Bernoulli { .. } | Family::Speckle { .. })
            && self.offset.unwrap_or(false)
    }
}

/// The noise the data term is built for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Noise {
    /// Least squares: Gaussian noise of equal variance.
    Gaussian,
    /// Photon counting: the Poisson likelihood by iteratively reweighted least squares, weights
    /// `1 / predicted bucket` from the model; `photon` is the bucket value of one photon.
    Poisson { photon: f64 },
}

/// A request that names an unknown method or bad parameters; `field` is the JSON path.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct ParamError {
    pub field: String,
    pub message: String,
}

pub const METHODS: [&str; 10] = [
    "gi",
    "dgi",
    "ngi",
    "direct",
    "zero_filled",
    "levels",
    "cs",
    "tv",
    "lsq",
    "auto",
];

/// Reads optional parameters from a JSON object, refusing unknown keys and naming bad ones.
struct Params<'a> {
    method: &'a str,
    map: serde_json::Map<String, Value>,
}

impl Params<'_> {
    fn number(
        &mut self,
        key: &str,
        default: f64,
        valid: impl Fn(f64) -> bool,
        rule: &str,
    ) -> Result<f64, ParamError> {
        match self.map.remove(key) {
            None | Some(Value::Null) => Ok(default),
            Some(Value::Number(n)) => {
                let v = n.as_f64().unwrap_or(f64::NAN);
                if v.is_finite() && valid(v) {
                    Ok(v)
                } else {
                    Err(bad(key, format!("must be {rule}, got {v}")))
                }
            }
            Some(other) => Err(bad(key, format!("must be a number ({rule}), got {other}"))),
        }
    }

    fn iterations(&mut self, default: usize) -> Result<usize, ParamError> {
        let v = self.number(
            "max_iter",
            default as f64,
            |v| v.fract() == 0.0 && (1.0..=100_000.0).contains(&v),
            "an integer in 1..=100000",
        )?;
        Ok(v as usize)
    }

    fn transform(&mut self, default: TransformKind) -> Result<TransformKind, ParamError> {
        match self.map.remove("transform") {
            None | Some(Value::Null) => Ok(default),
            Some(Value::String(name)) => TransformKind::ALL
                .into_iter()
                .find(|k| k.name() == name)
                .ok_or_else(|| {
                    bad(
                        "transform",
                        format!("unknown transform {name:?}; known: {}", transform_names()),
                    )
                }),
            Some(other) => Err(bad("transform", format!("must be a string, got {other}"))),
        }
    }

    fn fit(&mut self) -> Result<Fit, ParamError> {
        let holdout = match self.map.get("holdout") {
            None | Some(Value::Null) => {
                self.map.remove("holdout");
                None
            }
            Some(_) => Some(self.number(
                "holdout",
                0.0,
                |v| (0.02..=0.5).contains(&v),
                "a fraction in [0.02, 0.5]",
            )?),
        };
        let noise = match self.map.remove("noise") {
            None | Some(Value::Null) => "gaussian".to_string(),
            Some(Value::String(s)) => s,
            Some(other) => {
                return Err(bad(
                    "noise",
                    format!("must be \"gaussian\" or \"poisson\", got {other}"),
                ));
            }
        };
        let noise = match noise.as_str() {
            "gaussian" => {
                if self.map.contains_key("photon") {
                    return Err(bad(
                        "photon",
                        "applies only with \"noise\": \"poisson\"".into(),
                    ));
                }
                Noise::Gaussian
            }
            "poisson" => Noise::Poisson {
                photon: self.number(
                    "photon",
                    1.0,
                    |v| v > 0.0,
                    "the bucket value of one photon, > 0",
                )?,
            },
            other => {
                return Err(bad(
                    "noise",
                    format!("unknown noise {other:?}; known: gaussian, poisson"),
                ));
            }
        };
        let offset = match self.map.remove("offset") {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) if s == "fit" => Some(true),
            Some(Value::String(s)) if s == "none" => Some(false),
            Some(other) => {
                return Err(bad(
                    "offset",
                    format!(
                        "must be \"fit\" (an unknown dark level added to every bucket) or \"none\", got {other}"
                    ),
                ));
            }
        };
        Ok(Fit {
            holdout,
            noise,
            offset,
        })
    }

    fn models(&mut self) -> Result<Vec<Model>, ParamError> {
        let known = || {
            std::iter::once("tv")
                .chain(TransformKind::ALL.iter().map(|k| k.name()))
                .collect::<Vec<_>>()
                .join(", ")
        };
        match self.map.remove("models") {
            None | Some(Value::Null) => Ok(Model::DEFAULT.to_vec()),
            Some(Value::Array(items)) if !items.is_empty() => {
                let mut out = Vec::new();
                for (i, item) in items.iter().enumerate() {
                    let name = item.as_str().ok_or_else(|| {
                        bad(
                            &format!("models[{i}]"),
                            format!("must be a string, got {item}"),
                        )
                    })?;
                    let model = if name == "tv" {
                        Model::Tv
                    } else {
                        Model::L1(
                            TransformKind::ALL
                                .into_iter()
                                .find(|k| k.name() == name)
                                .ok_or_else(|| {
                                    bad(
                                        &format!("models[{i}]"),
                                        format!("unknown model {name:?}; known: {}", known()),
                                    )
                                })?,
                        )
                    };
                    if out.contains(&model) {
                        return Err(bad(
                            &format!("models[{i}]"),
                            format!("{name:?} is listed twice"),
                        ));
                    }
                    out.push(model);
                }
                Ok(out)
            }
            Some(other) => Err(bad(
                "models",
                format!(
                    "must be a non-empty array of model names ({}), got {other}",
                    known()
                ),
            )),
        }
    }

    fn finish(self) -> Result<(), ParamError> {
        match self.map.keys().next() {
            Some(key) => Err(bad(
                key,
                format!("method {} takes no parameter {key:?}", self.method),
            )),
            None => Ok(()),
        }
    }
}

fn bad(key: &str, message: String) -> ParamError {
    ParamError {
        field: format!("params.{key}"),
        message,
    }
}

fn transform_names() -> String {
    TransformKind::ALL
        .iter()
        .map(|k| k.name())
        .collect::<Vec<_>>()
        .join(", ")
}

impl MethodConfig {
    /// Parses `{"method": name, "params": params}`. `params` must be an object (or null).
    pub fn parse(name: &str, params: &Value) -> Result<Self, ParamError> {
        let map = match params {
            Value::Null => serde_json::Map::new(),
            Value::Object(map) => map.clone(),
            _ => {
                return Err(ParamError {
                    field: "params".into(),
                    message: "must be a JSON object".into(),
                });
            }
        };
        let mut p = Params { method: name, map };
        let config = match name {
            "gi" => MethodConfig::Gi,
            "dgi" => MethodConfig::Dgi,
            "ngi" => MethodConfig::Ngi,
            "direct" => MethodConfig::Direct,
            "zero_filled" => MethodConfig::ZeroFilled,
            "levels" => MethodConfig::Levels {
                level: match p.map.contains_key("level") {
                    false => None,
                    true => Some(p.number(
                        "level",
                        0.0,
                        |v| v.fract() == 0.0 && (0.0..=12.0).contains(&v),
                        "an integer level j in 0..=12 (2^j x 2^j blocks)",
                    )? as u32),
                },
            },
            "cs" => MethodConfig::Cs {
                transform: p.transform(TransformKind::Db4)?,
                lambda: p.number(
                    "lambda",
                    3e-4,
                    |v| v > 0.0 && v <= 1.0,
                    "a fraction of lambda_max in (0, 1]",
                )?,
                max_iter: p.iterations(300)?,
                fit: p.fit()?,
            },
            "tv" => MethodConfig::Tv {
                lambda: p.number(
                    "lambda",
                    1e-3,
                    |v| v > 0.0 && v <= 1.0,
                    "a fraction of lambda_max in (0, 1]",
                )?,
                max_iter: p.iterations(200)?,
                fit: p.fit()?,
            },
            "lsq" => MethodConfig::Lsq {
                mu: p.number("mu", 0.0, |v| v >= 0.0, ">= 0")?,
                max_iter: p.iterations(200)?,
                fit: p.fit()?,
            },
            "auto" => {
                let models = p.models()?;
                let max_iter = p.iterations(300)?;
                let read_noise = match p.map.get("read_noise") {
                    None | Some(Value::Null) => {
                        p.map.remove("read_noise");
                        None
                    }
                    Some(_) => Some(ReadNoise {
                        sigma: p.number(
                            "read_noise",
                            0.0,
                            |v| v >= 0.0,
                            "the standard deviation of one frame's noise in bucket units, >= 0",
                        )?,
                        single_frames: false,
                    }),
                };
                let fit = p.fit()?;
                if read_noise.is_some() && fit.noise != Noise::Gaussian {
                    return Err(bad(
                        "read_noise",
                        "applies only with \"noise\": \"gaussian\" (a constant noise per frame)"
                            .into(),
                    ));
                }
                let folds = p.number(
                    "folds",
                    crate::auto::FOLDS as f64,
                    |v| v == 0.0 || (v.fract() == 0.0 && (2.0..=20.0).contains(&v)),
                    "0 (no check) or an integer in 2..=20",
                )? as usize;
                MethodConfig::Auto {
                    models,
                    max_iter,
                    fit,
                    read_noise,
                    folds,
                }
            }
            other => {
                return Err(ParamError {
                    field: "method".into(),
                    message: format!("unknown method {other:?}; known: {}", METHODS.join(", ")),
                });
            }
        };
        p.finish()?;
        Ok(config)
    }

    pub fn name(&self) -> &'static str {
        match self {
            MethodConfig::Gi => "gi",
            MethodConfig::Dgi => "dgi",
            MethodConfig::Ngi => "ngi",
            MethodConfig::Direct => "direct",
            MethodConfig::ZeroFilled => "zero_filled",
            MethodConfig::Levels { .. } => "levels",
            MethodConfig::Cs { .. } => "cs",
            MethodConfig::Tv { .. } => "tv",
            MethodConfig::Lsq { .. } => "lsq",
            MethodConfig::Auto { .. } => "auto",
        }
    }

    /// The parameters in canonical form (defaults filled in), as stored and reported.
    pub fn params_json(&self) -> Value {
        let mut v = match self {
            MethodConfig::Cs {
                transform,
                lambda,
                max_iter,
                ..
            } => {
                json!({"transform": transform.name(), "lambda": lambda, "max_iter": max_iter})
            }
            MethodConfig::Tv {
                lambda, max_iter, ..
            } => json!({"lambda": lambda, "max_iter": max_iter}),
            MethodConfig::Lsq { mu, max_iter, .. } => json!({"mu": mu, "max_iter": max_iter}),
            MethodConfig::Auto {
                models,
                max_iter,
                read_noise,
                folds,
                ..
            } => {
                let mut v = json!({"models": models.iter().map(|m| m.name()).collect::<Vec<_>>(), "max_iter": max_iter, "folds": folds});
                if let Some(r) = read_noise {
                    v["read_noise"] = json!(r.sigma);
                }
                v
            }
            MethodConfig::Levels { level: Some(level) } => json!({ "level": level }),
            _ => Value::Object(Default::default()),
        };
        if let Some(fit) = self.fit() {
            if let Some(f) = fit.holdout {
                v["holdout"] = json!(f);
            }
            if let Some(o) = fit.offset {
                v["offset"] = json!(if o { "fit" } else { "none" });
            }
            match fit.noise {
                Noise::Gaussian => v["noise"] = json!("gaussian"),
                Noise::Poisson { photon } => {
                    v["noise"] = json!("poisson");
                    v["photon"] = json!(photon);
                }
            }
        }
        v
    }

    /// The data term and hold-out of an iterative method.
    pub fn fit(&self) -> Option<Fit> {
        match self {
            MethodConfig::Cs { fit, .. }
            | MethodConfig::Tv { fit, .. }
            | MethodConfig::Lsq { fit, .. }
            | MethodConfig::Auto { fit, .. } => Some(*fit),
            _ => None,
        }
    }

    /// Whether this method can run on `problem` at all; the error says why not.
    /// An upper bound on the heap a reconstruction of `problem` with this method takes, in bytes:
    /// image-sized vectors (per channel) times a per-method count, plus the pattern operator where
    /// it is stored (Bernoulli bits and their tables, speckle values), plus the buckets.
    ///
    /// The counts are the upper envelope of the peaks the counting allocator measured over the
    /// full benchmark grid (`docs/benchmarks.json`: 2,682 reconstructions, 32x32 to 256x256, 1 %
    /// to 400 % rows; e.g. Bernoulli `auto` at most 48 vectors + 4.7 kn/8 bytes, Hadamard `auto`
    /// 56 vectors), with a quarter more as margin; `tests/tests/e2e/memory.rs` checks the bound
    /// against the peaks the real server reports.
    pub fn memory_estimate(&self, problem: &Problem) -> u64 {
        const MIB: f64 = (1u64 << 20) as f64;
        let n = problem.spec.pixels() as f64;
        let k = problem.rows as f64;
        let ch = problem.channels.max(1) as f64;
        let vector = 8.0 * n;
        // (vectors per channel, whether the solver builds the pattern operator)
        let (vectors, operator) = match self {
            MethodConfig::Gi | MethodConfig::Dgi | MethodConfig::Ngi => (10.0, false),
            MethodConfig::Direct | MethodConfig::ZeroFilled | MethodConfig::Levels { .. } => {
                (4.0, false)
            }
            MethodConfig::Lsq { .. } | MethodConfig::Cs { .. } | MethodConfig::Tv { .. } => {
                (40.0, true)
            }
            MethodConfig::Auto { .. } => (60.0, true),
        };
        let operator_bytes = if !operator {
            0.0
        } else {
            match problem.spec.family() {
                // Packed bits, their transpose and the product kernels' tables.
                Family::Bernoulli { .. } => 5.0 * k * n / 8.0,
                // One f32 per pattern cell, and a cell index per pixel.
                Family::Speckle { grain } => {
                    let g = (*grain).max(1) as f64;
                    2.0 * (k * (n / (g * g)).ceil() * 4.0 + n * 4.0)
                }
                // Fast transforms and index lists: no stored matrix.
                Family::Hadamard { .. }
                | Family::Raster { .. }
                | Family::AdaptiveHadamard { .. }
                | Family::AdaptiveHaar { .. } => 16.0 * k,
            }
        };
        let buckets = 16.0 * k * ch;
        let bytes = 1.25 * (vectors * vector * ch + operator_bytes + buckets) + 4.0 * MIB;
        bytes.min(u64::MAX as f64) as u64
    }

    pub fn check(&self, problem: &Problem) -> Result<(), ReconError> {
        if problem.rows == 0 {
            return Err(ReconError::Unsolvable(
                "the session has no committed rows yet".into(),
            ));
        }
        if problem.rows > problem.spec.count() {
            return Err(ReconError::Unsolvable(format!(
                "{} rows requested but the spec declares {}",
                problem.rows,
                problem.spec.count()
            )));
        }
        // Split-pair families: y+ - y- per pair.
        let hadamard = matches!(
            problem.spec.family(),
            Family::Hadamard { .. } | Family::AdaptiveHadamard { .. } | Family::AdaptiveHaar { .. }
        );
        if problem.spec.is_adaptive() {
            let Some(indices) = problem.spec.adaptive_indices() else {
                return Err(ReconError::Unsolvable(format!(
                    "this {} session's spec is not resolved: its reconstruction needs the pattern \
                     indices the session showed (its issued batches)",
                    problem.spec.family().name()
                )));
            };
            if problem.rows > 2 * indices.len() as u64 {
                return Err(ReconError::Unsolvable(format!(
                    "{} rows requested but the session issued {} split pairs ({} frames)",
                    problem.rows,
                    indices.len(),
                    2 * indices.len()
                )));
            }
        }
        if let Some(Fit {
            noise: Noise::Poisson { .. },
            ..
        }) = self.fit()
        {
            if hadamard {
                return Err(ReconError::Unsolvable(
                    "noise \"poisson\" does not apply to Hadamard split pairs: the difference y+ - y- of two \
                     Poisson counts has variance y+ + y- (the whole scene's light, the same for every pair), so \
                     the least-squares data term is already the photon-weighted one"
                        .into(),
                ));
            }
            if matches!(self, MethodConfig::Lsq { .. }) {
                return Err(ReconError::Unsolvable(
                    "noise \"poisson\" needs a non-negative model (cs, tv or auto); lsq is unconstrained".into(),
                ));
            }
        }
        if let Some(Fit {
            offset: Some(true),
            noise,
            ..
        }) = self.fit()
        {
            match problem.spec.family() {
                Family::Raster { .. } => {
                    return Err(ReconError::Unsolvable(
                        "offset \"fit\" does not apply to raster patterns: every row lights the same number of pixels, \
                         so a constant dark level cannot be told apart from the image mean"
                            .into(),
                    ));
                }
                Family::Hadamard { .. }
                | Family::AdaptiveHadamard { .. }
                | Family::AdaptiveHaar { .. } => {
                    return Err(ReconError::Unsolvable(
                        "offset \"fit\" does not apply to split pairs: y+ - y- cancels a constant dark level exactly".into(),
                    ));
                }
                _ => {}
            }
            if matches!(noise, Noise::Poisson { .. }) {
                return Err(ReconError::Unsolvable(
                    "offset \"fit\" and noise \"poisson\" do not combine: photon counts are absolute; subtract a known dark level from the buckets first".into(),
                ));
            }
        }
        if matches!(self, MethodConfig::ZeroFilled | MethodConfig::Levels { .. }) && !hadamard {
            return Err(ReconError::Unsolvable(format!(
                "{} inverts Hadamard or adaptive split pairs; this session's patterns are {}",
                self.name(),
                problem.spec.family().name()
            )));
        }
        if let MethodConfig::Levels { .. } = self
            && !matches!(
                problem.spec.family(),
                Family::Hadamard {
                    ordering: helmholtz_proto::HadamardOrdering::RussianDoll
                }
            )
        {
            return Err(ReconError::Unsolvable(
                "levels needs the russian_doll ordering (complete 4^j levels of block-constant Walsh functions); \
                 use zero_filled for other orderings"
                    .into(),
            ));
        }
        if let MethodConfig::Direct = self {
            let k = problem.spec.pixels() as u64;
            match problem.spec.family() {
                Family::Raster { .. } => {
                    let (_, bx, by) = problem.spec.raster_grid().expect("raster");
                    let blocks = bx as u64 * by as u64;
                    if problem.rows < blocks {
                        return Err(ReconError::Unsolvable(format!(
                            "direct needs a complete raster scan: {blocks} rows, have {}",
                            problem.rows
                        )));
                    }
                }
                Family::Hadamard { .. } => {
                    if problem.rows < 2 * k {
                        return Err(ReconError::Unsolvable(format!(
                            "direct needs the complete Hadamard set: {} frames (P+ and P- of all {k} rows), have {}",
                            2 * k,
                            problem.rows
                        )));
                    }
                }
                // The adaptive scheme's own image: the zero-filled inverse of the coefficients it
                // chose (exact when the budget covered them all).
                Family::AdaptiveHadamard { .. } | Family::AdaptiveHaar { .. } => {}
                other => {
                    return Err(ReconError::Unsolvable(format!(
                        "direct inverts complete raster or hadamard sets; this session's patterns are {}",
                        other.name()
                    )));
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn parse_names_the_bad_field() {
        assert_eq!(
            MethodConfig::parse("dgi", &json!({})).unwrap(),
            MethodConfig::Dgi
        );
        assert_eq!(
            MethodConfig::parse("gi", &Value::Null).unwrap(),
            MethodConfig::Gi
        );
        assert_eq!(
            MethodConfig::parse("magic", &json!({})).unwrap_err().field,
            "method"
        );
        assert_eq!(
            MethodConfig::parse("gi", &json!({"lambda": 1}))
                .unwrap_err()
                .field,
            "params.lambda"
        );
        assert_eq!(
            MethodConfig::parse("gi", &json!([1])).unwrap_err().field,
            "params"
        );
        let cs = MethodConfig::parse("cs", &json!({"transform": "haar", "lambda": 0.01})).unwrap();
        assert_eq!(
            cs,
            MethodConfig::Cs {
                transform: TransformKind::Haar,
                lambda: 0.01,
                max_iter: 300,
                fit: Fit::default()
            }
        );
        assert_eq!(
            MethodConfig::parse(cs.name(), &cs.params_json()).unwrap(),
            cs,
            "canonical params round-trip"
        );
        assert_eq!(
            MethodConfig::parse("cs", &json!({"transform": "fourier"}))
                .unwrap_err()
                .field,
            "params.transform"
        );
        assert_eq!(
            MethodConfig::parse("tv", &json!({"lambda": -1}))
                .unwrap_err()
                .field,
            "params.lambda"
        );
        assert_eq!(
            MethodConfig::parse("tv", &json!({"max_iter": 2.5}))
                .unwrap_err()
                .field,
            "params.max_iter"
        );
        assert_eq!(
            MethodConfig::parse("lsq", &json!({"mu": "big"}))
                .unwrap_err()
                .field,
            "params.mu"
        );
        assert_eq!(
            MethodConfig::parse("tv", &json!({"holdout": 0.9}))
                .unwrap_err()
                .field,
            "params.holdout"
        );
        assert_eq!(
            MethodConfig::parse("tv", &json!({"noise": "cauchy"}))
                .unwrap_err()
                .field,
            "params.noise"
        );
        assert_eq!(
            MethodConfig::parse("tv", &json!({"photon": 2}))
                .unwrap_err()
                .field,
            "params.photon"
        );
        assert_eq!(
            MethodConfig::parse("cs", &json!({"noise": "poisson", "photon": 0}))
                .unwrap_err()
                .field,
            "params.photon"
        );
        assert_eq!(
            MethodConfig::parse("auto", &json!({"models": ["tv", "wavelet"]}))
                .unwrap_err()
                .field,
            "params.models[1]"
        );
        assert_eq!(
            MethodConfig::parse("auto", &json!({"models": ["tv", "tv"]}))
                .unwrap_err()
                .field,
            "params.models[1]"
        );
        assert_eq!(
            MethodConfig::parse("auto", &json!({"models": []}))
                .unwrap_err()
                .field,
            "params.models"
        );
        assert_eq!(
            MethodConfig::parse("levels", &json!({"level": 1.5}))
                .unwrap_err()
                .field,
            "params.level"
        );
        assert_eq!(
            MethodConfig::parse("tv", &json!({"offset": "maybe"}))
                .unwrap_err()
                .field,
            "params.offset"
        );
        let tv = MethodConfig::parse("tv", &json!({"offset": "none"})).unwrap();
        assert_eq!(MethodConfig::parse("tv", &tv.params_json()).unwrap(), tv);
        let auto = MethodConfig::parse(
            "auto",
            &json!({"models": ["haar", "tv"], "noise": "poisson", "photon": 3.5}),
        )
        .unwrap();
        assert_eq!(
            auto,
            MethodConfig::Auto {
                models: vec![Model::L1(TransformKind::Haar), Model::Tv],
                max_iter: 300,
                fit: Fit {
                    holdout: None,
                    noise: Noise::Poisson { photon: 3.5 },
                    offset: None
                },
                read_noise: None,
                folds: crate::auto::FOLDS,
            }
        );
        let declared = MethodConfig::parse("auto", &json!({"read_noise": 0.25})).unwrap();
        assert!(matches!(
            declared,
            MethodConfig::Auto {
                read_noise: Some(ReadNoise {
                    sigma: 0.25,
                    single_frames: false
                }),
                ..
            }
        ));
        for (params, field) in [
            (json!({"read_noise": -1.0}), "params.read_noise"),
            (json!({"read_noise": "low"}), "params.read_noise"),
            (
                json!({"read_noise": 1.0, "noise": "poisson"}),
                "params.read_noise",
            ),
            (json!({"folds": 1}), "params.folds"),
            (json!({"folds": 2.5}), "params.folds"),
            (json!({"folds": 21}), "params.folds"),
            (json!({"folds": "five"}), "params.folds"),
        ] {
            assert_eq!(
                MethodConfig::parse("auto", &params).unwrap_err().field,
                field,
                "{params}"
            );
        }
        assert_eq!(
            MethodConfig::parse("tv", &json!({"read_noise": 1.0}))
                .unwrap_err()
                .field,
            "params.read_noise",
            "only auto reads a declared noise"
        );
        let unchecked = MethodConfig::parse("auto", &json!({"folds": 0})).unwrap();
        assert!(matches!(unchecked, MethodConfig::Auto { folds: 0, .. }));
        assert!(matches!(
            MethodConfig::parse("auto", &json!({"folds": 10})).unwrap(),
            MethodConfig::Auto { folds: 10, .. }
        ));
        for m in [
            auto,
            declared,
            unchecked,
            MethodConfig::Levels { level: Some(3) },
            MethodConfig::parse("lsq", &json!({"holdout": 0.2})).unwrap(),
        ] {
            assert_eq!(
                MethodConfig::parse(m.name(), &m.params_json()).unwrap(),
                m,
                "canonical params round-trip"
            );
        }
    }
}
