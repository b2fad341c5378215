//! One typed reconstruction request: the method and its parameters, parsed and validated once at
//! the API edge ([`Request::parse`]), stored by name and canonical parameters, and dispatched
//! once by the worker (bucket rows -> [`crate::reconstruct`], camera frames ->
//! [`crate::transport::reconstruct_transport`]).

use serde_json::Value;

use crate::transport::TransportConfig;
use crate::{MethodConfig, ParamError};

/// What to reconstruct and how.
#[derive(Clone, Debug, PartialEq)]
pub enum Request {
    /// Dual images of a bucket session (one per channel) by one of the bucket methods.
    Bucket(MethodConfig),
    /// The transport matrix T of a camera session (`method = "transport"`).
    Transport(TransportConfig),
}

impl Request {
    /// Every method a request may name: the bucket methods, then `transport`.
    pub fn method_names() -> impl Iterator<Item = &'static str> {
        crate::method::METHODS.into_iter().chain(["transport"])
    }

    /// The method named `method` with `params` (a JSON object, or null for the defaults); errors
    /// name the offending field.
    pub fn parse(method: &str, params: &Value) -> Result<Request, ParamError> {
        if method == "transport" {
            TransportConfig::parse(params).map(Request::Transport)
        } else {
            MethodConfig::parse(method, params).map(Request::Bucket)
        }
    }

    /// The method's name as the API and the store know it.
    pub fn name(&self) -> &'static str {
        match self {
            Request::Bucket(c) => c.name(),
            Request::Transport(_) => "transport",
        }
    }

    /// The canonical parameters (defaults filled in): [`Request::parse`] of `name()` and these
    /// gives the same request back.
    pub fn params_json(&self) -> Value {
        match self {
            Request::Bucket(c) => c.params_json(),
            Request::Transport(c) => c.params_json(),
        }
    }

    /// True for a request that reconstructs a camera session.
    pub fn is_transport(&self) -> bool {
        matches!(self, Request::Transport(_))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn parse_round_trips_through_name_and_canonical_params() {
        for (method, params) in [
            ("dgi", json!({})),
            ("tv", json!({"lambda": 0.01})),
            ("auto", Value::Null),
            ("transport", json!({})),
            ("levels", json!({"level": 2})),
        ] {
            let r = Request::parse(method, &params).unwrap();
            assert_eq!(r.name(), method);
            assert_eq!(r.is_transport(), method == "transport");
            let again = Request::parse(r.name(), &r.params_json()).unwrap();
            assert_eq!(again, r, "{method}");
        }
    }

    /// The list the API shows is the list the parser knows: every name parses (with the one
    /// parameter `levels` requires), and the parser's own error lists the bucket methods.
    #[test]
    fn every_listed_method_parses() {
        let names: Vec<&str> = Request::method_names().collect();
        assert_eq!(names.last(), Some(&"transport"));
        for method in &names {
            let params = if *method == "levels" {
                json!({"level": 1})
            } else {
                json!({})
            };
            let r = Request::parse(method, &params).unwrap_or_else(|e| panic!("{method}: {e:?}"));
            assert_eq!(r.name(), *method);
        }
        let unknown = Request::parse("nope", &json!({})).unwrap_err();
        for method in &names[..names.len() - 1] {
            assert!(unknown.message.contains(method), "{}", unknown.message);
        }
    }

    #[test]
    fn errors_name_the_field() {
        let e = Request::parse("tv", &json!({"lambda": -1})).unwrap_err();
        assert_eq!(e.field, "params.lambda");
        let e = Request::parse("nope", &json!({})).unwrap_err();
        assert_eq!(e.field, "method");
        let e = Request::parse("transport", &json!({"bogus": 1})).unwrap_err();
        assert_eq!(e.field, "params.bogus");
    }
}
