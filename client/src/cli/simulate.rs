//! `helmholtz simulate`: a simulated rig measuring a known scene, spooled and uploaded.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use helmholtz_sim::scene::{self, Scene, Target};
use helmholtz_sim::simulate::lambert;
use helmholtz_sim::simulate::{self, NoiseModel};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde_json::{Value, json};

use crate::measurements;
use crate::rest;
use crate::spool::{DrainReport, SpoolDir};
use crate::upload::{self, NewSession, SampleFormat};

use super::Outcome;
use super::adaptive::{
    AdaptiveArg, AdaptiveRun, ErrorEstimateArg, FramesArg, adaptive_spec, measure_batch,
    simulate_adaptive,
};
use super::args::{
    FrameFormatArg, PatternArgs, ResultArgs, TransferArgs, parse_metadata, parse_params, spec_json,
    spec_summary,
};
use super::reconstruct::finish_reconstruction;
use super::spool::{MAX_BATCH_BYTES, spool_and_upload, spool_and_upload_rows, upload_text};
use crate::adaptive::BatchToMeasure;
use helmholtz_proto::Family;
use helmholtz_proto::wire::SampleBuf;

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

#[derive(Debug, Clone, Args)]
pub struct SimulateArgs {
    /// Target: camera, shapes, usaf (USAF-1951 chart), double-slit, smooth (smooth, low
    /// contrast), text (a page of capitals), or a PNG file (grey or colour,
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
    /// Adaptive acquisition (haar or hadamard): the server chooses the patterns batch by batch
    /// from the values measured so far (gRPC Acquire), and the simulated rig shows each batch's
    /// split pairs as they come. Replaces --family; --width = --height, a power of two; --count
    /// is the frame budget [default: 2 x width x height, the whole basis]. Bucket detectors, or
    /// with --scene lambert --camera a camera rig (hadamard only: the server chooses the pairs
    /// from every camera pixel's values; reconstruct T with --reconstruct transport). Buckets:
    /// the noise model applies to each batch (its seed varies by batch; drift restarts);
    /// camera frames get it frame by frame, as without --adaptive.
    #[arg(long, value_enum, value_name = "BASIS")]
    pub adaptive: Option<AdaptiveArg>,
    /// --adaptive: split pairs per batch (0: the server sizes batches so a DMD at kHz rates
    /// never waits for the next decision).
    #[arg(long, default_value_t = 0, value_name = "PAIRS")]
    pub adaptive_batch: u32,
    /// --adaptive: stop once the server's estimated relative error of the image falls below
    /// this (0: spend the whole budget).
    #[arg(long, default_value_t = 0.0, value_name = "ERROR")]
    pub target_error: f64,
    /// --adaptive: how strongly a measured detail pulls its finer children forward (the spec's
    /// `persistence`, proto/PATTERNS.md) [default: the family's, haar 0.5, hadamard 0].
    #[arg(long, value_name = "BETA")]
    pub persistence: Option<f64>,
    /// --adaptive: what --target-error compares with (the spec's `error_estimate`,
    /// proto/PATTERNS.md): `measured` (the predicted energy of what is not measured plus each
    /// level's measured prediction miss and the noise the pair sums show) or `prediction` (the
    /// predicted energy alone, several times low noise-free and blind to noise).
    #[arg(long, value_enum, default_value_t = ErrorEstimateArg::Measured)]
    pub error_estimate: ErrorEstimateArg,
    /// --adaptive haar: `single` shows every basis function but the first as one frame, its
    /// positive half, the negative half following from the light on its block, which the
    /// server keeps known by splitting whole blocks (the spec's `frames`, proto/PATTERNS.md,
    /// "Single frames"): about half the frames of `pairs` for the same coefficients, each with
    /// about 2.5x the read noise of a pair's; --count is then the frame budget up to
    /// width x height + 1 [default: that].
    #[arg(long, value_enum, default_value_t = FramesArg::Pairs)]
    pub frames: FramesArg,
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

pub(super) fn generated_session_id() -> String {
    let ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis())
        .unwrap_or(0);
    format!("sim-{ms}-{:08x}", rand::random::<u32>())
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

pub(super) fn sim_progress(len: u64, wanted: bool) -> ProgressBar {
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

pub(super) async fn simulate_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &SimulateArgs,
    progress: bool,
) -> anyhow::Result<Outcome> {
    let spec = match a.adaptive {
        Some(kind) => {
            anyhow::ensure!(
                !a.offline && a.frame_rate.is_none() && a.values_out.is_none(),
                "--adaptive runs a rig against a server as fast as it decides: drop --offline, --frame-rate and --values-out"
            );
            anyhow::ensure!(
                a.camera.is_none() || kind == AdaptiveArg::Hadamard,
                "--adaptive haar with --camera: a camera session's transport matrix is reconstructed from Walsh-Hadamard pairs; use --adaptive hadamard"
            );
            let p = &a.patterns;
            let family = Family::adaptive(
                kind == AdaptiveArg::Haar,
                a.adaptive_batch,
                a.target_error,
                a.persistence,
            )
            .with_error_estimate(match a.error_estimate {
                ErrorEstimateArg::Measured => helmholtz_proto::ErrorEstimate::Measured,
                ErrorEstimateArg::Prediction => helmholtz_proto::ErrorEstimate::Prediction,
            })
            .with_frames(match a.frames {
                FramesArg::Pairs => helmholtz_proto::AdaptiveFrames::Pairs,
                FramesArg::Single => helmholtz_proto::AdaptiveFrames::Single,
            });
            adaptive_spec(family, p.width, p.height, p.count, p.seed)?
        }
        None => a.patterns.to_spec()?,
    };
    let model = a.noise.model();
    model.validate()?;
    anyhow::ensure!(
        a.noise.gain > 0.0 && a.noise.gain.is_finite(),
        "--gain must be > 0"
    );
    let is_lambert = a.scene == scene::LAMBERT;
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
        let scene = helmholtz_sim::Relief::demo(spec.width(), spec.height(), a.scene_seed);
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
        if a.adaptive.is_some() {
            let run = AdaptiveRun {
                session,
                opts,
                reconstruct: a.reconstruct.as_deref(),
                params: &params,
                result: &a.result,
                progress,
            };
            let measure = |batch: &BatchToMeasure<'_>| {
                Ok(sim.frames_for(batch.spec, batch.rows.start, batch.rows.end))
            };
            let mut outcome = simulate_adaptive(server, run, measure, out, text).await?;
            if let Value::Object(o) = &mut outcome.json {
                o.insert("noise".into(), serde_json::to_value(sim.noise_report())?);
            }
            return Ok(outcome);
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
    let scene = Scene::load(&a.scene, spec.width(), spec.height(), a.scene_seed)?;
    let (names, directions, mut transports, ground_truth) = match &scene {
        Scene::Relief(relief) => {
            let plan =
                lambert::detector_plan(a.detectors.as_deref(), a.detector_elevation, a.colour)?;
            let transports = lambert::plan_transports(relief, &plan, a.noise.gain as f64);
            (plan.names, plan.directions, transports, None)
        }
        Scene::Flat(target) => {
            let transport = target.transport(a.noise.gain);
            if let Some(path) = &a.scene_out {
                rest::write_atomically(path, &target.to_png()?)?;
            }
            (
                a.channels.clone(),
                Vec::new(),
                vec![transport.clone(); a.channels.len()],
                Some(transport),
            )
        }
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

    // The bucket session as declared (the server scores reconstructions against the ground
    // truth unless --no-ground-truth).
    let mut session = NewSession::new(session_id.clone(), spec.clone(), names.clone())
        .with_rig(a.rig.clone())
        .with_directions(directions.clone());
    session.metadata = session_metadata;
    if !a.no_ground_truth {
        session = session.with_ground_truth(spec.width(), spec.height(), ground_truth);
    }
    if a.adaptive.is_some() {
        out.insert("channels".into(), json!(names));
        let run = AdaptiveRun {
            session,
            opts,
            reconstruct: a.reconstruct.as_deref(),
            params: &params,
            result: &a.result,
            progress,
        };
        let measure = |batch: &BatchToMeasure<'_>| {
            Ok(SampleBuf::F64(measure_batch(batch, &transports, &model)))
        };
        return simulate_adaptive(server, run, measure, out, String::new()).await;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::{Cli, Command, parse, run};
    use clap::Parser;
    use helmholtz_proto::patterns::{Family, HadamardOrdering};

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
}
