//! Access tokens on the client side.
//!
//! Every network function takes the server as `server: &str`; a token travels inside it as the
//! URL's user part, `http://hz_...@127.0.0.1:8080` (the CLI builds that from `--token` /
//! `HELMHOLTZ_TOKEN` with [`with_token`]). Requests go to the address without it and carry the
//! token as `Authorization: Bearer` (REST) or `authorization` metadata (gRPC). Error messages
//! show the address only, never the token.

use helmholtz_proto::v1::acquisition_client::AcquisitionClient;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

/// A gRPC client that sends the token on every call.
pub type Grpc = AcquisitionClient<InterceptedService<Channel, Bearer>>;

/// Splits `scheme://[token@]host[:port][/path]` into the address without the user part and
/// the token (the user part's password if it has one, else its user name).
pub fn split_server(server: &str) -> (String, Option<String>) {
    let Some((scheme, rest)) = server.split_once("://") else {
        return (server.to_string(), None);
    };
    let authority_end = rest.find('/').unwrap_or(rest.len());
    let (authority, path) = rest.split_at(authority_end);
    let Some((userinfo, host)) = authority.rsplit_once('@') else {
        return (server.to_string(), None);
    };
    let token = match userinfo.split_once(':') {
        Some((_, password)) if !password.is_empty() => password,
        Some((user, _)) => user,
        None => userinfo,
    };
    let token = (!token.is_empty()).then(|| token.to_string());
    (format!("{scheme}://{host}{path}"), token)
}

/// `server` with `token` as its user part (replacing any token already there).
pub fn with_token(server: &str, token: &str) -> String {
    let (address, _) = split_server(server);
    match address.split_once("://") {
        Some((scheme, rest)) if !token.is_empty() => format!("{scheme}://{token}@{rest}"),
        _ => address,
    }
}

/// Adds `authorization: Bearer <token>` to every gRPC request (nothing without a token).
#[derive(Clone, Debug, Default)]
pub struct Bearer(Option<MetadataValue<Ascii>>);

impl Bearer {
    pub fn new(token: Option<&str>) -> anyhow::Result<Bearer> {
        match token {
            None => Ok(Bearer(None)),
            Some(t) => Ok(Bearer(Some(format!("Bearer {t}").parse().map_err(
                |_| anyhow::anyhow!("the token holds characters that cannot be sent in a header"),
            )?))),
        }
    }
}

impl Interceptor for Bearer {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            request.metadata_mut().insert("authorization", v.clone());
        }
        Ok(request)
    }
}

/// The server's request id on a gRPC status, for error messages.
pub fn request_id(status: &tonic::Status) -> Option<String> {
    status
        .metadata()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .map(str::to_string)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_travel_in_the_user_part() {
        assert_eq!(
            split_server("http://127.0.0.1:8080"),
            ("http://127.0.0.1:8080".into(), None)
        );
        assert_eq!(
            split_server("http://hz_abc@127.0.0.1:8080"),
            ("http://127.0.0.1:8080".into(), Some("hz_abc".into()))
        );
        assert_eq!(
            split_server("http://x:hz_abc@h:1/p@q"),
            ("http://h:1/p@q".into(), Some("hz_abc".into()))
        );
        assert_eq!(
            split_server("http://hz_abc:@h"),
            ("http://h".into(), Some("hz_abc".into()))
        );
        assert_eq!(
            with_token("http://old@h:1/", "hz_new"),
            "http://hz_new@h:1/"
        );
        assert_eq!(with_token("http://h:1", ""), "http://h:1");
        assert_eq!(
            split_server(&with_token("http://h:1", "hz_t")).1.as_deref(),
            Some("hz_t")
        );
    }
}
