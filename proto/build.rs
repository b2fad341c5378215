//! Compiles the .proto files with protox (pure Rust): no system protoc is needed.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    let files = ["proto/helmholtz/v1/acquisition.proto"];
    let fds = protox::compile(files, ["proto"])?;
    // The messages always; the tonic service stubs only with feature `grpc`.
    let grpc = std::env::var_os("CARGO_FEATURE_GRPC").is_some();
    tonic_prost_build::configure()
        .build_server(grpc)
        .build_client(grpc)
        .compile_fds(fds)?;
    Ok(())
}
