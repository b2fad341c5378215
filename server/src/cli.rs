//! The `helmholtz-server` command line.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, Subcommand};

use crate::app::{Application, Config};
use crate::auth::Roles;
use crate::edge::{EdgeConfig, TlsFiles};
use crate::limits::Limits;

#[derive(Parser, Debug)]
#[command(
    name = "helmholtz-server",
    version,
    about = "Helmholtz: dual photography and ghost imaging reconstruction service.\n\nServes the gRPC acquisition API (helmholtz.v1.Acquisition) and the REST API on one address, stores sessions in SQLite (embedded, in --data-dir) or PostgreSQL (--database-url, shared by API nodes and `worker` processes on many machines) and reconstructs on a pool of CPU workers.\n\nEvery call but the health checks needs a lab's token (Authorization: Bearer hz_...); create the first with `helmholtz-server token create --lab LAB --role admin` (or rig, reader, metrics)."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log format on stderr.
    #[arg(long, global = true, default_value = "text", value_parser = ["text", "json"])]
    log_format: String,
}

/// The service's options (`serve`, and the demo binary, which runs the same service).
#[derive(clap::Args, Debug, Clone)]
pub struct ServeArgs {
    /// Address for gRPC and REST (one port serves both); port 0 picks a free port.
    #[arg(long, env = "HELMHOLTZ_LISTEN", default_value = "127.0.0.1:8080")]
    listen: SocketAddr,
    #[command(flatten)]
    database: DatabaseArgs,
    /// Reconstruction worker threads (default: the number of CPU cores). 0: none (API only:
    /// requests queue in the database for the workers of other server processes sharing it).
    #[arg(long, env = "HELMHOLTZ_WORKERS")]
    workers: Option<usize>,
    /// Job lease in seconds: a job whose worker stops heart-beating for this long is taken up again.
    #[arg(long, default_value_t = 30)]
    lease_seconds: u64,
    /// Working-set budget of one camera-session reconstruction in MiB: T is solved a block of
    /// camera pixels at a time, the block sized to stay within it.
    #[arg(long, env = "HELMHOLTZ_WORKER_MEMORY_MIB", default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    worker_memory_mib: u64,
    /// Camera pixels per shard of a camera session's transport matrix: the job's blocks of
    /// camera pixels are cut to at most this many and run in shards that any worker sharing the
    /// database takes (each shard re-reads the frames of its blocks).
    #[arg(long, env = "HELMHOLTZ_TRANSPORT_SHARD_PIXELS", default_value_t = crate::jobs::DEFAULT_TRANSPORT_SHARD_PIXELS as u64, value_parser = clap::value_parser!(u64).range(1..))]
    transport_shard_pixels: u64,
    /// Memory for decoded transport matrices kept for relighting, in MiB (least recently used
    /// ones are dropped first).
    #[arg(long, default_value_t = 2048)]
    transport_cache_mib: u64,
    /// Also serve Prometheus metrics (GET /metrics) without a token on this separate address
    /// (a private scrape network); port 0 picks a free port (printed on the first line). The main
    /// port always serves GET /metrics to tokens with the `metrics` role.
    #[arg(long, env = "HELMHOLTZ_METRICS_LISTEN")]
    metrics_listen: Option<SocketAddr>,
    #[command(flatten)]
    limits: LimitArgs,
    #[command(flatten)]
    edge: EdgeArgs,
}

/// Where the service keeps its data: the embedded SQLite database in a directory, or a
/// PostgreSQL database shared by every API node and worker.
#[derive(clap::Args, Debug, Clone)]
pub struct DatabaseArgs {
    /// Directory of the embedded SQLite database (created if missing); not used with
    /// --database-url.
    #[arg(
        long,
        env = "HELMHOLTZ_DATA_DIR",
        default_value = "helmholtz-data",
        global = true
    )]
    data_dir: PathBuf,
    /// PostgreSQL database shared by every API node and worker process, e.g.
    /// postgres://helmholtz@db.lab.example:5432/helmholtz (migrated at start). Without it the
    /// embedded SQLite database in --data-dir is used.
    #[arg(
        long,
        env = "HELMHOLTZ_DATABASE_URL",
        value_name = "URL",
        global = true
    )]
    database_url: Option<String>,
    /// Most pooled connections this process opens to PostgreSQL (besides 2 of their own for
    /// bulk reads: rows, frames, images, T).
    #[arg(long, env = "HELMHOLTZ_DATABASE_CONNECTIONS", default_value_t = 16, value_parser = clap::value_parser!(u32).range(2..), global = true)]
    database_connections: u32,
}

impl DatabaseArgs {
    async fn open(&self) -> anyhow::Result<crate::store::Store> {
        use anyhow::Context;
        crate::store::Store::connect(
            self.database_url.as_deref(),
            &self.data_dir,
            self.database_connections,
        )
        .await
        .with_context(|| match &self.database_url {
            Some(_) => "opening the PostgreSQL database (--database-url)".to_string(),
            None => format!("opening the database in {}", self.data_dir.display()),
        })
    }
}

/// The network edge: timeouts, the connection cap, the shutdown deadline, TLS and CORS
/// (docs/security.md).
#[derive(clap::Args, Debug, Clone)]
struct EdgeArgs {
    /// Seconds a connection has to send a complete request head (the first one counted from
    /// accept, TLS handshake and HTTP/2 preface included); slower connections are closed.
    #[arg(long, env = "HELMHOLTZ_HEADER_TIMEOUT_SECS", default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..))]
    header_timeout_secs: u64,
    /// Seconds a REST request body may pause before the request fails with 408 (gRPC upload
    /// streams are not affected).
    #[arg(long, env = "HELMHOLTZ_BODY_TIMEOUT_SECS", default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..))]
    body_timeout_secs: u64,
    /// Most connections open at once; further ones wait to be accepted (logged). Lowered to fit
    /// under the open-file limit.
    #[arg(long, env = "HELMHOLTZ_MAX_CONNECTIONS", default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    max_connections: u64,
    /// On SIGTERM/Ctrl-C: seconds requests in flight may take to finish before every connection
    /// still open (idle upload streams included) is cut and the server exits.
    #[arg(long, env = "HELMHOLTZ_SHUTDOWN_DEADLINE_SECS", default_value_t = 10)]
    shutdown_deadline_secs: u64,
    /// PEM certificate chain: serve REST and gRPC over TLS (https://, ALPN h2 and http/1.1) on
    /// the same address. Needs --tls-key.
    #[arg(
        long,
        env = "HELMHOLTZ_TLS_CERT",
        value_name = "FILE",
        requires = "tls_key"
    )]
    tls_cert: Option<PathBuf>,
    /// PEM private key (PKCS#8, PKCS#1 or SEC1) of --tls-cert.
    #[arg(
        long,
        env = "HELMHOLTZ_TLS_KEY",
        value_name = "FILE",
        requires = "tls_cert"
    )]
    tls_key: Option<PathBuf>,
    /// Allow browser pages from this origin (e.g. https://viewer.lab.example) to call the REST
    /// API (CORS). Repeat for several. Without it no CORS headers are sent.
    #[arg(long = "cors-origin", value_name = "ORIGIN")]
    cors_origins: Vec<String>,
}

impl EdgeArgs {
    fn edge(&self) -> EdgeConfig {
        EdgeConfig {
            header_timeout: Duration::from_secs(self.header_timeout_secs),
            body_timeout: Duration::from_secs(self.body_timeout_secs),
            max_connections: usize::try_from(self.max_connections).unwrap_or(usize::MAX),
            shutdown_deadline: Duration::from_secs(self.shutdown_deadline_secs),
            tls: match (&self.tls_cert, &self.tls_key) {
                (Some(cert), Some(key)) => Some(TlsFiles {
                    cert: cert.clone(),
                    key: key.clone(),
                }),
                _ => None,
            },
            cors_origins: self.cors_origins.clone(),
        }
    }
}

/// Caps; each refusal names its limit.
#[derive(clap::Args, Debug, Clone)]
struct LimitArgs {
    /// Largest gRPC message in bytes (tonic refuses larger ones with OUT_OF_RANGE naming the limit).
    #[arg(long, default_value_t = Limits::default().max_message_bytes)]
    max_message_bytes: usize,
    /// Largest REST request body in bytes (413 above it).
    #[arg(long, default_value_t = Limits::default().max_body_bytes)]
    max_body_bytes: usize,
    /// Largest upload chunk (bucket values of one MeasurementChunk) in bytes.
    #[arg(long, default_value_t = Limits::default().max_chunk_bytes)]
    max_chunk_bytes: usize,
    /// Most patterns (rows) a session may declare.
    #[arg(long, default_value_t = Limits::default().max_patterns)]
    max_patterns: u64,
    /// Most pixels (width x height) of a session's patterns.
    #[arg(long, default_value_t = Limits::default().max_pixels)]
    max_pixels: u64,
    /// Most pixels (width x height) of one camera frame.
    #[arg(long, default_value_t = Limits::default().max_frame_pixels)]
    max_frame_pixels: u64,
    /// Most ground-truth values a simulated session may send (a camera session's T is m x k).
    #[arg(long, default_value_t = Limits::default().max_ground_truth_values)]
    max_ground_truth_values: u64,
    /// Most sessions one lab may hold.
    #[arg(long, default_value_t = Limits::default().max_sessions_per_lab)]
    max_sessions_per_lab: u64,
    /// Most reconstructions one lab may have queued or running.
    #[arg(long, default_value_t = Limits::default().max_pending_jobs_per_lab)]
    max_pending_jobs_per_lab: u64,
    /// Most reconstructions of one lab running at once (0: no cap beyond --workers).
    #[arg(long, default_value_t = Limits::default().max_running_jobs_per_lab)]
    max_running_jobs_per_lab: u32,
    /// Sustained requests per second per token (0: unlimited).
    #[arg(long, default_value_t = Limits::default().rate_per_second)]
    rate_per_second: f64,
    /// Burst of requests per token above the sustained rate.
    #[arg(long, default_value_t = Limits::default().rate_burst)]
    rate_burst: f64,
    /// Seconds an upload stream's hold on its session (one writer per session) lasts without
    /// renewal: after a server dies mid-upload, its sessions take new writers after this long.
    #[arg(long, default_value_t = Limits::default().upload_lease.as_secs(), value_parser = clap::value_parser!(u64).range(1..))]
    upload_lease_secs: u64,
    /// Seconds an upload stream may stay silent (no chunk) before the server closes it; the
    /// rows it committed stay.
    #[arg(long, default_value_t = Limits::default().upload_idle.as_secs(), value_parser = clap::value_parser!(u64).range(1..))]
    upload_idle_secs: u64,
    /// Memory the reconstructions running in this process may take together, in MiB [default:
    /// three quarters of the machine's memory]. A request whose estimate exceeds it is refused
    /// up front (413 / RESOURCE_EXHAUSTED with the estimate); jobs start only while the running
    /// ones' estimates leave room.
    #[arg(long, env = "HELMHOLTZ_MEMORY_BUDGET_MIB", value_parser = clap::value_parser!(u64).range(1..))]
    memory_budget_mib: Option<u64>,
}

impl LimitArgs {
    fn limits(&self) -> Limits {
        Limits {
            max_message_bytes: self.max_message_bytes,
            max_body_bytes: self.max_body_bytes,
            max_chunk_bytes: self.max_chunk_bytes,
            max_patterns: self.max_patterns,
            max_pixels: self.max_pixels,
            max_frame_pixels: self.max_frame_pixels,
            max_ground_truth_values: self.max_ground_truth_values,
            max_sessions_per_lab: self.max_sessions_per_lab,
            max_pending_jobs_per_lab: self.max_pending_jobs_per_lab,
            max_running_jobs_per_lab: self.max_running_jobs_per_lab,
            rate_per_second: self.rate_per_second,
            rate_burst: self.rate_burst,
            upload_lease: Duration::from_secs(self.upload_lease_secs),
            upload_idle: Duration::from_secs(self.upload_idle_secs),
            memory_budget: self
                .memory_budget_mib
                .map_or_else(crate::limits::default_memory_budget, |m| m << 20),
        }
    }
}

#[derive(Subcommand, Debug)]
enum TokenCommand {
    /// Create a token for a lab and print it (once: only its SHA-256 is stored).
    Create {
        /// The lab the token belongs to (1-64 characters of A-Z a-z 0-9 . _ -).
        #[arg(long)]
        lab: String,
        /// Role: rig (create sessions, upload), reader (read, request and cancel
        /// reconstructions), admin (manage the lab's tokens), metrics (scrape GET /metrics on the
        /// main port). Repeat or comma-separate for several.
        #[arg(long = "role", required = true, value_delimiter = ',')]
        roles: Vec<String>,
        /// A note to recognise the token by in `token list`.
        #[arg(long, default_value = "")]
        note: String,
        /// Print JSON (id, lab, roles, token) instead of the bare token.
        #[arg(long)]
        json: bool,
    },
    /// List tokens (never their secrets).
    List {
        /// Only this lab's tokens.
        #[arg(long)]
        lab: Option<String>,
    },
    /// Revoke a token by id; it stops working at once.
    Revoke {
        /// The token's id (from `token list` or `token create --json`).
        id: i64,
    },
}

#[derive(Subcommand, Debug)]
#[allow(clippy::large_enum_variant)] // parsed once
enum Command {
    /// Run the service until Ctrl-C (or SIGTERM).
    Serve(ServeArgs),
    /// Manage access tokens directly in the database (works whether or not the server runs).
    Token {
        #[command(subcommand)]
        command: TokenCommand,
        #[command(flatten)]
        database: DatabaseArgs,
    },
    /// Run reconstruction workers only (no listener) until Ctrl-C (or SIGTERM): they take jobs
    /// from the database that API nodes (`serve --workers 0`) queue, on this or any machine.
    Worker(WorkerArgs),
    /// Apply the database's pending migrations and exit (`serve` and `worker` also do this at
    /// start).
    Migrate {
        #[command(flatten)]
        database: DatabaseArgs,
    },
    /// Check the database before starting processes on it: reachable, schema applied (pending
    /// migrations are applied, as `migrate` does), and the clock skew between this machine and
    /// the database (leases use the database's clock; a large skew only affects log times).
    /// Exits non-zero when the database cannot be used.
    Check {
        #[command(flatten)]
        database: DatabaseArgs,
    },
    /// Print a shell completion script to stdout (bash, zsh, fish, elvish, powershell), e.g.
    /// `helmholtz-server completions bash > ~/.local/share/bash-completion/completions/helmholtz-server`.
    Completions {
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
}

/// A worker process's options.
#[derive(clap::Args, Debug, Clone)]
pub struct WorkerArgs {
    #[command(flatten)]
    database: DatabaseArgs,
    /// Reconstruction worker threads (default: the number of CPU cores).
    #[arg(long, env = "HELMHOLTZ_WORKERS", value_parser = clap::value_parser!(u64).range(1..))]
    workers: Option<u64>,
    /// Job lease in seconds: a job whose worker stops heart-beating for this long is taken up again.
    #[arg(long, default_value_t = 30)]
    lease_seconds: u64,
    /// Working-set budget of one camera-session reconstruction in MiB.
    #[arg(long, env = "HELMHOLTZ_WORKER_MEMORY_MIB", default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    worker_memory_mib: u64,
    /// Camera pixels per shard of a camera session's transport matrix: the job's blocks of
    /// camera pixels are cut to at most this many and run in shards that any worker sharing the
    /// database takes (each shard re-reads the frames of its blocks).
    #[arg(long, env = "HELMHOLTZ_TRANSPORT_SHARD_PIXELS", default_value_t = crate::jobs::DEFAULT_TRANSPORT_SHARD_PIXELS as u64, value_parser = clap::value_parser!(u64).range(1..))]
    transport_shard_pixels: u64,
    /// Memory the reconstructions running in this process may take together, in MiB [default:
    /// three quarters of the machine's memory].
    #[arg(long, env = "HELMHOLTZ_MEMORY_BUDGET_MIB", value_parser = clap::value_parser!(u64).range(1..))]
    memory_budget_mib: Option<u64>,
    /// Most reconstructions of one lab running at once across all workers sharing the
    /// database (0: no cap). Give every process the same value.
    #[arg(long, default_value_t = Limits::default().max_running_jobs_per_lab)]
    max_running_jobs_per_lab: u32,
}

impl ServeArgs {
    /// The application's configuration from these options.
    pub fn config(&self) -> Config {
        let mut config = Config {
            listen: self.listen,
            data_dir: self.database.data_dir.clone(),
            database_url: self.database.database_url.clone(),
            database_connections: self.database.database_connections,
            lease: Duration::from_secs(self.lease_seconds.max(1)),
            limits: self.limits.limits(),
            metrics_listen: self.metrics_listen,
            worker_memory: (self.worker_memory_mib as usize) << 20,
            transport_cache: (self.transport_cache_mib as usize) << 20,
            transport_shard_pixels: self.transport_shard_pixels as usize,
            edge: self.edge.edge(),
            ..Config::default()
        };
        if let Some(w) = self.workers {
            config.workers = w;
        }
        config
    }
}

pub fn main() {
    let cli = Cli::parse();
    if let Command::Completions { shell } = cli.command {
        let mut command = <Cli as clap::CommandFactory>::command();
        clap_complete::generate(
            shell,
            &mut command,
            "helmholtz-server",
            &mut std::io::stdout(),
        );
        return;
    }
    init_tracing(&cli.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    let result = runtime.block_on(async move {
        match cli.command {
            Command::Serve(args) => serve(args.config()).await,
            Command::Token { command, database } => token(command, &database).await,
            Command::Worker(args) => worker(args).await,
            Command::Check { database } => check(&database).await,
            Command::Migrate { database } => {
                let store = database.open().await?;
                println!("{}: migrations applied", store.describe());
                store.close().await;
                Ok(())
            }
            Command::Completions { .. } => unreachable!("handled before the runtime starts"),
        }
    });
    if let Err(e) = result {
        eprintln!("helmholtz-server: {e:#}");
        std::process::exit(1);
    }
}

/// Logs to stderr as text or JSON lines, filtered by `RUST_LOG`.
pub fn init_tracing(format: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,sqlx=warn,tower_http=info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(colour_logs())
        .with_writer(std::io::stderr);
    if format == "json" {
        builder.json().init()
    } else {
        builder.init()
    }
}

/// Colour codes in logs only on a terminal (not in files, journald or pipes), and never with
/// `NO_COLOR` set.
pub fn colour_logs() -> bool {
    use std::io::IsTerminal;
    std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        if let Ok(mut s) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        {
            s.recv().await;
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! { _ = ctrl_c => {}, _ = term => {} }
    tracing::info!("shutting down: finishing requests, giving running jobs' leases back");
}

/// `helmholtz-server check`: what an operator wants to know before starting nodes.
async fn check(database: &DatabaseArgs) -> anyhow::Result<()> {
    let store = database.open().await?;
    anyhow::ensure!(store.ping().await, "{}: does not answer", store.describe());
    let version = store.schema_version().await?;
    let sent = std::time::SystemTime::now();
    let db_ms = store.clock_ms().await?;
    let round_trip = sent.elapsed().unwrap_or_default();
    let local_ms = crate::store::now_ms() - round_trip.as_millis() as i64 / 2;
    println!(
        "{}: reachable, schema at migration {version}, clock skew {:+} ms (round trip {} ms)",
        store.describe(),
        db_ms - local_ms,
        round_trip.as_millis()
    );
    store.close().await;
    Ok(())
}

/// Workers without a listener, until Ctrl-C or SIGTERM; running jobs give their leases back.
async fn worker(args: WorkerArgs) -> anyhow::Result<()> {
    let store = args.database.open().await?;
    let workers = args.workers.map_or_else(
        || std::thread::available_parallelism().map_or(2, |n| n.get()),
        |w| w as usize,
    );
    let pool = crate::jobs::WorkerPool::start(
        store.clone(),
        tokio::runtime::Handle::current(),
        crate::jobs::PoolConfig {
            workers,
            lease: Duration::from_secs(args.lease_seconds.max(1)),
            max_running_per_lab: args.max_running_jobs_per_lab,
            memory_budget: (args.worker_memory_mib as usize) << 20,
            process_memory: args
                .memory_budget_mib
                .map_or_else(crate::limits::default_memory_budget, |m| m << 20),
            transport_shard_pixels: args.transport_shard_pixels as usize,
            ..crate::jobs::PoolConfig::default()
        },
    );
    tracing::info!(database = %store.describe(), workers, "workers started");
    println!(
        "helmholtz-server worker: {workers} workers on {}",
        store.describe()
    );
    shutdown_signal().await;
    tokio::task::spawn_blocking(move || pool.shutdown()).await?;
    store.close().await;
    Ok(())
}

async fn token(command: TokenCommand, database: &DatabaseArgs) -> anyhow::Result<()> {
    let store = database.open().await?;
    let result = async {
        match command {
            TokenCommand::Create {
                lab,
                roles,
                note,
                json,
            } => {
                crate::auth::valid_lab(&lab).map_err(|e| anyhow::anyhow!("--lab: {e}"))?;
                let roles =
                    Roles::parse(&roles.join(",")).map_err(|e| anyhow::anyhow!("--role: {e}"))?;
                if note.len() > 256 || note.chars().any(char::is_control) {
                    anyhow::bail!("--note: at most 256 characters without control characters");
                }
                let (info, secret) = store.create_token(&lab, roles, &note).await?;
                if json {
                    let view = crate::api::rest::token_view(&info, Some(secret));
                    println!("{}", serde_json::to_string(&view)?);
                } else {
                    println!("{secret}");
                    eprintln!(
                        "token {} for lab {:?} with roles {}: shown once, store it now",
                        info.id, info.lab, info.roles
                    );
                }
            }
            TokenCommand::List { lab } => {
                for t in store.list_tokens(lab.as_deref()).await? {
                    println!(
                        "{}\t{}\t{}\t{}\t{}",
                        t.id,
                        t.lab,
                        t.roles,
                        if t.revoked_unix_ms.is_some() {
                            "revoked"
                        } else {
                            "valid"
                        },
                        t.note
                    );
                }
            }
            TokenCommand::Revoke { id } => {
                let t = store
                    .revoke_token(id, None)
                    .await?
                    .ok_or_else(|| anyhow::anyhow!("no token with id {id}"))?;
                println!("token {} of lab {:?} revoked", t.id, t.lab);
            }
        }
        Ok(())
    }
    .await;
    store.close().await;
    result
}

async fn serve(config: Config) -> anyhow::Result<()> {
    let app = Application::build(config.clone()).await?;
    announce(&app, &config);
    app.run_until(shutdown_signal()).await
}

/// The first line on stdout says where the service is (tests and scripts read it).
pub fn announce(app: &Application, config: &Config) {
    use std::io::Write;
    let metrics = app
        .metrics_url()
        .map(|u| format!(", metrics on {u}"))
        .unwrap_or_default();
    println!(
        "helmholtz-server listening on {} (gRPC + REST){metrics}, data in {}, {} workers",
        app.base_url(),
        app.store().describe(),
        config.workers
    );
    let _ = std::io::stdout().flush();
}
