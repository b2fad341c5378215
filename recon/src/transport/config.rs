//! `POST .../reconstructions {"method": "transport", "params": {...}}`: parsed and validated once.

use helmholtz_proto::{Family, PatternSpec};
use serde_json::{Value, json};

use crate::ParamError;
use crate::transforms::TransformKind;

/// Default working-set budget of one reconstruction when the server sets none: 1 GiB.
pub const DEFAULT_MEMORY_BUDGET: usize = 1 << 30;

/// The transforms tried when the data choose (`transform` absent).
pub const CANDIDATE_TRANSFORMS: [TransformKind; 4] = [
    TransformKind::Identity,
    TransformKind::Haar,
    TransformKind::Db4,
    TransformKind::Dct,
];

/// The weights (fractions of each row's `lambda_max`) tried, largest first, when the data choose.
pub const LAMBDA_PATH: [f64; 7] = [1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4];

/// A validated `transport` request.
#[derive(Clone, Debug, PartialEq)]
pub struct TransportConfig {
    /// Orthonormal transform the rows are sparse in; `None`: the data choose (held-out error on
    /// a sample of camera pixels; for a complete set, the fewest coefficients above the noise).
    pub transform: Option<TransformKind>,
    /// l1 weight as a fraction of each row's `lambda_max`; `None`: the data choose.
    pub lambda: Option<f64>,
    /// Iterations per row at most (FISTA iterations; coordinate-descent sweeps for random
    /// patterns).
    pub max_iter: usize,
    /// Per-row stop: `||s_k - s_{k-1}|| <= tol ||s_k||` on 3 consecutive FISTA iterations, or in
    /// one coordinate-descent sweep followed by a check that no coefficient held at zero
    /// violates the optimality conditions.
    pub tol: f64,
    /// Fraction of rows (Hadamard: split pairs) held out for the error estimate and the choice;
    /// `None`: [`crate::holdout::default_fraction`].
    pub holdout: Option<f64>,
    /// Camera pixels the model is chosen on.
    pub sample_pixels: usize,
    /// Solve the 2x2-binned camera first and warm-start each pixel from its parent.
    pub coarse_to_fine: bool,
    /// Reconstruct `T` on a projector grid coarser by this factor (a power of two dividing
    /// both sides; 1: the session's grid): each coarse projector pixel is a `b x b` block, its
    /// column of `T` the block's summed light. Hadamard sessions only: the pairs whose Walsh
    /// function is constant on the blocks measure the coarse `T` exactly (half of a
    /// Russian-doll set holds the complete set at half the resolution), the others are unused.
    pub projector_binning: u32,
    /// Let the model choice also consider every point compacted (its smallest coefficients
    /// dropped within a third of its held-out residual, refitted; `prune_rows` in the module).
    /// On by default; `false` keeps every coefficient the lasso (or its refit) kept.
    pub compact: bool,
    /// The whole working set of one reconstruction (frame block, solutions, scratch, operator);
    /// set by the server ([`TransportConfig::with_memory_budget`]), not a request parameter.
    pub memory_budget_bytes: usize,
}

impl Default for TransportConfig {
    fn default() -> Self {
        TransportConfig {
            transform: None,
            lambda: None,
            max_iter: 300,
            tol: 1e-4,
            holdout: None,
            sample_pixels: 64,
            coarse_to_fine: false,
            projector_binning: 1,
            compact: true,
            memory_budget_bytes: DEFAULT_MEMORY_BUDGET,
        }
    }
}

fn bad(key: &str, message: String) -> ParamError {
    ParamError {
        field: format!("params.{key}"),
        message,
    }
}

fn number(
    map: &mut serde_json::Map<String, Value>,
    key: &str,
    valid: impl Fn(f64) -> bool,
    rule: &str,
) -> Result<Option<f64>, ParamError> {
    match map.remove(key) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Number(n)) => {
            let v = n.as_f64().unwrap_or(f64::NAN);
            if v.is_finite() && valid(v) {
                Ok(Some(v))
            } else {
                Err(bad(key, format!("must be {rule}, got {v}")))
            }
        }
        Some(other) => Err(bad(key, format!("must be a number ({rule}), got {other}"))),
    }
}

/// A `true`/`false` parameter (`null` or absent: `default`).
fn flag(
    map: &mut serde_json::Map<String, Value>,
    key: &str,
    default: bool,
) -> Result<bool, ParamError> {
    match map.remove(key) {
        None | Some(Value::Null) => Ok(default),
        Some(Value::Bool(b)) => Ok(b),
        Some(other) => Err(bad(key, format!("must be true or false, got {other}"))),
    }
}

impl TransportConfig {
    /// From the `params` object of a `transport` request: unknown keys are refused and every
    /// error names its field (`params.max_iter`).
    pub fn parse(params: &Value) -> Result<TransportConfig, ParamError> {
        let mut map = match params {
            Value::Null => serde_json::Map::new(),
            Value::Object(map) => map.clone(),
            _ => {
                return Err(ParamError {
                    field: "params".into(),
                    message: "must be a JSON object".into(),
                });
            }
        };
        let d = TransportConfig::default();
        let transform = match map.remove("transform") {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) if s == "auto" => None,
            Some(Value::String(name)) => Some(
                TransformKind::ALL
                    .into_iter()
                    .find(|k| k.name() == name)
                    .ok_or_else(|| {
                        bad(
                            "transform",
                            format!(
                                "unknown transform {name:?}; known: auto, {}",
                                TransformKind::ALL.map(|k| k.name()).join(", ")
                            ),
                        )
                    })?,
            ),
            Some(other) => Err(bad("transform", format!("must be a string, got {other}")))?,
        };
        let lambda = number(
            &mut map,
            "lambda",
            |v| v > 0.0 && v < 1.0,
            "a fraction of lambda_max in (0, 1)",
        )?;
        let max_iter = number(
            &mut map,
            "max_iter",
            |v| v.fract() == 0.0 && (1.0..=100_000.0).contains(&v),
            "an integer in 1..=100000",
        )?
        .map_or(d.max_iter, |v| v as usize);
        let tol = number(
            &mut map,
            "tol",
            |v| v > 0.0 && v < 1.0,
            "a relative step in (0, 1)",
        )?
        .unwrap_or(d.tol);
        let holdout = number(
            &mut map,
            "holdout",
            |v| (0.02..=0.5).contains(&v),
            "a fraction in [0.02, 0.5]",
        )?;
        let sample_pixels = number(
            &mut map,
            "sample_pixels",
            |v| v.fract() == 0.0 && (1.0..=65_536.0).contains(&v),
            "an integer in 1..=65536",
        )?
        .map_or(d.sample_pixels, |v| v as usize);
        let coarse_to_fine = flag(&mut map, "coarse_to_fine", d.coarse_to_fine)?;
        let compact = flag(&mut map, "compact", d.compact)?;
        let projector_binning = number(
            &mut map,
            "projector_binning",
            |v| v.fract() == 0.0 && (1.0..=1024.0).contains(&v) && (v as u32).is_power_of_two(),
            "a power of two in 1..=1024",
        )?
        .map_or(d.projector_binning, |v| v as u32);
        if let Some(key) = map.keys().next() {
            return Err(bad(
                key,
                format!(
                    "method transport takes no parameter {key:?}; known: transform, lambda, max_iter, tol, holdout, sample_pixels, coarse_to_fine, projector_binning, compact"
                ),
            ));
        }
        Ok(TransportConfig {
            transform,
            lambda,
            max_iter,
            tol,
            holdout,
            sample_pixels,
            coarse_to_fine,
            projector_binning,
            compact,
            memory_budget_bytes: d.memory_budget_bytes,
        })
    }

    /// The canonical parameters, defaults filled in (`"auto"` where the data choose); parses
    /// back to the same config (the memory budget is the server's, not a parameter).
    pub fn params_json(&self) -> Value {
        json!({
            "transform": self.transform.map_or("auto", |t| t.name()),
            "lambda": self.lambda,
            "max_iter": self.max_iter,
            "tol": self.tol,
            "holdout": self.holdout,
            "sample_pixels": self.sample_pixels,
            "coarse_to_fine": self.coarse_to_fine,
            "projector_binning": self.projector_binning,
            "compact": self.compact,
        })
    }

    /// Checks the request against the session's patterns (`projector_binning`: Hadamard
    /// sessions, a factor dividing both sides), naming the field.
    pub fn check(&self, spec: &PatternSpec) -> Result<(), ParamError> {
        check_binning(spec, self.projector_binning)
    }

    /// The server's per-worker budget for the working set.
    pub fn with_memory_budget(mut self, bytes: usize) -> Self {
        self.memory_budget_bytes = bytes;
        self
    }
}

/// `projector_binning` `b` on `spec`'s patterns: 1 anywhere; otherwise Hadamard patterns (their
/// pairs constant on `b x b` blocks measure the coarse `T`) and `b` dividing both sides.
pub(super) fn check_binning(spec: &PatternSpec, b: u32) -> Result<(), ParamError> {
    if b <= 1 {
        return Ok(());
    }
    if !matches!(
        spec.family(),
        Family::Hadamard { .. } | Family::AdaptiveHadamard { .. }
    ) {
        return Err(bad(
            "projector_binning",
            format!(
                "projector binning is for Hadamard sessions (their block-constant pairs measure the coarse T); this session's patterns are {}",
                spec.family().name()
            ),
        ));
    }
    if !b.is_power_of_two() || !spec.width().is_multiple_of(b) || !spec.height().is_multiple_of(b) {
        return Err(bad(
            "projector_binning",
            format!(
                "{b} does not divide the {}x{} projector grid into whole blocks",
                spec.width(),
                spec.height()
            ),
        ));
    }
    Ok(())
}
