//! The `helmholtz` command line. `main.rs` only calls [`main`].
//!
//! Every command prints one JSON object on stdout with `--json`, human text otherwise. Errors go to
//! stderr (and, with `--json`, as `{"error": "..."}` on stdout) with exit code 1; usage errors
//! exit with 2.

use std::collections::BTreeMap;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use helmholtz_proto::patterns::{Family, HadamardOrdering};
use helmholtz_proto::{PatternSpec, SpecError};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde_json::{Value, json};

use crate::frames;
use crate::measurements::{self, Measurements};
use crate::rest::{self, FetchTarget, ImageFormat, Reconstruction};
use helmholtz_sim::Target;
use helmholtz_sim::simulate::lambert;
use helmholtz_sim::simulate::{self, NoiseModel};
use crate::spool::{self, DrainReport, SpoolDir};
use crate::upload::{self, NewSession, SampleBuf, SampleFormat, UploadOptions};

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
    /// Write pattern frames as 8-bit grey PNGs (frame_000000.png, ...) for a projector or DMD.
    Patterns(PatternsArgs),
    /// The local spool of measured rows: what is pending, and uploading it.
    #[command(subcommand)]
    Spool(SpoolCommand),
}

#[derive(Debug, Subcommand)]
pub enum SpoolCommand {
    /// Per spooled session: rows spooled, rows the server has committed (if reachable), rows
    /// pending, whether the producer finished, and the last upload error.
    Status(SpoolStatusArgs),
    /// Upload what is pending (every spooled session, or those named): rows not yet confirmed
    /// are sent and the server compares any it already holds byte for byte; then exit. Fully
    /// uploaded (and finished) sessions leave the spool; refused rows stay in it.
    Upload(SpoolUploadArgs),
}

#[derive(Debug, Clone, Args)]
pub struct SpoolStatusArgs {
    /// Sessions to show [default: every session in the spool].
    pub session_ids: Vec<String>,
}

#[derive(Debug, Clone, Args)]
pub struct SpoolUploadArgs {
    /// Sessions to upload [default: every session in the spool].
    pub session_ids: Vec<String>,
    #[command(flatten)]
    pub transfer: TransferArgs,
}

/// Pattern families.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FamilyArg {
    /// Each pixel on with probability --fill (random binary; GI/DGI/NGI).
    Bernoulli,
    /// 2D Walsh-Hadamard rows as P+/P- split pairs (--count frames, even, up to 2 x pixels).
    Hadamard,
    /// One pixel (or --block x --block block) on at a time.
    Raster,
    /// Random grey levels on --grain x --grain cells (SLM / rotating diffuser).
    Speckle,
}

/// Hadamard row orderings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum OrderingArg {
    /// Sylvester (Kronecker) order.
    Natural,
    /// Walsh order: by number of sign changes along the flattened pattern.
    Sequency,
    /// 2D sequency diagonals (low spatial frequencies first).
    Zigzag,
    /// Nested dyadic levels: after 4^j rows the whole 2^j x 2^j basis is measured.
    #[value(name = "russian-doll", alias = "russian_doll")]
    RussianDoll,
    /// By number of constant pieces (Yu et al. 2019).
    #[value(name = "cake-cutting", alias = "cake_cutting")]
    CakeCutting,
}

impl From<OrderingArg> for HadamardOrdering {
    fn from(o: OrderingArg) -> Self {
        match o {
            OrderingArg::Natural => HadamardOrdering::Natural,
            OrderingArg::Sequency => HadamardOrdering::Sequency,
            OrderingArg::Zigzag => HadamardOrdering::Zigzag,
            OrderingArg::RussianDoll => HadamardOrdering::RussianDoll,
            OrderingArg::CakeCutting => HadamardOrdering::CakeCutting,
        }
    }
}

/// The pattern declaration as flags.
#[derive(Debug, Clone, Args)]
pub struct PatternArgs {
    /// Pattern family.
    #[arg(long, value_enum, default_value = "bernoulli")]
    pub family: FamilyArg,
    /// Pattern width in pixels (a power of two for hadamard).
    #[arg(long, default_value_t = 64)]
    pub width: u32,
    /// Pattern height in pixels (a power of two for hadamard).
    #[arg(long, default_value_t = 64)]
    pub height: u32,
    /// Number of patterns (frames) shown. Default: the full basis for hadamard (2 x width x
    /// height frames) and raster (--scans x one per block); required for bernoulli and speckle.
    #[arg(long)]
    pub count: Option<u64>,
    /// Bernoulli: probability that a pixel is on, in (0, 1).
    #[arg(long, default_value_t = 0.5)]
    pub fill: f64,
    /// Hadamard: row ordering (matters when --count is below the full basis).
    #[arg(long, value_enum, default_value = "natural")]
    pub ordering: OrderingArg,
    /// Raster: block side in pixels.
    #[arg(long, default_value_t = 1)]
    pub block: u32,
    /// Raster: how many times the block scan repeats (e.g. to average noise); --count may be
    /// at most scans x blocks, and defaults to exactly that.
    #[arg(long, default_value_t = 1)]
    pub scans: u32,
    /// Speckle: cell side in pixels.
    #[arg(long, default_value_t = 1)]
    pub grain: u32,
    /// Pattern seed: the server regenerates the same patterns from it.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl PatternArgs {
    /// The validated spec; errors name the flag.
    pub fn to_spec(&self) -> anyhow::Result<PatternSpec> {
        let family = match self.family {
            FamilyArg::Bernoulli => Family::Bernoulli { fill: self.fill },
            FamilyArg::Hadamard => Family::Hadamard {
                ordering: self.ordering.into(),
            },
            FamilyArg::Raster => Family::Raster {
                block: self.block,
                scans: self.scans,
            },
            FamilyArg::Speckle => Family::Speckle { grain: self.grain },
        };
        let pixels = self.width as u64 * self.height as u64;
        let count = match (self.count, self.family) {
            (Some(c), _) => c,
            (None, FamilyArg::Hadamard) => 2 * pixels,
            (None, FamilyArg::Raster) => {
                let b = self.block.max(1);
                let blocks = self.width.div_ceil(b) as u64 * self.height.div_ceil(b) as u64;
                blocks * self.scans.max(1) as u64
            }
            (None, f) => bail!(
                "--count is required for {} patterns (correlation imaging needs many: e.g. {} = 8 x width x height)",
                format!("{f:?}").to_lowercase(),
                8 * pixels
            ),
        };
        PatternSpec::new(family, self.width, self.height, count, self.seed).map_err(spec_flag_error)
    }
}

fn spec_flag_error(e: SpecError) -> anyhow::Error {
    anyhow::anyhow!("--{}: {}", e.field, e.message)
}

/// A spec from `--spec FILE` or `--spec-json TEXT`.
#[derive(Debug, Clone, Args)]
#[group(required = true, multiple = false)]
pub struct SpecSource {
    /// Pattern spec JSON file, e.g. {"family":"bernoulli","width":64,"height":64,"count":4096,"seed":7,"fill":0.5}.
    #[arg(long, value_name = "FILE")]
    pub spec: Option<PathBuf>,
    /// Pattern spec as inline JSON (same form as --spec).
    #[arg(long, value_name = "JSON")]
    pub spec_json: Option<String>,
}

impl SpecSource {
    pub fn load(&self) -> anyhow::Result<PatternSpec> {
        let (text, origin) = match (&self.spec, &self.spec_json) {
            (Some(path), _) => (
                std::fs::read_to_string(path)
                    .with_context(|| format!("reading {}", path.display()))?,
                path.display().to_string(),
            ),
            (None, Some(text)) => (text.clone(), "--spec-json".to_string()),
            (None, None) => bail!("give --spec FILE or --spec-json JSON"),
        };
        serde_json::from_str(&text).with_context(|| format!("{origin}: not a valid pattern spec"))
    }
}

/// Noise flags of the simulator.
#[derive(Debug, Clone, Args)]
pub struct NoiseArgs {
    /// Peak transport: the scene is scaled so its brightest pixel is this (signal units).
    #[arg(long, default_value_t = 1.0)]
    pub gain: f32,
    /// Source drift: relative standard deviation of a slow multiplicative random walk (e.g. 0.02).
    #[arg(long, default_value_t = 0.0)]
    pub drift: f64,
    /// Correlation length of the drift in patterns [default: count / 20, at least 16].
    #[arg(long)]
    pub drift_correlation: Option<f64>,
    /// Shot noise: mean photo-electrons per pattern (Poisson). Omit for no shot noise.
    #[arg(long)]
    pub photons: Option<f64>,
    /// Read noise: signal-to-noise ratio in dB, sigma = rms(c) / 10^(snr/20). Omit for none.
    #[arg(long)]
    pub snr_db: Option<f64>,
    /// Dark offset added to every value (signal units).
    #[arg(long, default_value_t = 0.0)]
    pub dark: f64,
    /// ADC bits (e.g. 12 or 16): quantise to 2^bits levels of full scale = 1.1 max(signal) +
    /// dark, clipping above (saturation). Omit for an ideal, unquantised detector.
    #[arg(long)]
    pub adc_bits: Option<u32>,
    /// Seed of the noise (independent of the pattern --seed).
    #[arg(long, default_value_t = 1)]
    pub noise_seed: u64,
}

impl NoiseArgs {
    pub fn model(&self) -> NoiseModel {
        NoiseModel {
            drift: self.drift,
            drift_correlation: self.drift_correlation,
            photons: self.photons,
            snr_db: self.snr_db,
            dark: self.dark,
            adc_bits: self.adc_bits,
            seed: self.noise_seed,
        }
    }
}

/// Upload tuning flags.
#[derive(Debug, Clone, Args)]
pub struct TransferArgs {
    /// Rows per upload chunk [default: about 256 KiB of values].
    #[arg(long)]
    pub chunk_rows: Option<usize>,
    /// Keep retrying (re-asking the server's committed count and resuming) for this many seconds
    /// without progress before giving up.
    #[arg(long, default_value_t = 60.0)]
    pub retry_for: f64,
}

impl TransferArgs {
    fn options(&self, progress: bool) -> anyhow::Result<UploadOptions> {
        anyhow::ensure!(
            self.retry_for >= 0.0 && self.retry_for.is_finite(),
            "--retry-for must be >= 0"
        );
        anyhow::ensure!(
            self.chunk_rows != Some(0),
            "--chunk-rows must be at least 1"
        );
        Ok(UploadOptions {
            chunk_rows: self.chunk_rows,
            retry_for: Duration::from_secs_f64(self.retry_for),
            progress,
            ..UploadOptions::default()
        })
    }
}

/// Reconstruction flags shared by `simulate` and `reconstruct`.
#[derive(Debug, Clone, Args)]
pub struct ResultArgs {
    /// Method parameters as a JSON object, e.g. '{"lambda": 0.01}'.
    #[arg(long, value_name = "JSON")]
    pub params: Option<String>,
    /// Wait until the reconstruction is done (implied by --out).
    #[arg(long)]
    pub wait: bool,
    /// Give up waiting after this many seconds.
    #[arg(long, default_value_t = 600.0)]
    pub timeout: f64,
    /// Save the dual image here once done (format from the extension: .png, .tiff, .npy).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// Image format when --out has no telling extension.
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Detector channel to save [default: the server's default].
    #[arg(long)]
    pub channel: Option<String>,
}

/// How a simulated camera's frames are stored and sent.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FrameFormatArg {
    /// 32-bit floats in signal units.
    F32,
    /// 16-bit counts: the brightest noiseless pixel reads about 60000.
    U16,
}

impl From<FrameFormatArg> for SampleFormat {
    fn from(f: FrameFormatArg) -> Self {
        match f {
            FrameFormatArg::F32 => SampleFormat::F32,
            FrameFormatArg::U16 => SampleFormat::U16,
        }
    }
}

#[derive(Debug, Clone, Args)]
pub struct SimulateArgs {
    /// Target: camera, shapes, usaf (USAF-1951 chart), double-slit, or a PNG file (grey or colour,
    /// 8/16 bit; resampled to the pattern grid): one bucket detector sees it as its transport.
    /// Or lambert: an analytic Lambertian scene (ground plane, hemisphere, box; cast shadows, one
    /// diffuse bounce) with a known light transport for any detector direction or camera (see
    /// --detectors, --colour, --camera); without those, one bucket detector at the projector.
    #[arg(long)]
    pub scene: String,
    /// lambert: seed of the scene's albedo texture.
    #[arg(long, default_value_t = 1)]
    pub scene_seed: u64,
    /// lambert: bucket detectors, comma separated names. n, e, s, w (or north, ...) stand at
    /// azimuths 270, 0, 90, 180 degrees (y is down the image: north is -y); other names are
    /// spread evenly from +x. Each channel's dual image is the scene seen from its direction,
    /// and the directions are declared with the session.
    #[arg(long, value_delimiter = ',', value_name = "NAMES")]
    pub detectors: Option<Vec<String>>,
    /// lambert: elevation of the --detectors above the ground plane, in degrees (0, 90].
    #[arg(long, default_value_t = 45.0, value_name = "DEG")]
    pub detector_elevation: f64,
    /// lambert: colour-filtered buckets: channels r, g, b of one detector at the projector (or
    /// NAME-r, NAME-g, NAME-b for each of --detectors).
    #[arg(long, alias = "color")]
    pub colour: bool,
    /// lambert: a camera of WIDTHxHEIGHT pixels (at most 256x256) in place of bucket detectors:
    /// each pattern's row is a whole frame (the session measures the light transport T).
    /// Ground truth (T itself) is sent when camera pixels x pattern pixels <= 4,194,304.
    #[arg(long, value_name = "WxH")]
    pub camera: Option<String>,
    /// lambert --camera: tilt of the camera from the projector's axis toward +x, in degrees.
    #[arg(long, default_value_t = 0.0, value_name = "DEG")]
    pub camera_tilt: f64,
    /// lambert --camera: frame format, f32 (signal units) or u16 (counts; the brightest
    /// noiseless pixel reads about 60000, the rest is clamped to 0..65535 and rounded).
    #[arg(long, value_enum, default_value = "f32")]
    pub frame_format: FrameFormatArg,
    #[command(flatten)]
    pub patterns: PatternArgs,
    /// Detector channel names, comma separated (each sees the same scene, see --channel-gains).
    /// Image scenes only (lambert names its channels by --detectors / --colour).
    #[arg(long, value_delimiter = ',', default_value = "bucket")]
    pub channels: Vec<String>,
    /// Per-channel scale of the scene, comma separated (default 1 for every channel).
    #[arg(long, value_delimiter = ',')]
    pub channel_gains: Vec<f32>,
    #[command(flatten)]
    pub noise: NoiseArgs,
    /// Session id (1-128 of A-Z a-z 0-9 . _ -) [default: sim-<time>-<random>]. Re-running with
    /// the same id and declaration resumes the upload instead of creating a new session.
    #[arg(long)]
    pub session_id: Option<String>,
    /// Rig name recorded with the session.
    #[arg(long, default_value = "simulator")]
    pub rig: String,
    /// Extra session metadata, KEY=VALUE (repeatable).
    #[arg(long = "metadata", value_name = "KEY=VALUE")]
    pub metadata: Vec<String>,
    /// Do not send the noiseless scene as ground truth (the server then reports no PSNR/SSIM).
    #[arg(long)]
    pub no_ground_truth: bool,
    /// Also write the simulated values (rows x channels) to a .csv or .npy file.
    #[arg(long, value_name = "FILE")]
    pub values_out: Option<PathBuf>,
    /// Only simulate (and write --values-out / --scene-out): contact no server, use no spool.
    #[arg(long)]
    pub offline: bool,
    /// Pace the simulated rig like a real one: this many patterns per second are measured and
    /// spooled (and uploaded as they arrive) [default: as fast as the disk allows].
    #[arg(long, value_name = "HZ")]
    pub frame_rate: Option<f64>,
    /// Rows per spool write: each batch is fsync'ed before it counts as measured (camera
    /// frames: at most 8 MiB a write).
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch_rows: u64,
    /// Write the scene as seen on the pattern grid (8-bit PNG) to this file (lambert: the first
    /// channel's dual image, or what the camera sees of the scene, scaled to its maximum).
    #[arg(long, value_name = "FILE")]
    pub scene_out: Option<PathBuf>,
    /// Request a reconstruction after the upload: gi, dgi, ngi, direct, zero_filled, levels, lsq,
    /// cs, tv or auto (see --params).
    #[arg(long, value_name = "METHOD")]
    pub reconstruct: Option<String>,
    #[command(flatten)]
    pub result: ResultArgs,
    #[command(flatten)]
    pub transfer: TransferArgs,
}

#[derive(Debug, Clone, Args)]
pub struct UploadArgs {
    /// Session id (1-128 of A-Z a-z 0-9 . _ -). Created if new; re-running resumes.
    #[arg(long)]
    pub session_id: String,
    #[command(flatten)]
    pub spec: SpecSource,
    /// Measurements: CSV (one row per pattern, one column per channel, optional header of
    /// channel names, '#' comments) or NPY (shape (n,) or (n, channels); float or int). A camera
    /// rig's frames: NPY of shape (n, height, width), uint16 or float32, which makes a camera
    /// session (frames are read from the file batch by batch, never all at once).
    #[arg(long, value_name = "FILE")]
    pub values: PathBuf,
    /// Channel names, comma separated [default: the CSV header, else "bucket" for one column,
    /// else ch0,ch1,...].
    #[arg(long, value_delimiter = ',')]
    pub channels: Vec<String>,
    /// Rig name recorded with the session.
    #[arg(long, default_value = "rig")]
    pub rig: String,
    /// Extra session metadata, KEY=VALUE (repeatable).
    #[arg(long = "metadata", value_name = "KEY=VALUE")]
    pub metadata: Vec<String>,
    /// Finish the session after the upload (all rows of the spec must then be committed).
    #[arg(long)]
    pub finish: bool,
    /// Accept a file with fewer rows than the spec's count (upload a prefix, continue later).
    #[arg(long)]
    pub partial: bool,
    /// Rows per spool write: each batch is fsync'ed before it counts as measured.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch_rows: u64,
    #[command(flatten)]
    pub transfer: TransferArgs,
}

#[derive(Debug, Clone, Args)]
pub struct AcquireArgs {
    /// Session id (1-128 of A-Z a-z 0-9 . _ -). Created if new; re-running continues it.
    #[arg(long)]
    pub session_id: String,
    #[command(flatten)]
    pub spec: SpecSource,
    /// Channel names, comma separated (one number per channel on each line).
    #[arg(long, value_delimiter = ',', default_value = "bucket")]
    pub channels: Vec<String>,
    /// Rig name recorded with the session.
    #[arg(long, default_value = "rig")]
    pub rig: String,
    /// Extra session metadata, KEY=VALUE (repeatable).
    #[arg(long = "metadata", value_name = "KEY=VALUE")]
    pub metadata: Vec<String>,
    /// Finish the session at the end of input (every row of the spec must then be in).
    #[arg(long)]
    pub finish: bool,
    /// Rows per spool write: each batch is fsync'ed before it counts as measured.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch_rows: u64,
    /// Spool the rows read so far once the first of them has waited this long.
    #[arg(long, default_value_t = 200)]
    pub flush_ms: u64,
    /// The pattern index of the first row on stdin [default: where the session continues: the
    /// end of this session's spool, else the server's committed count]. Given, it must agree
    /// with the spool (a spool holding unsent rows fixes where the next row goes) and must not
    /// leave a gap after the server's rows; rows before the server's count are compared with
    /// the stored ones.
    #[arg(long)]
    pub start_row: Option<u64>,
    #[command(flatten)]
    pub transfer: TransferArgs,
}

#[derive(Debug, Clone, Args)]
pub struct StatusArgs {
    /// Session to show; omit to list all sessions.
    pub session_id: Option<String>,
}

#[derive(Debug, Clone, Args)]
pub struct FetchArgs {
    /// Reconstruction id.
    #[arg(long, required_unless_present = "session", conflicts_with = "session")]
    pub reconstruction: Option<i64>,
    /// Session id: its latest finished reconstruction.
    #[arg(long)]
    pub session: Option<String>,
    /// Image format [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Detector channel [default: the server's default].
    #[arg(long)]
    pub channel: Option<String>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Args)]
pub struct ReconstructArgs {
    /// Session to reconstruct.
    #[arg(long)]
    pub session_id: String,
    /// Method: gi (correlation), dgi (differential), ngi (normalised), direct (complete
    /// Hadamard/raster inverse), zero_filled / levels (Hadamard subsets), lsq, cs, tv, or auto
    /// (the data choose the model by held-out error). Parameters: --params.
    #[arg(long)]
    pub method: String,
    #[command(flatten)]
    pub result: ResultArgs,
}

#[derive(Debug, Clone, Args)]
#[command(group(clap::ArgGroup::new("light_source").required(true).args(["full", "disc", "stripe", "weights", "light"])))]
pub struct RelightArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
    /// Every camera pixel lit.
    #[arg(long)]
    pub full: bool,
    /// A disc of camera pixels: centre X,Y and radius R (camera pixel units).
    #[arg(long, value_name = "X,Y,R")]
    pub disc: Option<String>,
    /// Camera columns X0 <= x < X1 lit.
    #[arg(long, value_name = "X0,X1")]
    pub stripe: Option<String>,
    /// Bucket sessions: a weight per detector channel, e.g. n=1,e=0.5.
    #[arg(long, value_name = "NAME=W,...")]
    pub weights: Option<String>,
    /// A camera-sized light image (.png or .npy), sent as it is.
    #[arg(long, value_name = "FILE")]
    pub light: Option<PathBuf>,
    /// Image format of the result [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Args)]
#[command(group(clap::ArgGroup::new("pattern_source").required(true).args(["pattern_index", "pattern"])))]
pub struct PrimalArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
    /// A measured pattern of the session (0-based): the server also scores the prediction
    /// against the measured frame.
    #[arg(long, value_name = "I")]
    pub pattern_index: Option<u64>,
    /// Any projector-sized pattern image (.png or .npy), sent as it is.
    #[arg(long, value_name = "FILE")]
    pub pattern: Option<PathBuf>,
    /// Image format of the result [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Args)]
pub struct NormalsArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
    /// png (an RGB normal map) or npy [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Args)]
pub struct CancelArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
}

#[derive(Debug, Clone, Args)]
pub struct PatternsArgs {
    #[command(flatten)]
    pub spec: SpecSource,
    /// First frame index.
    #[arg(long, default_value_t = 0)]
    pub first: u64,
    /// Number of frames to write.
    #[arg(long, default_value_t = 16)]
    pub count: u64,
    /// Output directory (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
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
    let spools = SpoolDir::new(cli.spool.clone().unwrap_or_else(spool::default_root));
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
        Command::Acquire(a) => acquire_cmd(server, &spools, a).await,
    }
}

fn parse_metadata(items: &[String]) -> anyhow::Result<BTreeMap<String, String>> {
    items
        .iter()
        .map(|kv| {
            let (k, v) = kv
                .split_once('=')
                .with_context(|| format!("--metadata {kv:?}: expected KEY=VALUE"))?;
            anyhow::ensure!(!k.trim().is_empty(), "--metadata {kv:?}: empty key");
            Ok((k.trim().to_string(), v.to_string()))
        })
        .collect()
}

fn parse_params(params: Option<&str>) -> anyhow::Result<Value> {
    match params {
        None => Ok(json!({})),
        Some(text) => {
            let v: Value = serde_json::from_str(text)
                .with_context(|| format!("--params {text:?}: not valid JSON"))?;
            anyhow::ensure!(
                v.is_object(),
                "--params must be a JSON object like '{{\"lambda\": 0.1}}', got {v}"
            );
            Ok(v)
        }
    }
}

fn generated_session_id() -> String {
    let ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis())
        .unwrap_or(0);
    format!("sim-{ms}-{:08x}", rand::random::<u32>())
}

fn spec_summary(spec: &PatternSpec) -> String {
    format!(
        "{} {}x{}, {} patterns, seed {}",
        spec.family().name(),
        spec.width(),
        spec.height(),
        spec.count(),
        spec.seed()
    )
}

fn spec_json(spec: &PatternSpec) -> Value {
    serde_json::to_value(spec).expect("spec serialises")
}

fn upload_text(r: &DrainReport, spooled_before: u64) -> String {
    let mut s = format!(
        "spooled {} rows of session {} ({} were spooled by an earlier run); uploaded in {:.2} s: {} rows sent",
        r.spooled_rows, r.session_id, spooled_before, r.seconds, r.rows_sent
    );
    if r.resumes > 0 {
        s.push_str(&format!(", resumed {} time(s)", r.resumes));
    }
    s.push_str(&format!(
        "; server has {}/{} rows{}\n",
        r.committed_rows,
        r.expected_rows,
        if r.removed { "; spool cleared" } else { "" }
    ));
    s
}

/// Rows `start..end` of a session, made on demand (from memory, or rendered by a simulator).
pub type RowsFn<'a> = dyn Fn(u64, u64) -> anyhow::Result<SampleBuf> + Sync + 'a;

/// Spool writes of camera frames hold at most this many bytes (whatever --batch-rows says).
const MAX_BATCH_BYTES: usize = 8 << 20;

/// Spools `values` (rows x channels, every row of the session from row 0) for `session` and
/// uploads them; see [`spool_and_upload_rows`].
#[allow(clippy::too_many_arguments)]
async fn spool_and_upload(
    server: &str,
    spools: &SpoolDir,
    session: &NewSession,
    finish: bool,
    values: &[f64],
    batch_rows: u64,
    frame_rate: Option<f64>,
    opts: &UploadOptions,
) -> anyhow::Result<(DrainReport, u64)> {
    let ch = session.channel_count() as usize;
    let total = (values.len() / ch.max(1)) as u64;
    let rows = |start: u64, end: u64| {
        Ok(SampleBuf::F64(
            values[start as usize * ch..end as usize * ch].to_vec(),
        ))
    };
    spool_and_upload_rows(
        server, spools, session, finish, total, &rows, batch_rows, frame_rate, opts,
    )
    .await
}

/// Spools rows `0..total` of `session` (made by `rows`, in the session's sample format) and
/// uploads them: rows an earlier run already spooled are checked to be the same (byte for byte)
/// and not written again; a background task drains the spool as batches of `batch_rows` land
/// (camera frames: at most 8 MiB a batch), paced at `frame_rate` rows per second if given.
/// Returns the drain report and the rows spooled before.
#[allow(clippy::too_many_arguments)]
async fn spool_and_upload_rows(
    server: &str,
    spools: &SpoolDir,
    session: &NewSession,
    finish: bool,
    total: u64,
    rows: &RowsFn<'_>,
    batch_rows: u64,
    frame_rate: Option<f64>,
    opts: &UploadOptions,
) -> anyhow::Result<(DrainReport, u64)> {
    let id = &session.session_id;
    let spool = Arc::new(spools.create_or_open(session, finish)?);
    let row_bytes = spool.manifest().row_bytes();
    let have = spool.rows();
    anyhow::ensure!(
        have <= total,
        "the spool {} already holds {have} rows of session {id}, more than the {total} given now",
        spool.dir().display()
    );
    // The rows an earlier run spooled must be the ones given now.
    let base = spool.base_row();
    let step = (MAX_BATCH_BYTES / row_bytes).max(1) as u64;
    let mut row = base;
    while row < have {
        let end = (row + step).min(have);
        let held = spool.read_bytes(row, end)?;
        let given = rows(row, end)?.as_samples().encode();
        if let Some(i) = held.iter().zip(&given).position(|(a, b)| a != b) {
            bail!(
                "the spool {} holds different values for row {} of session {id} than the ones given now; \
                 upload the spooled session first (`helmholtz spool upload {id}`) or use another session id",
                spool.dir().display(),
                row + (i / row_bytes) as u64
            );
        }
        row = end;
    }
    if have < total {
        spool.unseal()?;
    }
    let batch_rows = if session.camera.is_some() {
        batch_rows.clamp(1, step)
    } else {
        batch_rows.max(1)
    };
    let drainer = tokio::spawn({
        let (spool, server, opts) = (spool.clone(), server.to_string(), opts.clone());
        async move { spool::drain(&server, spool, &opts, true).await }
    });
    let produce = async {
        let started = Instant::now();
        let mut next = have;
        while next < total {
            let end = (next + batch_rows).min(total);
            if let Some(rate) = frame_rate {
                // The batch is complete when its last pattern has been shown.
                let due = started + Duration::from_secs_f64((end - have) as f64 / rate);
                tokio::time::sleep_until(due.into()).await;
            }
            let batch = rows(next, end)?;
            let s = spool.clone();
            tokio::task::spawn_blocking(move || s.append_samples(batch.as_samples()))
                .await
                .context("spool writer panicked")??;
            next = end;
        }
        spool.seal()
    };
    if let Err(e) = produce.await {
        drainer.abort();
        return Err(e.context(format!(
            "spooling session {id} stopped at row {}; the rows spooled so far stay in {}",
            spool.rows(),
            spool.dir().display()
        )));
    }
    let report = drainer.await.context("upload task panicked")??;
    Ok((report, have))
}

fn recon_text(r: &Reconstruction) -> String {
    let mut s = format!(
        "reconstruction {} ({}) of session {}: {}",
        r.id, r.method, r.session_id, r.state
    );
    if r.is_terminal() {
        s.push_str(&format!(", {} rows, {:.2} s", r.rows, r.seconds));
    } else {
        s.push_str(&format!(" ({:.0}%)", r.progress * 100.0));
    }
    if let Some(e) = &r.error {
        s.push_str(&format!("\n  error: {e}"));
    }
    if let Some(obj) = r.report.as_object() {
        let figures: Vec<String> = ["psnr_db", "psnr", "ssim", "iterations"]
            .iter()
            .filter_map(|k| obj.get(*k).map(|v| format!("{k} {v}")))
            .collect();
        if !figures.is_empty() {
            s.push_str(&format!("\n  {}", figures.join(", ")));
        }
    }
    s.push('\n');
    s
}

fn timeout_of(secs: f64) -> anyhow::Result<Duration> {
    anyhow::ensure!(
        secs >= 0.0 && secs.is_finite(),
        "--timeout must be >= 0 seconds"
    );
    Ok(Duration::from_secs_f64(secs))
}

fn output_format(format: Option<ImageFormat>, out: &Path) -> ImageFormat {
    format
        .or_else(|| ImageFormat::from_path(out))
        .unwrap_or(ImageFormat::Png)
}

/// After a reconstruction was requested: wait and save as the flags say.
async fn finish_reconstruction(
    server: &str,
    rec: Reconstruction,
    result: &ResultArgs,
    progress: bool,
    json_out: &mut serde_json::Map<String, Value>,
    text: &mut String,
) -> anyhow::Result<()> {
    let rec = if result.wait || result.out.is_some() {
        let rec =
            rest::wait_reconstruction_with(server, rec.id, timeout_of(result.timeout)?, progress)
                .await?;
        if !rec.is_done() {
            json_out.insert("reconstruction".into(), serde_json::to_value(&rec)?);
            bail!(
                "reconstruction {} {}: {}",
                rec.id,
                rec.state,
                rec.error.as_deref().unwrap_or("no error message")
            );
        }
        rec
    } else {
        rec
    };
    text.push_str(&recon_text(&rec));
    json_out.insert("reconstruction".into(), serde_json::to_value(&rec)?);
    if let Some(out) = &result.out {
        let format = output_format(result.format, out);
        let report = rest::fetch(
            server,
            &FetchTarget::Reconstruction(rec.id),
            format,
            result.channel.as_deref(),
            out,
        )
        .await?;
        text.push_str(&format!(
            "saved {} ({} bytes)\n",
            out.display(),
            report.bytes
        ));
        json_out.insert("saved".into(), serde_json::to_value(&report)?);
    }
    Ok(())
}

fn write_values(path: &Path, names: &[String], rows: usize, values: &[f64]) -> anyhow::Result<()> {
    let bytes = match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("npy") => measurements::to_npy_f64(rows, names.len(), values),
        Some("csv") | Some("txt") => measurements::to_csv(names, values).into_bytes(),
        _ => bail!(
            "--values-out {}: use a .csv or .npy file name",
            path.display()
        ),
    };
    rest::write_atomically(path, &bytes)
}

fn sim_progress(len: u64, wanted: bool) -> ProgressBar {
    if !wanted {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
    bar.set_style(
        ProgressStyle::with_template("{prefix:>10} [{bar:40.yellow/blue}] {human_pos}/{human_len} patterns {per_sec} eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix("simulating");
    bar
}

/// `values` scaled to [0, 1] by their maximum, as an 8-bit PNG.
fn normalised_png(width: u32, height: u32, values: &[f64]) -> anyhow::Result<Vec<u8>> {
    let max = values.iter().copied().fold(0.0f64, f64::max);
    let pixels = values
        .iter()
        .map(|&v| if max > 0.0 { (v / max) as f32 } else { 0.0 })
        .collect();
    Target {
        width,
        height,
        pixels,
    }
    .to_png()
}

fn noise_text(names: &[String], noise: &simulate::NoiseReport) -> String {
    let mut text = String::new();
    for (name, ch) in names.iter().zip(&noise.channels) {
        text.push_str(&format!(
            "  {name}: mean signal {:.4}, effective SNR {}{}\n",
            ch.mean_signal,
            if ch.effective_snr_db.is_finite() {
                format!("{:.1} dB", ch.effective_snr_db)
            } else {
                "noiseless".into()
            },
            if ch.saturated > 0 {
                format!(", {} saturated", ch.saturated)
            } else {
                String::new()
            }
        ));
    }
    text
}

async fn simulate_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &SimulateArgs,
    progress: bool,
) -> anyhow::Result<Outcome> {
    let spec = a.patterns.to_spec()?;
    let model = a.noise.model();
    model.validate()?;
    anyhow::ensure!(
        a.noise.gain > 0.0 && a.noise.gain.is_finite(),
        "--gain must be > 0"
    );
    let is_lambert = a.scene == "lambert";
    if is_lambert {
        anyhow::ensure!(
            a.channels == ["bucket"],
            "--channels: with --scene lambert the channels are named by --detectors and --colour"
        );
        anyhow::ensure!(
            spec.width() >= 4 && spec.height() >= 4,
            "--scene lambert needs patterns of at least 4x4 pixels"
        );
        if a.camera.is_some() {
            anyhow::ensure!(
                a.detectors.is_none() && !a.colour && a.channel_gains.is_empty(),
                "--camera replaces bucket detectors: drop --detectors, --colour and --channel-gains"
            );
            anyhow::ensure!(
                a.values_out.is_none(),
                "--values-out writes bucket values; a camera session's frames go to the spool and the server"
            );
        }
    } else {
        anyhow::ensure!(
            a.camera.is_none() && a.detectors.is_none() && !a.colour,
            "--camera, --detectors and --colour need --scene lambert (a scene with a known transport for every direction)"
        );
        anyhow::ensure!(
            !a.channels.is_empty() && a.channels.iter().all(|c| !c.trim().is_empty()),
            "--channels: empty channel name"
        );
    }
    let session_id = a.session_id.clone().unwrap_or_else(generated_session_id);
    anyhow::ensure!(
        upload::valid_session_id(&session_id),
        "--session-id {session_id:?}: use 1-128 of A-Z a-z 0-9 . _ -"
    );
    let params = parse_params(a.result.params.as_deref())?;
    let metadata = parse_metadata(&a.metadata)?;
    if a.offline && (a.reconstruct.is_some() || a.result.out.is_some()) {
        bail!("--offline contacts no server: --reconstruct and --out need one");
    }
    if a.reconstruct.is_none() && (a.result.out.is_some() || a.result.wait) {
        bail!("--wait and --out need --reconstruct METHOD");
    }
    if let Some(rate) = a.frame_rate {
        anyhow::ensure!(
            rate > 0.0 && rate.is_finite(),
            "--frame-rate must be > 0 patterns per second"
        );
    }
    let opts = a.transfer.options(progress)?;
    let mut out = serde_json::Map::new();
    out.insert("session_id".into(), json!(session_id));
    out.insert("spec".into(), spec_json(&spec));
    out.insert("noise_model".into(), serde_json::to_value(&model)?);
    let mut session_metadata = metadata;
    session_metadata.insert("scene".into(), a.scene.clone());
    if is_lambert {
        session_metadata.insert("scene_seed".into(), a.scene_seed.to_string());
    }

    if let Some(camera) = &a.camera {
        let (cw, ch) = lambert::parse_size(camera)?;
        let format = SampleFormat::from(a.frame_format);
        upload::CameraLayout {
            width: cw,
            height: ch,
            format,
        }
        .validate()
        .context("--camera")?;
        anyhow::ensure!(
            a.camera_tilt.is_finite() && a.camera_tilt.abs() < 90.0,
            "--camera-tilt must be within (-90, 90) degrees"
        );
        let scene = helmholtz_sim::Scene::demo(spec.width(), spec.height(), a.scene_seed);
        let rig = helmholtz_sim::Camera::tilted(cw, ch, a.camera_tilt);
        let t0 = Instant::now();
        let sim =
            lambert::FrameSimulator::new(&scene, rig, &spec, a.noise.gain as f64, format, &model)?;
        let stats = sim.stats();
        if let Some(path) = &a.scene_out {
            let seen = sim.view().relight(&vec![1.0; sim.pixels()]);
            rest::write_atomically(path, &normalised_png(spec.width(), spec.height(), &seen)?)?;
        }
        let mut text = format!(
            "simulating {} ({}) with a {cw}x{ch} camera tilted {} deg, {} frames; noiseless pixels: mean {:.4}, max {:.4} (signal units)\n",
            session_id,
            spec_summary(&spec),
            a.camera_tilt,
            format.name(),
            stats.mean,
            stats.max
        );
        if format == SampleFormat::U16 {
            text.push_str(&format!(
                "  u16 counts: {:.3} counts per signal unit\n",
                sim.counts_per_unit()
            ));
            session_metadata.insert(
                "counts_per_unit".into(),
                format!("{}", sim.counts_per_unit()),
            );
        }
        session_metadata.insert("camera_tilt_degrees".into(), a.camera_tilt.to_string());
        out.insert(
            "camera".into(),
            json!({"width": cw, "height": ch, "format": format.name(), "tilt_degrees": a.camera_tilt,
                   "counts_per_unit": sim.counts_per_unit()}),
        );
        out.insert("frame_stats".into(), serde_json::to_value(stats)?);
        let total = spec.count();
        let rows = |start: u64, end: u64| Ok(sim.frames(start, end));
        if a.offline {
            let step = (MAX_BATCH_BYTES / (sim.pixels() * format.bytes())).max(1) as u64;
            let mut next = 0;
            while next < total {
                let end = (next + step).min(total);
                rows(next, end)?;
                next = end;
            }
            let noise = sim.noise_report();
            text.push_str(&noise_text(&["camera".to_string()], &noise));
            out.insert("noise".into(), serde_json::to_value(&noise)?);
            out.insert("simulate_seconds".into(), json!(t0.elapsed().as_secs_f64()));
            return Ok(Outcome {
                json: Value::Object(out),
                text,
            });
        }
        let mut session = NewSession::camera(session_id.clone(), spec.clone(), cw, ch, format)
            .with_rig(a.rig.clone());
        session.metadata = session_metadata;
        if !a.no_ground_truth {
            match sim.ground_truth(upload::MAX_CAMERA_GROUND_TRUTH) {
                Some(t) => session = session.with_ground_truth(spec.width(), spec.height(), t),
                None => text.push_str(&format!(
                    "  no ground truth sent: {} camera pixels x {} pattern pixels exceed {} values\n",
                    sim.pixels(),
                    spec.pixels(),
                    upload::MAX_CAMERA_GROUND_TRUTH
                )),
            }
        }
        let (report, spooled_before) = spool_and_upload_rows(
            server,
            spools,
            &session,
            true,
            total,
            &rows,
            a.batch_rows,
            a.frame_rate,
            &opts,
        )
        .await?;
        let noise = sim.noise_report();
        if spooled_before == 0 {
            text.push_str(&noise_text(&["camera".to_string()], &noise));
            out.insert("noise".into(), serde_json::to_value(&noise)?);
        }
        out.insert("simulate_seconds".into(), json!(t0.elapsed().as_secs_f64()));
        return finish_simulated_upload(
            server,
            spools,
            a,
            &session_id,
            report,
            spooled_before,
            &params,
            progress,
            out,
            text,
        )
        .await;
    }

    // Bucket detectors: names, directions and one transport per channel.
    let (names, directions, mut transports, ground_truth) = if is_lambert {
        let plan = lambert::detector_plan(a.detectors.as_deref(), a.detector_elevation, a.colour)?;
        let scene = helmholtz_sim::Scene::demo(spec.width(), spec.height(), a.scene_seed);
        let transports = lambert::plan_transports(&scene, &plan, a.noise.gain as f64);
        (plan.names, plan.directions, transports, None)
    } else {
        let scene = Target::load(&a.scene, spec.width(), spec.height())?;
        let transport = scene.transport(a.noise.gain);
        if let Some(path) = &a.scene_out {
            rest::write_atomically(path, &scene.to_png()?)?;
        }
        (
            a.channels.clone(),
            Vec::new(),
            vec![transport.clone(); a.channels.len()],
            Some(transport),
        )
    };
    if !a.channel_gains.is_empty() {
        anyhow::ensure!(
            a.channel_gains.len() == names.len(),
            "--channel-gains has {} values for {} channels",
            a.channel_gains.len(),
            names.len()
        );
        for (t, g) in transports.iter_mut().zip(&a.channel_gains) {
            t.iter_mut().for_each(|v| *v *= g);
        }
    }
    // Image scenes: the scene (all channels share it); lambert: one dual image per channel.
    let ground_truth = ground_truth.unwrap_or_else(|| {
        if transports.len() == 1 {
            transports[0].clone()
        } else {
            transports.concat()
        }
    });
    if let Some(path) = a.scene_out.as_ref().filter(|_| is_lambert) {
        // The first channel's dual image.
        let first: Vec<f64> = transports[0].iter().map(|&v| v as f64).collect();
        rest::write_atomically(path, &normalised_png(spec.width(), spec.height(), &first)?)?;
    }

    let t0 = Instant::now();
    let bar = sim_progress(spec.count(), progress);
    let sim = {
        let spec = spec.clone();
        let model = model.clone();
        let bar = bar.clone();
        tokio::task::spawn_blocking(move || {
            let refs: Vec<&[f32]> = transports.iter().map(Vec::as_slice).collect();
            simulate::simulate(&spec, &refs, &model, Some(&bar))
        })
        .await
        .context("simulation thread panicked")?
    };
    bar.finish_and_clear();
    let sim_seconds = t0.elapsed().as_secs_f64();

    let mut text = format!(
        "simulated {} ({}) with {} channel(s) in {:.2} s; scene {} {}\n",
        session_id,
        spec_summary(&spec),
        sim.channels,
        sim_seconds,
        a.scene,
        if is_lambert {
            format!("(seed {}) times gain {}", a.scene_seed, a.noise.gain)
        } else {
            format!("scaled to peak {}", a.noise.gain)
        }
    );
    text.push_str(&noise_text(&names, &sim.noise));
    out.insert("channels".into(), json!(names));
    if !directions.is_empty() {
        out.insert("directions".into(), json!(directions));
    }
    out.insert("noise".into(), serde_json::to_value(&sim.noise)?);
    out.insert("simulate_seconds".into(), json!(sim_seconds));
    if let Some(path) = &a.values_out {
        write_values(path, &names, sim.rows, &sim.values)?;
        text.push_str(&format!("wrote values to {}\n", path.display()));
        out.insert("values_out".into(), json!(path));
    }
    if a.offline {
        return Ok(Outcome {
            json: Value::Object(out),
            text,
        });
    }

    let mut session = NewSession::new(session_id.clone(), spec.clone(), names.clone())
        .with_rig(a.rig.clone())
        .with_directions(directions);
    session.metadata = session_metadata;
    if !a.no_ground_truth {
        session = session.with_ground_truth(spec.width(), spec.height(), ground_truth);
    }
    let (report, spooled_before) = spool_and_upload(
        server,
        spools,
        &session,
        true,
        &sim.values,
        a.batch_rows,
        a.frame_rate,
        &opts,
    )
    .await?;
    finish_simulated_upload(
        server,
        spools,
        a,
        &session_id,
        report,
        spooled_before,
        &params,
        progress,
        out,
        text,
    )
    .await
}

/// The end of `simulate` once the rows are spooled and uploaded: report, check the session is
/// finished, reconstruct if asked.
#[allow(clippy::too_many_arguments)]
async fn finish_simulated_upload(
    server: &str,
    spools: &SpoolDir,
    a: &SimulateArgs,
    session_id: &str,
    report: DrainReport,
    spooled_before: u64,
    params: &Value,
    progress: bool,
    mut out: serde_json::Map<String, Value>,
    mut text: String,
) -> anyhow::Result<Outcome> {
    text.push_str(&upload_text(&report, spooled_before));
    out.insert("spool".into(), json!(spools.session_dir(session_id)));
    out.insert("spooled_before".into(), json!(spooled_before));
    out.insert("upload".into(), serde_json::to_value(&report)?);
    anyhow::ensure!(
        report.finished,
        "session {session_id}: {} of {} rows committed but not finished",
        report.committed_rows,
        report.expected_rows
    );
    text.push_str(&format!(
        "session {} finished with {} rows\n",
        session_id, report.committed_rows
    ));
    if let Some(method) = &a.reconstruct {
        let rec = upload::request_reconstruction(server, session_id, method, params).await?;
        finish_reconstruction(server, rec, &a.result, progress, &mut out, &mut text).await?;
    }
    Ok(Outcome {
        json: Value::Object(out),
        text,
    })
}

fn channel_names(given: &[String], m: &Measurements) -> anyhow::Result<Vec<String>> {
    let names = if !given.is_empty() {
        given.to_vec()
    } else if let Some(header) = &m.names {
        header.clone()
    } else if m.channels == 1 {
        vec!["bucket".to_string()]
    } else {
        (0..m.channels).map(|c| format!("ch{c}")).collect()
    };
    anyhow::ensure!(
        names.len() == m.channels,
        "--channels names {} channel(s) ({}) but the file has {} column(s)",
        names.len(),
        names.join(","),
        m.channels
    );
    Ok(names)
}

/// Checks the file's rows against the spec: same count (or fewer with `partial`).
pub fn check_rows(
    file: &Path,
    rows: usize,
    spec: &PatternSpec,
    partial: bool,
) -> anyhow::Result<()> {
    let expected = spec.count();
    if rows as u64 > expected || (!partial && (rows as u64) < expected) {
        bail!(
            "{}: {rows} rows, but the spec declares {expected} patterns (one row per pattern){}",
            file.display(),
            if (rows as u64) < expected {
                "; pass --partial to upload a prefix"
            } else {
                ""
            }
        );
    }
    Ok(())
}

async fn upload_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &UploadArgs,
    progress: bool,
) -> anyhow::Result<Outcome> {
    anyhow::ensure!(
        upload::valid_session_id(&a.session_id),
        "--session-id {:?}: use 1-128 of A-Z a-z 0-9 . _ -",
        a.session_id
    );
    let spec = a.spec.load()?;
    if let Some(frames) = measurements::npy_frames(&a.values)? {
        return upload_frames_cmd(server, spools, a, progress, spec, frames).await;
    }
    let m = measurements::read_measurements(&a.values)?;
    let names = channel_names(&a.channels, &m)?;
    check_rows(&a.values, m.rows, &spec, a.partial)?;
    let mut session =
        NewSession::new(a.session_id.clone(), spec.clone(), names.clone()).with_rig(a.rig.clone());
    session.metadata = parse_metadata(&a.metadata)?;
    let opts = a.transfer.options(progress)?;
    let mut text = format!(
        "session {} ({}; channels {})\n",
        a.session_id,
        spec_summary(&spec),
        names.join(",")
    );
    let (report, spooled_before) = spool_and_upload(
        server,
        spools,
        &session,
        a.finish,
        &m.values,
        a.batch_rows,
        None,
        &opts,
    )
    .await?;
    text.push_str(&upload_text(&report, spooled_before));
    if a.finish {
        anyhow::ensure!(
            report.finished,
            "session {}: {} of {} rows committed, so it cannot be finished",
            a.session_id,
            report.committed_rows,
            report.expected_rows
        );
        text.push_str(&format!(
            "session finished with {} rows\n",
            report.committed_rows
        ));
    }
    let out = json!({
        "session_id": a.session_id,
        "spec": spec_json(&spec),
        "channels": names,
        "file": a.values,
        "spooled_before": spooled_before,
        "upload": report,
        "finished": report.finished,
    });
    Ok(Outcome { json: out, text })
}

/// `helmholtz upload` of a camera rig's frames (a 3-D NPY file): a camera session, spooled and
/// uploaded batch by batch straight from the file.
async fn upload_frames_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &UploadArgs,
    progress: bool,
    spec: PatternSpec,
    frames: measurements::NpyFrames,
) -> anyhow::Result<Outcome> {
    anyhow::ensure!(
        a.channels.is_empty(),
        "--channels does not apply to camera frames ({} is an NPY of shape ({}, {}, {}))",
        a.values.display(),
        frames.rows,
        frames.height,
        frames.width
    );
    check_rows(&a.values, frames.rows as usize, &spec, a.partial)?;
    let mut session = NewSession::camera(
        a.session_id.clone(),
        spec.clone(),
        frames.width,
        frames.height,
        frames.format,
    )
    .with_rig(a.rig.clone());
    session.metadata = parse_metadata(&a.metadata)?;
    session.validate()?;
    let opts = a.transfer.options(progress)?;
    let rows = |start: u64, end: u64| frames.read(start, end);
    let (report, spooled_before) = spool_and_upload_rows(
        server,
        spools,
        &session,
        a.finish,
        frames.rows,
        &rows,
        a.batch_rows,
        None,
        &opts,
    )
    .await?;
    let mut text = format!(
        "session {} ({}; camera {}x{} {:?} frames)\n",
        a.session_id,
        spec_summary(&spec),
        frames.width,
        frames.height,
        frames.format
    );
    text.push_str(&upload_text(&report, spooled_before));
    if a.finish {
        anyhow::ensure!(
            report.finished,
            "session {}: {} of {} rows committed, so it cannot be finished",
            a.session_id,
            report.committed_rows,
            report.expected_rows
        );
        text.push_str(&format!(
            "session finished with {} frames\n",
            report.committed_rows
        ));
    }
    let out = json!({
        "session_id": a.session_id,
        "spec": spec_json(&spec),
        "camera": {"width": frames.width, "height": frames.height},
        "file": a.values,
        "spooled_before": spooled_before,
        "upload": report,
        "finished": report.finished,
    });
    Ok(Outcome { json: out, text })
}

async fn status_cmd(server: &str, a: &StatusArgs) -> anyhow::Result<Outcome> {
    match &a.session_id {
        None => {
            let sessions = rest::list_sessions(server).await?;
            let mut text = if sessions.is_empty() {
                "no sessions\n".to_string()
            } else {
                String::new()
            };
            for s in &sessions {
                text.push_str(&format!(
                    "{:<32} {:<8} {:>9}/{:<9} rows  {}{}\n",
                    s.id,
                    s.state,
                    s.committed_rows,
                    s.expected_rows,
                    s.patterns
                        .get("family")
                        .and_then(Value::as_str)
                        .unwrap_or("?"),
                    s.latest_reconstruction
                        .map(|r| format!("  latest reconstruction {r}"))
                        .unwrap_or_default()
                ));
            }
            Ok(Outcome {
                json: json!({ "sessions": sessions }),
                text,
            })
        }
        Some(id) => {
            let s = rest::get_session(server, id).await?;
            let mut text = format!(
                "session {} ({}): {}, {}/{} rows committed ({:.1}%)\n  rig {:?}, channels {}, ground truth: {}\n  patterns {}\n",
                s.id,
                s.state,
                if s.state == "finished" {
                    "finished"
                } else {
                    "accepting rows"
                },
                s.committed_rows,
                s.expected_rows,
                if s.expected_rows > 0 {
                    100.0 * s.committed_rows as f64 / s.expected_rows as f64
                } else {
                    0.0
                },
                s.rig,
                s.channels.join(","),
                if s.has_ground_truth { "yes" } else { "no" },
                s.patterns
            );
            let mut out = json!({ "session": s });
            if let Some(rid) = s.latest_reconstruction {
                let r = rest::get_reconstruction(server, rid).await?;
                text.push_str("latest ");
                text.push_str(&recon_text(&r));
                out["latest_reconstruction"] = serde_json::to_value(&r)?;
            } else {
                text.push_str("no reconstructions yet\n");
            }
            Ok(Outcome { json: out, text })
        }
    }
}

/// One line of rig output: `channels` finite numbers; `None` for a blank or comment line.
fn parse_row_line(line: &str, number: u64, channels: usize) -> anyhow::Result<Option<Vec<f64>>> {
    let text = line.split('#').next().unwrap_or("").trim();
    if text.is_empty() {
        return Ok(None);
    }
    let fields: Vec<&str> = text
        .split([',', ';', '\t', ' '])
        .map(str::trim)
        .filter(|f| !f.is_empty())
        .collect();
    anyhow::ensure!(
        fields.len() == channels,
        "stdin line {number}: {} value(s), expected {channels} (one per channel)",
        fields.len()
    );
    fields
        .iter()
        .enumerate()
        .map(|(c, f)| {
            let v: f64 = f.parse().map_err(|_| {
                anyhow::anyhow!(
                    "stdin line {number}, column {}: {f:?} is not a number",
                    c + 1
                )
            })?;
            anyhow::ensure!(
                v.is_finite(),
                "stdin line {number}, column {}: {f:?} is not a finite number",
                c + 1
            );
            Ok(v)
        })
        .collect::<anyhow::Result<Vec<f64>>>()
        .map(Some)
}

async fn acquire_cmd(server: &str, spools: &SpoolDir, a: &AcquireArgs) -> anyhow::Result<Outcome> {
    use tokio::io::AsyncBufReadExt;
    anyhow::ensure!(
        upload::valid_session_id(&a.session_id),
        "--session-id {:?}: use 1-128 of A-Z a-z 0-9 . _ -",
        a.session_id
    );
    anyhow::ensure!(
        !a.channels.is_empty() && a.channels.iter().all(|c| !c.trim().is_empty()),
        "--channels: empty channel name"
    );
    let spec = a.spec.load()?;
    let opts = a.transfer.options(false)?;
    let mut session = NewSession::new(a.session_id.clone(), spec.clone(), a.channels.clone())
        .with_rig(a.rig.clone());
    session.metadata = parse_metadata(&a.metadata)?;
    let ch = a.channels.len();
    let spool = Arc::new(spools.create_or_open(&session, a.finish)?);
    let first_row = acquire_start_row(server, &spool, a.start_row).await?;
    let spooled_before = spool.rows() - spool.base_row();
    spool.unseal()?;
    let drainer = tokio::spawn({
        let (spool, server, opts) = (spool.clone(), server.to_string(), opts.clone());
        async move { spool::drain(&server, spool, &opts, true).await }
    });
    let flush_after = Duration::from_millis(a.flush_ms);
    let produce = async {
        let mut lines = tokio::io::BufReader::new(tokio::io::stdin()).lines();
        let mut pending: Vec<f64> = Vec::new();
        let mut oldest: Option<tokio::time::Instant> = None;
        let mut number = 0u64;
        let flush = |pending: &mut Vec<f64>| {
            let batch = std::mem::take(pending);
            let s = spool.clone();
            async move {
                if !batch.is_empty() {
                    tokio::task::spawn_blocking(move || s.append(&batch))
                        .await
                        .context("spool writer panicked")??;
                }
                anyhow::Ok(())
            }
        };
        loop {
            let next = match oldest {
                Some(t) => {
                    match tokio::time::timeout_at(t + flush_after, lines.next_line()).await {
                        Ok(line) => line,
                        Err(_) => {
                            flush(&mut pending).await?;
                            oldest = None;
                            continue;
                        }
                    }
                }
                None => lines.next_line().await,
            };
            let Some(line) = next.context("reading stdin")? else {
                break;
            };
            number += 1;
            let row = match parse_row_line(&line, number, ch) {
                Ok(Some(row)) => row,
                Ok(None) => continue,
                Err(e) => {
                    // The rows before the bad line are measured data: keep them.
                    flush(&mut pending).await?;
                    return Err(e);
                }
            };
            pending.extend(row);
            oldest.get_or_insert_with(tokio::time::Instant::now);
            if (pending.len() / ch) as u64 >= a.batch_rows {
                flush(&mut pending).await?;
                oldest = None;
            }
        }
        flush(&mut pending).await?;
        spool.seal()
    };
    if let Err(e) = produce.await {
        drainer.abort();
        return Err(e.context(format!(
            "acquisition of session {} stopped with {} rows spooled in {} (uploaded by `helmholtz spool upload`; \
             a re-run continues after them)",
            a.session_id,
            spool.rows(),
            spool.dir().display()
        )));
    }
    let report = drainer.await.context("upload task panicked")??;
    let mut text = format!(
        "session {} ({}; channels {}); rows on stdin from row {first_row}\n",
        a.session_id,
        spec_summary(&spec),
        a.channels.join(",")
    );
    text.push_str(&upload_text(&report, spooled_before));
    if a.finish {
        anyhow::ensure!(
            report.finished,
            "session {}: {} of {} rows in, so it cannot be finished; run acquire again with the missing rows",
            a.session_id,
            report.committed_rows,
            report.expected_rows
        );
        text.push_str(&format!(
            "session finished with {} rows\n",
            report.committed_rows
        ));
    }
    Ok(Outcome {
        json: json!({
            "session_id": a.session_id,
            "spec": spec_json(&spec),
            "channels": a.channels,
            "spooled_before": spooled_before,
            "first_row": first_row,
            "upload": report,
            "finished": report.finished,
        }),
        text,
    })
}

/// Where the rows `acquire` reads on stdin go: the pattern index of the first one. Rows are
/// never renumbered silently: a spool holding rows continues after them; an empty one continues
/// at the server's committed count (or `--start-row`). Refused when stdin's rows cannot be
/// aligned with what the spool and the server hold.
async fn acquire_start_row(
    server: &str,
    spool: &spool::Spool,
    given: Option<u64>,
) -> anyhow::Result<u64> {
    let id = spool.session_id();
    let server_rows = match spool::probe_status(server, id).await {
        Ok(Some(s)) if s.state == helmholtz_proto::v1::SessionState::Finished as i32 => bail!(
            "session {id} is finished with {} rows: it takes no more rows, so nothing was read from stdin \
             (acquire into a new --session-id){}",
            s.committed_rows,
            if spool.is_empty() {
                String::new()
            } else {
                format!(
                    "; the spool {} still holds {} unsent row(s), kept",
                    spool.dir().display(),
                    spool.rows() - spool.base_row()
                )
            }
        ),
        Ok(s) => Ok(s.map_or(0, |s| s.committed_rows)),
        Err(e) => Err(e),
    };
    if !spool.is_empty() {
        let next = spool.rows();
        if let Some(g) = given.filter(|g| *g != next) {
            bail!(
                "--start-row {g}: the spool {} holds unsent rows of session {id} up to row {next}, so the next \
                 row on stdin is row {next}; upload them first (`helmholtz spool upload {id}`) or give --start-row {next}",
                spool.dir().display()
            );
        }
        if let Ok(c) = server_rows
            && c > next
        {
            bail!(
                "session {id}: the server holds {c} rows but the spool {} ends at row {next}; the rows on stdin \
                 cannot be aligned (another writer added rows?). Upload the spool first (`helmholtz spool upload {id}`)",
                spool.dir().display()
            );
        }
        return Ok(next);
    }
    let row = match (given, &server_rows) {
        (Some(g), Ok(c)) if g > *c => bail!(
            "--start-row {g}: session {id} holds {c} rows on the server, so row {g} would leave a gap; \
             stdin must continue at row {c} or earlier (rows before {c} are compared with the stored ones)"
        ),
        (Some(g), _) => g,
        (None, Ok(c)) => *c,
        (None, Err(e)) => bail!(
            "session {id}: cannot ask the server where the session's rows continue ({e}); nothing was read \
             from stdin. Start again when the server is reachable, or give --start-row N (the pattern index \
             of stdin's first row; 0 for a new session)"
        ),
    };
    spool.start_at(row)?;
    Ok(row)
}

/// One session's line of `helmholtz spool status`.
#[derive(Debug, serde::Serialize)]
struct SpoolEntry {
    session_id: String,
    #[serde(flatten)]
    info: Option<spool::SpoolInfo>,
    /// The server's committed count now (None if unreachable).
    committed_rows: Option<u64>,
    /// Spooled rows not yet confirmed stored on the server with the spool's bytes.
    pending_rows: Option<u64>,
    /// spooling (another process is writing or uploading it), pending, incomplete (its producer
    /// stopped before every row was measured), uploaded (every spooled row committed).
    status: String,
    server_error: Option<String>,
    error: Option<String>,
}

fn spool_ids(spools: &SpoolDir, given: &[String]) -> anyhow::Result<Vec<String>> {
    if given.is_empty() {
        spools.sessions()
    } else {
        Ok(given.to_vec())
    }
}

async fn spool_status_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &SpoolStatusArgs,
) -> anyhow::Result<Outcome> {
    let mut entries = Vec::new();
    for id in spool_ids(spools, &a.session_ids)? {
        let mut entry = SpoolEntry {
            session_id: id.clone(),
            info: None,
            committed_rows: None,
            pending_rows: None,
            status: "error".into(),
            server_error: None,
            error: None,
        };
        match spools.inspect(&id) {
            Err(e) => entry.error = Some(format!("{e:#}")),
            Ok(info) => {
                match spool::probe_committed(server, &id).await {
                    Ok(c) => entry.committed_rows = Some(c),
                    Err(e) => entry.server_error = Some(e),
                }
                // Only rows the server confirmed with the spool's bytes count as uploaded; its
                // committed count alone proves nothing about whose rows it holds.
                let confirmed = info
                    .state
                    .confirmed_rows
                    .unwrap_or(0)
                    .min(info.spooled_rows)
                    .max(info.base_row);
                let pending = info.spooled_rows.saturating_sub(confirmed);
                entry.pending_rows = Some(pending);
                entry.status = if info.busy {
                    "spooling"
                } else if pending > 0 {
                    "pending"
                } else if !info.sealed {
                    "incomplete"
                } else {
                    "uploaded"
                }
                .into();
                entry.info = Some(info);
            }
        }
        entries.push(entry);
    }
    let mut text = if entries.is_empty() {
        format!("the spool {} holds no sessions\n", spools.root().display())
    } else {
        format!(
            "spool {}\n{:<32} {:>21} {:>10} {:>10}  status\n",
            spools.root().display(),
            "session",
            "spooled/expected",
            "committed",
            "pending"
        )
    };
    for e in &entries {
        match &e.info {
            None => text.push_str(&format!(
                "{:<32} error: {}\n",
                e.session_id,
                e.error.as_deref().unwrap_or("?")
            )),
            Some(info) => {
                text.push_str(&format!(
                    "{:<32} {:>21} {:>10} {:>10}  {}{}\n",
                    e.session_id,
                    format!("{}/{}", info.spooled_rows, info.expected_rows),
                    e.committed_rows
                        .map(|c| c.to_string())
                        .unwrap_or_else(|| "?".into()),
                    e.pending_rows.unwrap_or(0),
                    e.status,
                    if info.torn_bytes > 0 {
                        format!(
                            " (a torn tail of {} bytes, cut at the next open)",
                            info.torn_bytes
                        )
                    } else {
                        String::new()
                    }
                ));
                if let Some(err) = &info.state.last_error {
                    text.push_str(&format!("    last upload error: {err}\n"));
                }
                if let Some(err) = &e.server_error {
                    text.push_str(&format!("    server not asked: {err}\n"));
                }
            }
        }
    }
    Ok(Outcome {
        json: json!({ "spool": spools.root(), "sessions": entries }),
        text,
    })
}

async fn spool_upload_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &SpoolUploadArgs,
) -> anyhow::Result<Outcome> {
    let opts = a.transfer.options(false)?;
    let mut reports = Vec::new();
    let mut failures = Vec::new();
    let mut text = String::new();
    for id in spool_ids(spools, &a.session_ids)? {
        let result = async {
            let spool = Arc::new(spools.open(&id)?);
            spool::drain(server, spool, &opts, false).await
        }
        .await;
        match result {
            Ok(r) => {
                text.push_str(&format!(
                    "{}: {} rows sent, server has {}/{} rows{}{}\n",
                    id,
                    r.rows_sent,
                    r.committed_rows,
                    r.expected_rows,
                    if r.finished { ", finished" } else { "" },
                    if r.removed {
                        ", spool cleared"
                    } else {
                        ", kept in the spool (its producer has not written every row)"
                    }
                ));
                reports.push(r);
            }
            Err(e) => {
                text.push_str(&format!("{id}: failed: {e:#}\n"));
                failures.push(format!("{id}: {e:#}"));
            }
        }
    }
    if reports.is_empty() && failures.is_empty() {
        text.push_str(&format!(
            "nothing to upload: the spool {} holds no sessions\n",
            spools.root().display()
        ));
    }
    if !failures.is_empty() {
        bail!(
            "{} of {} spooled session(s) not uploaded:\n{}",
            failures.len(),
            failures.len() + reports.len(),
            failures.join("\n")
        );
    }
    Ok(Outcome {
        json: json!({ "spool": spools.root(), "uploaded": reports }),
        text,
    })
}

async fn fetch_cmd(server: &str, a: &FetchArgs) -> anyhow::Result<Outcome> {
    let target = match (&a.reconstruction, &a.session) {
        (Some(id), _) => FetchTarget::Reconstruction(*id),
        (None, Some(s)) => FetchTarget::Session(s.clone()),
        (None, None) => bail!("give --reconstruction ID or --session ID"),
    };
    let format = output_format(a.format, &a.out);
    let report = rest::fetch(server, &target, format, a.channel.as_deref(), &a.out).await?;
    let text = format!(
        "saved {} ({} bytes, {})\n",
        report.path.display(),
        report.bytes,
        format.extension()
    );
    Ok(Outcome {
        json: serde_json::to_value(&report)?,
        text,
    })
}

async fn reconstruct_cmd(
    server: &str,
    a: &ReconstructArgs,
    progress: bool,
) -> anyhow::Result<Outcome> {
    let params = parse_params(a.result.params.as_deref())?;
    let rec = upload::request_reconstruction(server, &a.session_id, &a.method, &params).await?;
    let mut out = serde_json::Map::new();
    let mut text = String::new();
    finish_reconstruction(server, rec, &a.result, progress, &mut out, &mut text).await?;
    Ok(Outcome {
        json: Value::Object(out),
        text,
    })
}

/// `N` comma-separated numbers of flag `flag`.
fn numbers<const N: usize>(text: &str, flag: &str, form: &str) -> anyhow::Result<[f64; N]> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("{flag} {text:?}: expected {form} (numbers)"))?;
    values
        .try_into()
        .map_err(|_| anyhow::anyhow!("{flag} {text:?}: expected {form}"))
}

/// The light `relight` sends, from its flags.
pub fn light_of(a: &RelightArgs) -> anyhow::Result<rest::Light> {
    use rest::Light;
    Ok(if a.full {
        Light::Full
    } else if let Some(d) = &a.disc {
        let [x, y, radius] = numbers::<3>(d, "--disc", "X,Y,R")?;
        Light::Disc { x, y, radius }
    } else if let Some(st) = &a.stripe {
        let [x0, x1] = numbers::<2>(st, "--stripe", "X0,X1")?;
        Light::Stripe { x0, x1 }
    } else if let Some(w) = &a.weights {
        Light::Weights(rest::parse_weights(w)?)
    } else if let Some(path) = &a.light {
        Light::Image(path.clone())
    } else {
        bail!("give one of --full, --disc, --stripe, --weights or --light")
    })
}

/// The pattern `primal` sends, from its flags.
pub fn pattern_of(a: &PrimalArgs) -> anyhow::Result<rest::PatternInput> {
    match (a.pattern_index, &a.pattern) {
        (Some(i), _) => Ok(rest::PatternInput::Index(i)),
        (None, Some(path)) => Ok(rest::PatternInput::Image(path.clone())),
        (None, None) => bail!("give --pattern-index I or --pattern FILE"),
    }
}

fn saved_text(report: &rest::ImageReport) -> String {
    format!(
        "saved {} ({} bytes{})\n",
        report.path.display(),
        report.bytes,
        report
            .content_type
            .as_deref()
            .map(|c| format!(", {c}"))
            .unwrap_or_default()
    )
}

async fn relight_cmd(server: &str, a: &RelightArgs) -> anyhow::Result<Outcome> {
    let light = light_of(a)?;
    let format = output_format(a.format, &a.out);
    let report = rest::relight(server, a.reconstruction, &light, format, &a.out).await?;
    Ok(Outcome {
        text: saved_text(&report),
        json: serde_json::to_value(&report)?,
    })
}

async fn primal_cmd(server: &str, a: &PrimalArgs) -> anyhow::Result<Outcome> {
    let pattern = pattern_of(a)?;
    let format = output_format(a.format, &a.out);
    let report = rest::primal(server, a.reconstruction, &pattern, format, &a.out).await?;
    let mut text = saved_text(&report);
    if report.relative_error.is_some() || report.psnr_db.is_some() {
        let show = |v: Option<f64>, unit: &str| {
            v.map(|v| format!("{v:.6}{unit}"))
                .unwrap_or_else(|| "?".to_string())
        };
        text.push_str(&format!(
            "prediction vs the measured frame: relative error {}, PSNR {}\n",
            show(report.relative_error, ""),
            show(report.psnr_db, " dB")
        ));
    }
    Ok(Outcome {
        text,
        json: serde_json::to_value(&report)?,
    })
}

async fn normals_cmd(server: &str, a: &NormalsArgs) -> anyhow::Result<Outcome> {
    let format = output_format(a.format, &a.out);
    let report = rest::normals(server, a.reconstruction, format, &a.out).await?;
    Ok(Outcome {
        text: saved_text(&report),
        json: serde_json::to_value(&report)?,
    })
}

async fn cancel_cmd(server: &str, a: &CancelArgs) -> anyhow::Result<Outcome> {
    let rec = rest::cancel_reconstruction(server, a.reconstruction).await?;
    Ok(Outcome {
        text: recon_text(&rec),
        json: serde_json::to_value(&rec)?,
    })
}

fn patterns_cmd(a: &PatternsArgs) -> anyhow::Result<Outcome> {
    let spec = a.spec.load()?;
    let paths = frames::write_frames(&spec, a.first, a.count, &a.out)?;
    let text = format!(
        "wrote {} frame(s) {}..{} of {} to {}\n",
        paths.len(),
        a.first,
        a.first + a.count,
        spec_summary(&spec),
        a.out.display()
    );
    Ok(Outcome {
        json: json!({ "spec": spec_json(&spec), "dir": a.out, "frames": paths }),
        text,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn cli_definition_is_consistent() {
        Cli::command().debug_assert();
    }

    #[test]
    fn relight_primal_normals_cancel_flags() {
        let light = |args: &[&str]| {
            let mut all = vec!["relight", "--reconstruction", "4", "--out", "r.png"];
            all.extend_from_slice(args);
            let Command::Relight(a) = parse(&all).command else {
                panic!("not relight")
            };
            light_of(&a)
        };
        use rest::Light;
        assert_eq!(light(&["--full"]).unwrap(), Light::Full);
        assert_eq!(
            light(&["--disc", "10,12.5,3"]).unwrap(),
            Light::Disc {
                x: 10.0,
                y: 12.5,
                radius: 3.0
            }
        );
        assert_eq!(
            light(&["--stripe", "0,8"]).unwrap(),
            Light::Stripe { x0: 0.0, x1: 8.0 }
        );
        assert_eq!(
            light(&["--weights", "n=1,e=0.5"]).unwrap(),
            Light::Weights(vec![("n".into(), 1.0), ("e".into(), 0.5)])
        );
        assert_eq!(
            light(&["--light", "l.npy"]).unwrap(),
            Light::Image("l.npy".into())
        );
        assert!(
            light(&["--disc", "1,2"])
                .unwrap_err()
                .to_string()
                .contains("X,Y,R")
        );
        assert!(light(&["--stripe", "a,b"]).is_err());
        // Exactly one light.
        for args in [
            vec!["relight", "--reconstruction", "4", "--out", "r.png"],
            vec![
                "relight",
                "--reconstruction",
                "4",
                "--out",
                "r.png",
                "--full",
                "--stripe",
                "0,1",
            ],
        ] {
            assert!(Cli::try_parse_from(std::iter::once("helmholtz").chain(args)).is_err());
        }
        let Command::Primal(a) = parse(&[
            "primal",
            "--reconstruction",
            "2",
            "--pattern-index",
            "7",
            "--out",
            "p.tiff",
        ])
        .command
        else {
            panic!()
        };
        assert_eq!(pattern_of(&a).unwrap(), rest::PatternInput::Index(7));
        assert_eq!(output_format(a.format, &a.out), ImageFormat::Tiff);
        assert!(
            Cli::try_parse_from([
                "helmholtz",
                "primal",
                "--reconstruction",
                "2",
                "--out",
                "p.png"
            ])
            .is_err()
        );
        assert!(
            Cli::try_parse_from([
                "helmholtz",
                "primal",
                "--reconstruction",
                "2",
                "--pattern-index",
                "1",
                "--pattern",
                "x.png",
                "--out",
                "p.png"
            ])
            .is_err()
        );
        let Command::Normals(a) =
            parse(&["normals", "--reconstruction", "3", "--out", "n.npy"]).command
        else {
            panic!()
        };
        assert_eq!(output_format(a.format, &a.out), ImageFormat::Npy);
        let Command::Cancel(a) = parse(&["cancel", "--reconstruction", "9"]).command else {
            panic!()
        };
        assert_eq!(a.reconstruction, 9);
    }

    #[tokio::test]
    async fn offline_lambert_rigs_report_their_channels_and_directions() {
        let run_json = |args: &[&str]| {
            let mut all = vec![
                "helmholtz",
                "--json",
                "simulate",
                "--scene",
                "lambert",
                "--offline",
            ];
            all.extend_from_slice(args);
            run(Cli::try_parse_from(all).unwrap())
        };
        let out = run_json(&[
            "--detectors",
            "n,e,s,w",
            "--count",
            "50",
            "--width",
            "16",
            "--height",
            "16",
        ])
        .await
        .unwrap()
        .json;
        assert_eq!(out["channels"], json!(["n", "e", "s", "w"]));
        let dirs: Vec<[f64; 3]> = serde_json::from_value(out["directions"].clone()).unwrap();
        let h = 0.5f64.sqrt();
        let want = [[0.0, -h, h], [h, 0.0, h], [0.0, h, h], [-h, 0.0, h]];
        assert_eq!(dirs.len(), 4);
        for (d, w) in dirs.iter().zip(want) {
            assert!(
                (0..3).all(|i| (d[i] - w[i]).abs() < 1e-12),
                "{d:?} vs {w:?}"
            );
            assert!(
                d[0] == 0.0 || d[1] == 0.0,
                "compass detectors lie exactly on an axis: {d:?}"
            );
        }
        let out = run_json(&[
            "--colour", "--count", "50", "--width", "16", "--height", "16",
        ])
        .await
        .unwrap()
        .json;
        assert_eq!(out["channels"], json!(["r", "g", "b"]));
        assert_eq!(
            out["directions"],
            json!([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
        );
        let out = run_json(&["--count", "50", "--width", "16", "--height", "16"])
            .await
            .unwrap()
            .json;
        assert_eq!(out["channels"], json!(["bucket"]));
        assert_eq!(out["directions"], json!([[0.0, 0.0, 1.0]]));
        let out = run_json(&[
            "--camera",
            "8x6",
            "--frame-format",
            "u16",
            "--family",
            "hadamard",
            "--width",
            "16",
            "--height",
            "16",
        ])
        .await
        .unwrap()
        .json;
        assert_eq!(out["camera"]["format"], "u16");
        assert_eq!(out["noise"]["channels"][0]["saturated"], 0);
        // Bad combinations are refused with the flag named.
        for (args, says) in [
            (
                vec!["--camera", "8x6", "--detectors", "n"],
                "--camera replaces",
            ),
            (vec!["--camera", "300x300"], "65536"),
            (
                vec![
                    "--camera",
                    "8x6",
                    "--frame-format",
                    "u16",
                    "--adc-bits",
                    "12",
                ],
                "--adc-bits",
            ),
            (vec!["--channels", "a,b"], "--channels"),
            (
                vec!["--detectors", "n", "--detector-elevation", "95"],
                "--detector-elevation",
            ),
        ] {
            let mut full = args.clone();
            full.extend(["--family", "hadamard", "--width", "16", "--height", "16"]);
            let e = format!("{:#}", run_json(&full).await.unwrap_err());
            assert!(e.contains(says), "{args:?}: {e}");
        }
    }

    #[test]
    fn lambert_simulation_flags() {
        let Command::Simulate(a) = parse(&[
            "simulate",
            "--scene",
            "lambert",
            "--camera",
            "32x24",
            "--camera-tilt",
            "15",
            "--frame-format",
            "u16",
            "--family",
            "hadamard",
            "--width",
            "32",
            "--height",
            "32",
        ])
        .command
        else {
            panic!()
        };
        assert_eq!(
            lambert::parse_size(a.camera.as_deref().unwrap()).unwrap(),
            (32, 24)
        );
        assert_eq!(
            (a.camera_tilt, SampleFormat::from(a.frame_format)),
            (15.0, SampleFormat::U16)
        );
        let Command::Simulate(a) = parse(&[
            "simulate",
            "--scene",
            "lambert",
            "--detectors",
            "n,e,s,w",
            "--detector-elevation",
            "30",
            "--colour",
            "--count",
            "10",
        ])
        .command
        else {
            panic!()
        };
        assert_eq!(a.detectors.as_deref().unwrap(), ["n", "e", "s", "w"]);
        assert!(a.colour && a.detector_elevation == 30.0);
        let Command::Simulate(a) =
            parse(&["simulate", "--scene", "lambert", "--color", "--count", "10"]).command
        else {
            panic!()
        };
        assert!(a.colour && a.detectors.is_none() && a.camera.is_none());
    }

    fn parse(args: &[&str]) -> Cli {
        Cli::try_parse_from(std::iter::once("helmholtz").chain(args.iter().copied())).unwrap()
    }

    #[test]
    fn simulate_flags_build_specs() {
        let cli = parse(&[
            "simulate",
            "--scene",
            "usaf",
            "--family",
            "hadamard",
            "--width",
            "32",
            "--height",
            "16",
            "--ordering",
            "russian_doll",
            "--seed",
            "3",
            "--photons",
            "1e4",
            "--json",
        ]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        assert!(cli.json);
        let spec = a.patterns.to_spec().unwrap();
        assert_eq!(spec.count(), 2 * 32 * 16);
        assert_eq!(
            spec.family(),
            &Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll
            }
        );
        assert_eq!(a.noise.model().photons, Some(1e4));
        assert_eq!(a.channels, ["bucket"]);

        let cli = parse(&[
            "simulate", "--scene", "camera", "--count", "100", "--fill", "1.5",
        ]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        let e = a.patterns.to_spec().unwrap_err().to_string();
        assert!(e.starts_with("--fill:"), "{e}");

        let cli = parse(&["simulate", "--scene", "camera", "--family", "speckle"]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        assert!(
            a.patterns
                .to_spec()
                .unwrap_err()
                .to_string()
                .contains("--count is required")
        );

        let cli = parse(&[
            "simulate", "--scene", "x", "--family", "raster", "--width", "10", "--height", "7",
            "--block", "3",
        ]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        assert_eq!(a.patterns.to_spec().unwrap().count(), 4 * 3);
        let cli = parse(&[
            "simulate", "--scene", "x", "--family", "raster", "--width", "10", "--height", "7",
            "--block", "3", "--scans", "2",
        ]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        assert_eq!(a.patterns.to_spec().unwrap().count(), 2 * 4 * 3);
        let cli = parse(&[
            "simulate", "--scene", "x", "--family", "raster", "--width", "10", "--height", "7",
            "--block", "3", "--count", "13",
        ]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        let e = a.patterns.to_spec().unwrap_err().to_string();
        assert!(e.starts_with("--count:") && e.contains("scans"), "{e}");
    }

    #[test]
    fn rig_lines_parse_or_say_where_they_are_wrong() {
        assert_eq!(
            parse_row_line(" 1.5, -2 # note", 1, 2).unwrap(),
            Some(vec![1.5, -2.0])
        );
        assert_eq!(parse_row_line("3\t4", 1, 2).unwrap(), Some(vec![3.0, 4.0]));
        assert_eq!(parse_row_line("  # only a comment", 1, 2).unwrap(), None);
        assert_eq!(parse_row_line("", 1, 2).unwrap(), None);
        let e = parse_row_line("1,2,3", 7, 2).unwrap_err().to_string();
        assert!(
            e.contains("line 7") && e.contains("3 value(s), expected 2"),
            "{e}"
        );
        let e = parse_row_line("1,x", 8, 2).unwrap_err().to_string();
        assert!(
            e.contains("line 8, column 2") && e.contains("not a number"),
            "{e}"
        );
        let e = parse_row_line("1,NaN", 9, 2).unwrap_err().to_string();
        assert!(
            e.contains("line 9, column 2") && e.contains("finite"),
            "{e}"
        );
    }

    #[test]
    fn spool_commands_parse() {
        let cli = parse(&[
            "--spool",
            "/tmp/sp",
            "spool",
            "upload",
            "a",
            "b",
            "--retry-for",
            "5",
        ]);
        assert_eq!(cli.spool.as_deref(), Some(Path::new("/tmp/sp")));
        let Command::Spool(SpoolCommand::Upload(a)) = cli.command else {
            panic!()
        };
        assert_eq!(a.session_ids, ["a", "b"]);
        assert_eq!(a.transfer.retry_for, 5.0);
        let cli = parse(&["spool", "status"]);
        let Command::Spool(SpoolCommand::Status(a)) = cli.command else {
            panic!()
        };
        assert!(a.session_ids.is_empty());
        let cli = parse(&["simulate", "--scene", "usaf", "--count", "10"]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        assert_eq!((a.batch_rows, a.frame_rate), (1024, None));
        assert!(
            Cli::try_parse_from(["helmholtz", "simulate", "--scene", "u", "--batch-rows", "0"])
                .is_err()
        );
    }

    #[test]
    fn fetch_needs_exactly_one_target() {
        assert!(Cli::try_parse_from(["helmholtz", "fetch", "--out", "x.png"]).is_err());
        assert!(
            Cli::try_parse_from([
                "helmholtz",
                "fetch",
                "--reconstruction",
                "1",
                "--session",
                "s",
                "--out",
                "x.png"
            ])
            .is_err()
        );
        let cli = parse(&[
            "fetch",
            "--session",
            "s",
            "--out",
            "x.tiff",
            "--server",
            "http://h:1",
        ]);
        assert_eq!(cli.server, "http://h:1");
    }

    #[test]
    fn params_and_metadata() {
        assert_eq!(parse_params(None).unwrap(), json!({}));
        assert_eq!(parse_params(Some(r#"{"a":1}"#)).unwrap(), json!({"a":1}));
        assert!(
            parse_params(Some("[1]"))
                .unwrap_err()
                .to_string()
                .contains("JSON object")
        );
        assert!(
            parse_params(Some("{"))
                .unwrap_err()
                .to_string()
                .contains("not valid JSON")
        );
        let m = parse_metadata(&["lens=50mm".into(), "note=a=b".into()]).unwrap();
        assert_eq!(m["note"], "a=b");
        assert!(parse_metadata(&["novalue".into()]).is_err());
        assert!(upload::valid_session_id(&generated_session_id()));
    }

    #[test]
    fn row_count_checks_name_the_file() {
        let spec: PatternSpec =
            serde_json::from_str(r#"{"family":"raster","width":4,"height":4,"count":16}"#).unwrap();
        let f = Path::new("run7.csv");
        assert!(check_rows(f, 16, &spec, false).is_ok());
        let e = check_rows(f, 15, &spec, false).unwrap_err().to_string();
        assert!(
            e.contains("run7.csv")
                && e.contains("15 rows")
                && e.contains("16 patterns")
                && e.contains("--partial"),
            "{e}"
        );
        assert!(check_rows(f, 15, &spec, true).is_ok());
        assert!(check_rows(f, 17, &spec, true).is_err());
    }

    #[test]
    fn channel_names_follow_header_or_flags() {
        let m = Measurements {
            rows: 1,
            channels: 2,
            names: Some(vec!["n".into(), "s".into()]),
            values: vec![1.0, 2.0],
        };
        assert_eq!(channel_names(&[], &m).unwrap(), ["n", "s"]);
        assert_eq!(
            channel_names(&["a".into(), "b".into()], &m).unwrap(),
            ["a", "b"]
        );
        assert!(channel_names(&["a".into()], &m).is_err());
        let m = Measurements { names: None, ..m };
        assert_eq!(channel_names(&[], &m).unwrap(), ["ch0", "ch1"]);
    }
}
