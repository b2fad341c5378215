//! JSON request bodies decoded into the contract's typed requests ([`helmholtz_proto::rest`]),
//! once, with every error naming its field: the path serde was at (`light.radius`,
//! `roles[1]`), or for a missing or unknown field, that field.

use serde::de::DeserializeOwned;

use super::ApiError;

/// Decodes `bytes` as the JSON request `T`; `example` shows a valid body in the error of a body
/// that is not a JSON object at all.
pub fn decode<T: DeserializeOwned>(bytes: &[u8], example: &str) -> Result<T, ApiError> {
    // A derived struct would also take an array of its fields in order: bodies are objects.
    if bytes.iter().find(|b| !b.is_ascii_whitespace()) != Some(&b'{') {
        return Err(ApiError::invalid(
            "body",
            format!("must be a JSON object like {example}"),
        ));
    }
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| problem(e, example))?;
    de.end()
        .map_err(|e| ApiError::invalid("body", format!("not JSON: {}", without_position(&e))))?;
    Ok(value)
}

fn problem(e: serde_path_to_error::Error<serde_json::Error>, example: &str) -> ApiError {
    let path = e.path().to_string();
    let inner = e.into_inner();
    let message = without_position(&inner);
    if inner.is_syntax() || inner.is_eof() || inner.is_io() {
        return ApiError::invalid("body", format!("not JSON: {message}"));
    }
    // serde names a missing or unknown field in its message, at the path of its parent object.
    let named = ["missing field `", "unknown field `", "duplicate field `"]
        .iter()
        .find_map(|prefix| message.strip_prefix(prefix))
        .and_then(|rest| rest.split('`').next());
    let field = match (path.as_str(), named) {
        (".", Some(name)) => name.to_string(),
        (".", None) => {
            return ApiError::invalid(
                "body",
                format!("must be a JSON object like {example}: {message}"),
            );
        }
        (parent, Some(name)) if !parent.ends_with(name) => format!("{parent}.{name}"),
        (parent, _) => parent.to_string(),
    };
    let message = match message.strip_prefix("unknown field ") {
        Some(rest) => format!("unknown field {rest}"),
        None if message.starts_with("missing field ") => "is required".to_string(),
        None if message.starts_with("duplicate field ") => "is given twice".to_string(),
        None => message,
    };
    ApiError::invalid(field, message)
}

/// serde_json's message without its " at line L column C" (the body is one line to most
/// callers; the field says where).
fn without_position(e: &serde_json::Error) -> String {
    let text = e.to_string();
    match text.rfind(" at line ") {
        Some(i) => text[..i].to_string(),
        None => text,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use helmholtz_proto::rest::{
        LightPreset, LightRequest, PrimalRequest, ReconstructionRequest, RelightRequest,
        TokenRequest,
    };

    fn field_of<T: DeserializeOwned + std::fmt::Debug>(body: &str) -> (String, String) {
        match decode::<T>(body.as_bytes(), "{}") {
            Err(ApiError::InvalidArgument { field, message }) => (field, message),
            other => panic!("{body}: expected a field error, got {other:?}"),
        }
    }

    #[test]
    fn valid_bodies_decode_into_the_contract_types() {
        let r: ReconstructionRequest =
            decode(br#"{"method": "tv", "params": {"lambda": 0.1}}"#, "").unwrap();
        assert_eq!(r.method, "tv");
        assert_eq!(r.params["lambda"], 0.1);
        let r: ReconstructionRequest = decode(br#"{"method": "dgi"}"#, "").unwrap();
        assert!(r.params.is_null());
        let l: RelightRequest = decode(
            br#"{"light": {"preset": "disc", "x": 1, "y": 2.5, "radius": 3}}"#,
            "",
        )
        .unwrap();
        assert_eq!(
            l.light,
            LightRequest::Preset(LightPreset::Disc {
                x: 1.0,
                y: 2.5,
                radius: 3.0
            })
        );
        let l: RelightRequest =
            decode(br#"{"light": {"weights": {"r": 1, "g": -0.5}}}"#, "").unwrap();
        assert!(matches!(l.light, LightRequest::Weights { ref weights } if weights["g"] == -0.5));
        let p: PrimalRequest = decode(br#"{"pattern_index": 7}"#, "").unwrap();
        assert_eq!(p.pattern_index, 7);
        let t: TokenRequest = decode(br#"{"roles": ["rig"]}"#, "").unwrap();
        assert_eq!((t.roles, t.note), (vec!["rig".to_string()], String::new()));
    }

    #[test]
    fn errors_name_the_field() {
        let cases: &[(&str, &str, &str)] = &[
            // (body, field, a word of the message)
            (r#"{"method": 3}"#, "method", "invalid type"),
            (r#"{"params": {}}"#, "method", "is required"),
            (r#"{"method": "gi", "extra": 1}"#, "extra", "unknown field"),
            (r#"{"method": "gi", "method": "tv"}"#, "method", "twice"),
            (r#"[1, 2]"#, "body", "JSON object"),
            (r#"{"method": "gi""#, "body", "not JSON"),
            (r#"{"method": "gi"} trailing"#, "body", "not JSON"),
        ];
        for (body, field, word) in cases {
            let (f, m) = field_of::<ReconstructionRequest>(body);
            assert_eq!(&f, field, "{body}: {m}");
            assert!(m.contains(word), "{body}: {m}");
        }
        let cases: &[(&str, &str, &str)] = &[
            (r#"{}"#, "light", "is required"),
            (
                r#"{"light": {"preset": "disc", "x": 2, "y": 2}}"#,
                "light.radius",
                "is required",
            ),
            (
                r#"{"light": {"preset": "disc", "x": "a", "y": 2, "radius": 1}}"#,
                "light.x",
                "invalid type",
            ),
            (
                r#"{"light": {"preset": "full", "x": 2}}"#,
                "light.x",
                "unknown field",
            ),
            (r#"{"light": {"preset": "cone"}}"#, "light.preset", "cone"),
            (
                r#"{"light": {"preset": 3}}"#,
                "light.preset",
                "invalid type",
            ),
            (r#"{"light": {}}"#, "light", "preset or weights"),
            (
                r#"{"light": {"weights": {"a": 1}, "preset": "full"}}"#,
                "light",
                "either",
            ),
            (
                r#"{"light": {"weights": {"a": "x"}}}"#,
                "light.weights.a",
                "invalid type",
            ),
            (
                r#"{"light": {"weights": {"a": 1}, "x": 1}}"#,
                "light.x",
                "unknown field",
            ),
            (r#"{"light": 3}"#, "light", "invalid type"),
            (
                r#"{"light": {"preset": "disc", "x": 1, "x": 2}}"#,
                "light.x",
                "twice",
            ),
        ];
        for (body, field, word) in cases {
            let (f, m) = field_of::<RelightRequest>(body);
            assert_eq!(&f, field, "{body}: {m}");
            assert!(m.contains(word), "{body}: {m}");
        }
        assert_eq!(
            field_of::<PrimalRequest>(r#"{"pattern_index": -1}"#).0,
            "pattern_index"
        );
        assert_eq!(
            field_of::<PrimalRequest>(r#"{"pattern_index": 1.5}"#).0,
            "pattern_index"
        );
        assert_eq!(
            field_of::<TokenRequest>(r#"{"roles": ["rig", 2]}"#).0,
            "roles[1]"
        );
        assert_eq!(field_of::<TokenRequest>(r#"{"roles": "rig"}"#).0, "roles");
        assert_eq!(field_of::<TokenRequest>(r#"{"note": "x"}"#).0, "roles");
    }
}
