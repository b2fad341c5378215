//! The `helmholtz` command line. `main.rs` only calls [`main`].
//!
//! Every command prints one JSON object on stdout with `--json`, human text otherwise. Errors go to
//! stderr (and, with `--json`, as `{"error": "..."}` on stdout) with exit code 1; usage errors
//! exit with 2.

mod acquire;
mod adaptive;
mod args;
mod patterns;
mod preview;
mod reconstruct;
mod relight;
mod report;
mod simulate;
mod spool;
mod upload;

pub use acquire::AcquireArgs;
pub use args::{
    FamilyArg, FrameFormatArg, OrderingArg, PatternArgs, ResultArgs, SpecSource, TransferArgs,
};
pub use patterns::PatternsArgs;
pub use preview::PreviewArgs;
pub use reconstruct::{CancelArgs, FetchArgs, ReconstructArgs, StatusArgs};
pub use relight::{NormalsArgs, PrimalArgs, RelightArgs, light_of, pattern_of};
pub use simulate::{NoiseArgs, SimulateArgs};
pub use spool::{RowsFn, SpoolCommand, SpoolStatusArgs, SpoolUploadArgs};
pub use upload::{UploadArgs, check_rows};

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use serde_json::{Value, json};

use crate::spool::SpoolDir;
use acquire::acquire_cmd;
use patterns::patterns_cmd;
use preview::preview_cmd;
use reconstruct::{cancel_cmd, fetch_cmd, reconstruct_cmd, status_cmd};
use relight::{normals_cmd, primal_cmd, relight_cmd};
use simulate::simulate_cmd;
use spool::{spool_status_cmd, spool_upload_cmd};
use upload::upload_cmd;

const ABOUT: &str = "Helmholtz edge client: simulate a single-pixel / dual-photography rig, upload \
bucket measurements, and fetch reconstructed dual (ghost) images.";

const LONG_ABOUT: &str = "Helmholtz edge client.

A projector shows known patterns p_i (declared by a pattern spec and regenerated from its seed), a \
bucket detector records c_i = t . p_i + noise per pattern and channel, and the server reconstructs \
the light transport t on the pattern grid: the dual image.

A camera session replaces the bucket detector by a camera: every pattern's row is a whole frame \
(f32 or u16), and the server reconstructs the light transport T, which `relight` and `primal` then \
use (relight the scene from any virtual light, predict the camera image of any pattern).

One server address serves gRPC (uploads) and REST (reconstructions, images).

Every measured row is first written to a durable local spool (--spool DIR, env HELMHOLTZ_SPOOL; fsync'ed before it counts) and uploaded from there in the background. If the client, the network or the server dies, nothing measured is lost: `helmholtz spool status` shows what is pending and `helmholtz spool upload` resumes from the server's committed count.";

/// Top-level arguments.
#[derive(Debug, Parser)]
#[command(name = "helmholtz", version, about = ABOUT, long_about = LONG_ABOUT)]
pub struct Cli {
    /// Server address, for gRPC and REST alike (http://host:port, or https://host:port when the
    /// server runs with --tls-cert).
    #[arg(
        long,
        global = true,
        env = "HELMHOLTZ_SERVER",
        default_value = "http://127.0.0.1:8080"
    )]
    pub server: String,
    /// The lab's access token (hz_...), sent on every call; `helmholtz-server token create`
    /// makes one. A rig needs the rig role, requesting and fetching reconstructions the reader
    /// role. (It may also ride in --server as http://TOKEN@host:port.)
    #[arg(long, global = true, env = "HELMHOLTZ_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Print one JSON object on stdout instead of text (and no progress bars).
    #[arg(long, global = true)]
    pub json: bool,
    /// Spool directory: measured rows are kept here (one directory per session) until the server
    /// has committed them [default: $XDG_STATE_HOME/helmholtz/spool, else
    /// ~/.local/state/helmholtz/spool].
    #[arg(long, global = true, env = "HELMHOLTZ_SPOOL", value_name = "DIR")]
    pub spool: Option<PathBuf>,
    /// For an https:// server: also trust this PEM CA certificate (a lab's own CA), besides the
    /// system's roots.
    #[arg(long, global = true, env = "HELMHOLTZ_CA_FILE", value_name = "FILE")]
    pub ca_file: Option<PathBuf>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
#[allow(clippy::large_enum_variant)] // parsed once
pub enum Command {
    /// Simulate a rig imaging a scene, upload it as a session, optionally reconstruct and save.
    ///
    /// Steps: draw or load the scene, resample it to the pattern grid, compute every bucket value
    /// t . p_i, add noise (drift, shot, read, dark, ADC), write the rows to the spool (in batches
    /// of --batch-rows, at --frame-rate if given) while a background task creates the session
    /// (with the noiseless scene as ground truth unless --no-ground-truth) and uploads them with
    /// resume, finish, and with --reconstruct request a reconstruction (--wait / --out wait for it
    /// and save the image). Re-running an interrupted command with the same --session-id
    /// continues from what was spooled and committed.
    ///
    /// --scene lambert is an analytic Lambertian scene with a known transport for any direction:
    /// bucket detectors around it (--detectors, declared with their directions), colour filters
    /// (--colour), or a camera (--camera WxH: each pattern's row is a whole f32 or u16 frame,
    /// rendered batch by batch and spooled as it is).
    Simulate(SimulateArgs),
    /// Upload a real rig's measurements (CSV or NPY) to a session, creating it if needed.
    ///
    /// The file holds one row per pattern in pattern order and one column per detector channel.
    /// Its rows go through the spool like measured rows. Rows already committed on the server (an
    /// interrupted earlier upload) are not sent again.
    Upload(UploadArgs),
    /// Record a real rig's rows as they arrive on stdin: spool each batch, upload in the background.
    ///
    /// One row per line (pattern order), one number per channel, separated by commas, semicolons,
    /// tabs or spaces; blank lines and '#' comments are skipped. Rows are spooled every
    /// --batch-rows rows or --flush-ms after the first unspooled one, whichever comes first, and
    /// uploaded as they land. Rows continue after those already spooled for the session: re-run
    /// after a crash and feed the rows from there (`helmholtz spool status` says how many). At
    /// the end of input the session is finished with --finish once every row of the spec is in.
    Acquire(AcquireArgs),
    /// Show one session (upload progress, latest reconstruction), or list all sessions.
    Status(StatusArgs),
    /// Download a dual image (PNG, 32-bit float TIFF, or NPY).
    Fetch(FetchArgs),
    /// Request a reconstruction of a session; optionally wait for it and save the image.
    Reconstruct(ReconstructArgs),
    /// Relight a reconstructed transport: the dual image (projector-sized) under a virtual light.
    ///
    /// POST /v1/reconstructions/{id}/relight. The light shines from the camera (camera sessions:
    /// --full, --disc, --stripe in camera pixel units, or --light, a camera-sized PNG/NPY image
    /// sent as it is) or from the bucket detectors (--weights, one weight per channel).
    Relight(RelightArgs),
    /// Predict the camera image of a projector pattern from a reconstructed transport.
    ///
    /// POST /v1/reconstructions/{id}/primal with a measured pattern (--pattern-index; the server
    /// then also compares the prediction with the measured frame, printed as relative error and
    /// PSNR) or any pattern image (--pattern, projector-sized PNG/NPY).
    Primal(PrimalArgs),
    /// Download the surface normals a reconstruction of a multi-detector session estimated.
    ///
    /// GET /v1/reconstructions/{id}/normals.png (an RGB normal map) or normals.npy.
    Normals(NormalsArgs),
    /// Cancel a queued or running reconstruction (an ended one is refused with 409).
    Cancel(CancelArgs),
    /// Watch a session's live preview while it uploads: one line per frame.
    ///
    /// gRPC WatchPreview: a progressive dual image of the rows committed so far (DGI for
    /// bernoulli and speckle patterns, the zero-filled inverse for hadamard, the running scan
    /// for raster; a camera session as the sum over its pixels), every --every-rows rows or
    /// --every-ms milliseconds, until the final frame once every row is in. Run it beside
    /// `simulate`, `upload` or `acquire`; watching never slows the upload.
    Preview(PreviewArgs),
    /// Write pattern frames for a projector or DMD: 8-bit grey PNGs (frame_000000.png, ...)
    /// with --out DIR, and/or one float32 NPY stack (frames, height, width) with --npy FILE.
    Patterns(PatternsArgs),
    /// The local spool of measured rows: what is pending, and uploading it.
    #[command(subcommand)]
    Spool(SpoolCommand),
    /// Print a shell completion script to stdout (bash, zsh, fish, elvish, powershell).
    ///
    /// bash: `helmholtz completions bash > ~/.local/share/bash-completion/completions/helmholtz`;
    /// zsh: `helmholtz completions zsh > "${fpath[1]}/_helmholtz"`;
    /// fish: `helmholtz completions fish > ~/.config/fish/completions/helmholtz.fish`.
    Completions {
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
}

/// What a command prints.
#[derive(Debug)]
pub struct Outcome {
    pub json: Value,
    pub text: String,
}

/// Parses the arguments, runs the command, prints, and returns the exit code.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        // Colour codes only on a terminal, never with NO_COLOR.
        .with_ansi(
            std::io::IsTerminal::is_terminal(&std::io::stderr())
                && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty()),
        )
        .with_writer(std::io::stderr)
        .try_init();
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    let json_mode = cli.json;
    match runtime.block_on(run(cli)) {
        Ok(outcome) => {
            let text = if json_mode {
                serde_json::to_string_pretty(&outcome.json).expect("json")
            } else {
                outcome.text.trim_end().to_string()
            };
            // A closed pipe (`| head`) is not an error of ours.
            let _ = writeln!(std::io::stdout(), "{text}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            if json_mode {
                let chain: Vec<String> = e.chain().map(|c| c.to_string()).collect();
                let _ = writeln!(
                    std::io::stdout(),
                    "{}",
                    json!({ "error": format!("{e:#}"), "causes": chain })
                );
            }
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Runs one parsed command.
pub async fn run(cli: Cli) -> anyhow::Result<Outcome> {
    let progress = !cli.json && std::io::stderr().is_terminal();
    let server = match &cli.token {
        Some(token) => crate::auth::with_token(&cli.server, token.trim()),
        None => cli.server.clone(),
    };
    let server = server.as_str();
    if let Some(ca) = &cli.ca_file {
        crate::tls::trust_ca_file(ca)?;
    }
    let spools = SpoolDir::new(cli.spool.clone().unwrap_or_else(crate::spool::default_root));
    match &cli.command {
        Command::Simulate(a) => simulate_cmd(server, &spools, a, progress).await,
        Command::Upload(a) => upload_cmd(server, &spools, a, progress).await,
        Command::Spool(SpoolCommand::Status(a)) => spool_status_cmd(server, &spools, a).await,
        Command::Spool(SpoolCommand::Upload(a)) => spool_upload_cmd(server, &spools, a).await,
        Command::Status(a) => status_cmd(server, a).await,
        Command::Fetch(a) => fetch_cmd(server, a).await,
        Command::Reconstruct(a) => reconstruct_cmd(server, a, progress).await,
        Command::Patterns(a) => patterns_cmd(a),
        Command::Relight(a) => relight_cmd(server, a).await,
        Command::Primal(a) => primal_cmd(server, a).await,
        Command::Normals(a) => normals_cmd(server, a).await,
        Command::Cancel(a) => cancel_cmd(server, a).await,
        Command::Preview(a) => preview_cmd(server, a, cli.json).await,
        Command::Acquire(a) => acquire_cmd(server, &spools, a).await,
        Command::Completions { shell } => {
            let mut script = Vec::new();
            let mut command = <Cli as clap::CommandFactory>::command();
            clap_complete::generate(*shell, &mut command, "helmholtz", &mut script);
            let script = String::from_utf8(script)?;
            Ok(Outcome {
                json: json!({ "shell": shell.to_string(), "script": script }),
                text: script,
            })
        }
    }
}

/// `helmholtz ARGS` parsed (the command modules' tests).
#[cfg(test)]
fn parse(args: &[&str]) -> Cli {
    Cli::try_parse_from(std::iter::once("helmholtz").chain(args.iter().copied())).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn cli_definition_is_consistent() {
        Cli::command().debug_assert();
    }
}
