//! Method names and parameters: parsed and validated once, before a job is queued.

use helmholtz_proto::Family;
use serde_json::Value;

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
}

/// A request that names an unknown method or bad parameters; `field` is the JSON path.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct ParamError {
    pub field: String,
    pub message: String,
}

pub const METHODS: [&str; 4] = ["gi", "dgi", "ngi", "direct"];

impl MethodConfig {
    /// Parses `{"method": name, "params": params}`. `params` must be an object (or null).
    pub fn parse(name: &str, params: &Value) -> Result<Self, ParamError> {
        let config = match name {
            "gi" => MethodConfig::Gi,
            "dgi" => MethodConfig::Dgi,
            "ngi" => MethodConfig::Ngi,
            "direct" => MethodConfig::Direct,
            other => {
                return Err(ParamError {
                    field: "method".into(),
                    message: format!("unknown method {other:?}; known: {}", METHODS.join(", ")),
                });
            }
        };
        match params {
            Value::Null => {}
            Value::Object(map) => {
                // None of these methods takes parameters yet: refuse rather than ignore.
                if let Some(key) = map.keys().next() {
                    return Err(ParamError {
                        field: format!("params.{key}"),
                        message: format!("method {name} takes no parameter {key:?}"),
                    });
                }
            }
            _ => {
                return Err(ParamError {
                    field: "params".into(),
                    message: "must be a JSON object".into(),
                });
            }
        }
        Ok(config)
    }

    pub fn name(&self) -> &'static str {
        match self {
            MethodConfig::Gi => "gi",
            MethodConfig::Dgi => "dgi",
            MethodConfig::Ngi => "ngi",
            MethodConfig::Direct => "direct",
        }
    }

    /// The parameters in canonical form (defaults filled in), as stored and reported.
    pub fn params_json(&self) -> Value {
        Value::Object(Default::default())
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
    }
}
