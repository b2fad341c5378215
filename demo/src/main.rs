//! `helmholtz-demo`: the service (the same as `helmholtz-server serve`, same options) plus
//! simulated rigs that use the real edge client library over loopback, so one command shows the
//! whole path working. The service binary itself does not link the client.

mod rig;

use clap::Parser;
use helmholtz_server::cli::ServeArgs;

#[global_allocator]
static ALLOC: helmholtz_alloc::CountingAlloc = helmholtz_alloc::CountingAlloc;

#[derive(Parser, Debug)]
#[command(
    name = "helmholtz-demo",
    version,
    about = "Runs the Helmholtz service with simulated rigs: uploads demo sessions (lab \"demo\"), reconstructs them, prints the URLs of the sessions, dual images and a relightable transport matrix, then keeps serving until Ctrl-C.\n\nRe-running it is idempotent (same session ids and specs: nothing is uploaded twice; new reconstructions are queued)."
)]
struct Cli {
    #[command(flatten)]
    serve: ServeArgs,
    /// Exit once the demo sessions are reconstructed instead of serving on.
    #[arg(long)]
    exit_after_demo: bool,
    /// Log format on stderr.
    #[arg(long, default_value = "text", value_parser = ["text", "json"])]
    log_format: String,
}

fn main() {
    helmholtz_alloc::retain_freed_memory();
    let cli = Cli::parse();
    helmholtz_server::cli::init_tracing(&cli.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    if let Err(e) = runtime.block_on(rig::run(cli.serve.config(), cli.exit_after_demo)) {
        eprintln!("helmholtz-demo: {e:#}");
        std::process::exit(1);
    }
}
