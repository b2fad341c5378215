//! gRPC server reflection: a client without the .proto files lists the server's services and
//! reads their schema from the server, over v1 and over v1alpha (the only version Python's
//! grpcio-reflection speaks), with no token: the schema is public, the service's calls are not.

use helmholtz_tests::ServerProcess;
use prost::Message;
use prost_types::FileDescriptorProto;
use tonic_reflection::pb::{v1, v1alpha};

/// The methods of `service` in `files` (decoded FileDescriptorProtos), by name.
fn methods(files: &[Vec<u8>], service: &str) -> Vec<String> {
    let (package, name) = service.rsplit_once('.').unwrap();
    files
        .iter()
        .map(|f| FileDescriptorProto::decode(f.as_slice()).unwrap())
        .filter(|f| f.package() == package)
        .flat_map(|f| f.service)
        .filter(|s| s.name() == name)
        .flat_map(|s| s.method)
        .map(|m| m.name().to_string())
        .collect()
}

#[tokio::test]
async fn reflection_lists_the_services_and_serves_their_schema_without_a_token() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let channel = tonic::transport::Endpoint::from_shared(server.address.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();

    // v1
    let mut client = v1::server_reflection_client::ServerReflectionClient::new(channel.clone());
    let ask =
        |request: v1::server_reflection_request::MessageRequest| v1::ServerReflectionRequest {
            host: String::new(),
            message_request: Some(request),
        };
    let requests = vec![
        ask(v1::server_reflection_request::MessageRequest::ListServices(
            String::new(),
        )),
        ask(
            v1::server_reflection_request::MessageRequest::FileContainingSymbol(
                "helmholtz.v1.Acquisition".into(),
            ),
        ),
        ask(
            v1::server_reflection_request::MessageRequest::FileContainingSymbol(
                "helmholtz.v1.NoSuchService".into(),
            ),
        ),
    ];
    let mut answers = client
        .server_reflection_info(tokio_stream::iter(requests))
        .await
        .unwrap()
        .into_inner();
    use v1::server_reflection_response::MessageResponse as R;
    let mut services = Vec::new();
    match answers.message().await.unwrap().unwrap().message_response {
        Some(R::ListServicesResponse(list)) => {
            services.extend(list.service.into_iter().map(|s| s.name));
        }
        other => panic!("ListServices answered {other:?}"),
    }
    for want in [
        "helmholtz.v1.Acquisition",
        "grpc.health.v1.Health",
        "grpc.reflection.v1.ServerReflection",
    ] {
        assert!(
            services.iter().any(|s| s == want),
            "{want} not in {services:?}"
        );
    }
    let files = match answers.message().await.unwrap().unwrap().message_response {
        Some(R::FileDescriptorResponse(f)) => f.file_descriptor_proto,
        other => panic!("FileContainingSymbol answered {other:?}"),
    };
    let found = methods(&files, "helmholtz.v1.Acquisition");
    for want in [
        "CreateSession",
        "UploadMeasurements",
        "GetUploadStatus",
        "FinishSession",
        "RequestReconstruction",
        "GetReconstruction",
        "CancelReconstruction",
    ] {
        assert!(found.iter().any(|m| m == want), "{want} not in {found:?}");
    }
    // An unknown symbol ends the stream NOT_FOUND.
    let unknown = answers.message().await.unwrap_err();
    assert_eq!(unknown.code(), tonic::Code::NotFound, "{unknown:?}");

    // v1alpha
    let mut client =
        v1alpha::server_reflection_client::ServerReflectionClient::new(channel.clone());
    let request = v1alpha::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(
            v1alpha::server_reflection_request::MessageRequest::FileContainingSymbol(
                "helmholtz.v1.Acquisition".into(),
            ),
        ),
    };
    let mut answers = client
        .server_reflection_info(tokio_stream::iter(vec![request]))
        .await
        .unwrap()
        .into_inner();
    match answers.message().await.unwrap().unwrap().message_response {
        Some(v1alpha::server_reflection_response::MessageResponse::FileDescriptorResponse(f)) => {
            let found = methods(&f.file_descriptor_proto, "helmholtz.v1.Acquisition");
            assert!(found.iter().any(|m| m == "UploadMeasurements"), "{found:?}");
        }
        other => panic!("v1alpha answered {other:?}"),
    }

    // The schema is open; the service is not.
    let mut acquisition = helmholtz_proto::v1::acquisition_client::AcquisitionClient::new(channel);
    let refused = acquisition
        .get_upload_status(helmholtz_proto::v1::SessionRef {
            session_id: "x".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{refused:?}");
}
