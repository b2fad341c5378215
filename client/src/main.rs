//! `helmholtz`: the Helmholtz edge client. See `helmholtz --help` and the library docs.
fn main() -> std::process::ExitCode {
    helmholtz_client::cli::main()
}
