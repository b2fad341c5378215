//! Compiles the .proto files with protox (pure Rust): no system protoc is needed.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    let files = ["proto/helmholtz/v1/acquisition.proto"];
    let fds = protox::compile(files, ["proto"])?;
    // The encoded descriptors, for gRPC server reflection (`v1::FILE_DESCRIPTOR_SET`).
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out.join("helmholtz_descriptor.bin"),
        prost::Message::encode_to_vec(&fds),
    )?;
    // The messages always; the tonic service stubs only with feature `grpc`.
    let grpc = std::env::var_os("CARGO_FEATURE_GRPC").is_some();
    tonic_prost_build::configure()
        .build_server(grpc)
        .build_client(grpc)
        .compile_fds(fds)?;
    Ok(())
}
