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
    /// Compressed sensing: `min 1/2 ||A t - c||^2 + lambda ||Psi t||_1`, `t >= 0`, Psi an orthonormal
    /// transform; `lambda` is a fraction of lambda_max (scale-free).
    Cs { transform: TransformKind, lambda: f64, max_iter: usize },
    /// `min 1/2 ||A t - c||^2 + lambda TV(t)`, `t >= 0`; `lambda` a fraction of lambda_max.
    Tv { lambda: f64, max_iter: usize },
    /// Least squares / Tikhonov `min ||A t - c||^2 + mu ||t||^2` by CGLS (unconstrained).
    Lsq { mu: f64, max_iter: usize },
}

/// A request that names an unknown method or bad parameters; `field` is the JSON path.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct ParamError {
    pub field: String,
    pub message: String,
}

pub const METHODS: [&str; 7] = ["gi", "dgi", "ngi", "direct", "cs", "tv", "lsq"];

/// Reads optional parameters from a JSON object, refusing unknown keys and naming bad ones.
struct Params<'a> {
    method: &'a str,
    map: serde_json::Map<String, Value>,
}

impl Params<'_> {
    fn number(&mut self, key: &str, default: f64, valid: impl Fn(f64) -> bool, rule: &str) -> Result<f64, ParamError> {
        match self.map.remove(key) {
            None | Some(Value::Null) => Ok(default),
            Some(Value::Number(n)) => {
                let v = n.as_f64().unwrap_or(f64::NAN);
                if v.is_finite() && valid(v) { Ok(v) } else { Err(bad(key, format!("must be {rule}, got {v}"))) }
            }
            Some(other) => Err(bad(key, format!("must be a number ({rule}), got {other}"))),
        }
    }

    fn iterations(&mut self, default: usize) -> Result<usize, ParamError> {
        let v = self.number("max_iter", default as f64, |v| v.fract() == 0.0 && (1.0..=100_000.0).contains(&v), "an integer in 1..=100000")?;
        Ok(v as usize)
    }

    fn transform(&mut self, default: TransformKind) -> Result<TransformKind, ParamError> {
        match self.map.remove("transform") {
            None | Some(Value::Null) => Ok(default),
            Some(Value::String(name)) => TransformKind::ALL
                .into_iter()
                .find(|k| k.name() == name)
                .ok_or_else(|| bad("transform", format!("unknown transform {name:?}; known: {}", transform_names()))),
            Some(other) => Err(bad("transform", format!("must be a string, got {other}"))),
        }
    }

    fn finish(self) -> Result<(), ParamError> {
        match self.map.keys().next() {
            Some(key) => Err(bad(key, format!("method {} takes no parameter {key:?}", self.method))),
            None => Ok(()),
        }
    }
}

fn bad(key: &str, message: String) -> ParamError {
    ParamError { field: format!("params.{key}"), message }
}

fn transform_names() -> String {
    TransformKind::ALL.iter().map(|k| k.name()).collect::<Vec<_>>().join(", ")
}

impl MethodConfig {
    /// Parses `{"method": name, "params": params}`. `params` must be an object (or null).
    pub fn parse(name: &str, params: &Value) -> Result<Self, ParamError> {
        let map = match params {
            Value::Null => serde_json::Map::new(),
            Value::Object(map) => map.clone(),
            _ => return Err(ParamError { field: "params".into(), message: "must be a JSON object".into() }),
        };
        let mut p = Params { method: name, map };
        let config = match name {
            "gi" => MethodConfig::Gi,
            "dgi" => MethodConfig::Dgi,
            "ngi" => MethodConfig::Ngi,
            "direct" => MethodConfig::Direct,
            "cs" => MethodConfig::Cs {
                transform: p.transform(TransformKind::Db4)?,
                lambda: p.number("lambda", 1e-3, |v| v > 0.0 && v <= 1.0, "a fraction of lambda_max in (0, 1]")?,
                max_iter: p.iterations(300)?,
            },
            "tv" => MethodConfig::Tv {
                lambda: p.number("lambda", 3e-3, |v| v > 0.0 && v <= 1.0, "a fraction of lambda_max in (0, 1]")?,
                max_iter: p.iterations(200)?,
            },
            "lsq" => MethodConfig::Lsq {
                mu: p.number("mu", 0.0, |v| v >= 0.0, ">= 0")?,
                max_iter: p.iterations(200)?,
            },
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
            MethodConfig::Cs { .. } => "cs",
            MethodConfig::Tv { .. } => "tv",
            MethodConfig::Lsq { .. } => "lsq",
        }
    }

    /// The parameters in canonical form (defaults filled in), as stored and reported.
    pub fn params_json(&self) -> Value {
        match self {
            MethodConfig::Cs { transform, lambda, max_iter } => {
                json!({"transform": transform.name(), "lambda": lambda, "max_iter": max_iter})
            }
            MethodConfig::Tv { lambda, max_iter } => json!({"lambda": lambda, "max_iter": max_iter}),
            MethodConfig::Lsq { mu, max_iter } => json!({"mu": mu, "max_iter": max_iter}),
            _ => Value::Object(Default::default()),
        }
    }

    /// Whether this method can run on `problem` at all; the error says why not.
    pub fn check(&self, problem: &Problem) -> Result<(), ReconError> {
        if problem.rows == 0 {
            return Err(ReconError::Unsolvable("the session has no committed rows yet".into()));
        }
        if problem.rows > problem.spec.count() {
            return Err(ReconError::Unsolvable(format!(
                "{} rows requested but the spec declares {}",
                problem.rows,
                problem.spec.count()
            )));
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
        assert_eq!(MethodConfig::parse("dgi", &json!({})).unwrap(), MethodConfig::Dgi);
        assert_eq!(MethodConfig::parse("gi", &Value::Null).unwrap(), MethodConfig::Gi);
        assert_eq!(MethodConfig::parse("magic", &json!({})).unwrap_err().field, "method");
        assert_eq!(MethodConfig::parse("gi", &json!({"lambda": 1})).unwrap_err().field, "params.lambda");
        assert_eq!(MethodConfig::parse("gi", &json!([1])).unwrap_err().field, "params");
        let cs = MethodConfig::parse("cs", &json!({"transform": "haar", "lambda": 0.01})).unwrap();
        assert_eq!(cs, MethodConfig::Cs { transform: TransformKind::Haar, lambda: 0.01, max_iter: 300 });
        assert_eq!(MethodConfig::parse(cs.name(), &cs.params_json()).unwrap(), cs, "canonical params round-trip");
        assert_eq!(MethodConfig::parse("cs", &json!({"transform": "fourier"})).unwrap_err().field, "params.transform");
        assert_eq!(MethodConfig::parse("tv", &json!({"lambda": -1})).unwrap_err().field, "params.lambda");
        assert_eq!(MethodConfig::parse("tv", &json!({"max_iter": 2.5})).unwrap_err().field, "params.max_iter");
        assert_eq!(MethodConfig::parse("lsq", &json!({"mu": "big"})).unwrap_err().field, "params.mu");
    }
}
