//! The `helmholtz-server` command line.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, Subcommand};

use crate::app::{Application, Config};

#[derive(Parser, Debug)]
#[command(name = "helmholtz-server", version, about = "Helmholtz: dual photography and ghost imaging reconstruction service.\n\nServes the gRPC acquisition API (helmholtz.v1.Acquisition) and the REST API on one address, stores sessions in SQLite and reconstructs on a pool of CPU workers.")]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log format on stderr.
    #[arg(long, global = true, default_value = "text", value_parser = ["text", "json"])]
    log_format: String,
}

#[derive(clap::Args, Debug, Clone)]
struct ServeArgs {
    /// Address for gRPC and REST (one port serves both); port 0 picks a free port.
    #[arg(long, env = "HELMHOLTZ_LISTEN", default_value = "127.0.0.1:8080")]
    listen: SocketAddr,
    /// Directory of the SQLite database (created if missing).
    #[arg(long, env = "HELMHOLTZ_DATA_DIR", default_value = "helmholtz-data")]
    data_dir: PathBuf,
    /// Reconstruction worker threads (default: the number of CPU cores).
    #[arg(long, env = "HELMHOLTZ_WORKERS")]
    workers: Option<usize>,
    /// Job lease in seconds: a job whose worker stops heart-beating for this long is taken up again.
    #[arg(long, default_value_t = 30)]
    lease_seconds: u64,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the service until Ctrl-C (or SIGTERM).
    Serve(ServeArgs),
    /// Run the service with a simulated rig: uploads demo sessions, reconstructs them, prints the
    /// URLs of the sessions and dual images, then keeps serving until Ctrl-C.
    Demo {
        #[command(flatten)]
        serve: ServeArgs,
        /// Exit once the demo sessions are reconstructed instead of serving on.
        #[arg(long)]
        exit_after_demo: bool,
    },
}

impl ServeArgs {
    fn config(&self) -> Config {
        let mut config = Config {
            listen: self.listen,
            data_dir: self.data_dir.clone(),
            lease: Duration::from_secs(self.lease_seconds.max(1)),
            ..Config::default()
        };
        if let Some(w) = self.workers {
            config.workers = w.max(1);
        }
        config
    }
}

pub fn main() {
    let cli = Cli::parse();
    init_tracing(&cli.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().expect("tokio runtime");
    let result = runtime.block_on(async move {
        match cli.command {
            Command::Serve(args) => serve(args.config()).await,
            Command::Demo { serve, exit_after_demo } => crate::demo::run(serve.config(), exit_after_demo).await,
        }
    });
    if let Err(e) = result {
        eprintln!("helmholtz-server: {e:#}");
        std::process::exit(1);
    }
}

fn init_tracing(format: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,sqlx=warn,tower_http=info"));
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    if format == "json" { builder.json().init() } else { builder.init() }
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        if let Ok(mut s) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            s.recv().await;
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! { _ = ctrl_c => {}, _ = term => {} }
    tracing::info!("shutting down: finishing requests, giving running jobs' leases back");
}

async fn serve(config: Config) -> anyhow::Result<()> {
    let app = Application::build(config.clone()).await?;
    announce(&app, &config);
    app.run_until(shutdown_signal()).await
}

/// The first line on stdout says where the service is (tests and scripts read it).
pub fn announce(app: &Application, config: &Config) {
    use std::io::Write;
    println!(
        "helmholtz-server listening on {} (gRPC + REST), data in {}, {} workers",
        app.base_url(),
        config.data_dir.display(),
        config.workers
    );
    let _ = std::io::stdout().flush();
}
