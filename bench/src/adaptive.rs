//! `--preset adaptive`: adaptive acquisition (issue 24) against the non-adaptive families, PSNR
//! against the number of frames, in one run.
//!
//! Per scene, size (128x128, 256x256), noise (none; read noise) and frame count (1, 2, 5, 10,
//! 25 % of `k`, always counted in **frames**: a split pair is 2):
//! - `adaptive_haar` and `adaptive_hadamard`: a simulated rig runs the session through the
//!   planner (`helmholtz_recon::adaptive`, automatic batches, two outstanding), then the session is
//!   reconstructed by `direct` (the zero-filled inverse: the adaptive scheme's own image) and by
//!   `auto` on the same data; and `adaptive_haar` with single frames (`frames: "single"`,
//!   PATTERNS.md "Single frames": one frame a basis function but the first, the planner
//!   splitting whole blocks), the same way;
//! - `bernoulli` (fill 1/2) and `hadamard` in the Russian-doll ordering at the same frame count,
//!   reconstructed by `auto` (the service's best non-adaptive answer).
//!
//! The rig's frames: `y+ - y- = g_n c_n` and `y+ + y- = <support, t>` from the exact transform
//! of the scene (the values `<P, t>` of the generated patterns, which the tests check), plus, for
//! the noisy rows, Gaussian read noise of the same absolute standard deviation on every frame of
//! every family: `sigma = 10^(-30/20) (sum t) / 2`, i.e. 30 dB below the bucket of a half-lit
//! pattern (the bench's usual 30 dB convention, made absolute so that a pattern lighting a small
//! support is not given less noise than a half-lit one).
//!
//! Oracle (noise-free, per scene, size and frame count, `k' = frames / 2` coefficients: the
//! split pairs an adaptive session of that many frames measures), in the orthonormal Haar basis
//! of `adaptive_haar` (the recon crate's `Wavelet2d::haar`, Mallat layout = the family's indices)
//! and the Walsh-Hadamard basis of `adaptive_hadamard` (`fwht / W`, natural order):
//! - **best k'**: the `k'` largest true coefficients (mean included), zero elsewhere, inverted:
//!   the best image any scheme measuring `k'` basis functions and reconstructing linearly can
//!   make (for an orthonormal basis the squared error is the energy left out);
//! - **tree**: the planner's rule fed the true coefficients: one at a time, the largest `|c_n|`
//!   among the indices whose parent ([`Basis::parent`]) is taken, root first (a feasible tree,
//!   so between the planner's ideal and the best tree-constrained `k'`);
//! - **capture**: the share of the scene's energy without the mean (`sum over n != 0 of c_n^2`)
//!   in the best-`k'` set, the tree set, and the indices the planner actually measured (its
//!   noise-free and its 30 dB session).
//!
//! Also reported: the planner's decision time per batch (mean and longest, prediction plus
//! selection) against the batch's display time at 20 kHz binary frames, and the planner's memory.
//!
//! `cargo run --release -p helmholtz-bench -- --preset adaptive --out docs` writes
//! docs/benchmarks-adaptive.md and .json; `--sizes 128` and `--scenes camera,relief` narrow it,
//! `--persistence B` runs both planners with that `persistence` instead of their defaults.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context as _;
use helmholtz_proto::{
    AdaptiveFrames, ErrorEstimate, Family, HaarFunction, HadamardOrdering, PatternSpec,
};
use helmholtz_recon::adaptive::{Basis, Planner, StopReason};
use helmholtz_recon::fwht::fwht;
use helmholtz_recon::linop::LinearOperator;
use helmholtz_recon::transforms::wavelet::Wavelet2d;
use helmholtz_recon::{self as recon, Control, MethodConfig, Problem, SliceSource, metrics};
use helmholtz_sim::simulate::random::SplitMix64;
use helmholtz_sim::simulate::{NoiseModel, simulate};
use helmholtz_sim::{Relief, Target};
use serde::Serialize;

use super::machine;

pub struct Options {
    pub out: PathBuf,
    pub sizes: Vec<u32>,
    pub scenes: Vec<String>,
    pub ratios: Vec<f64>,
    /// The planners' `persistence`; `None`: each family's default.
    pub persistence: Option<f64>,
}

impl Options {
    pub fn default_scenes() -> Vec<String> {
        ["camera", "relief", "shapes", "text"]
            .map(String::from)
            .to_vec()
    }
    pub const RATIOS: [f64; 5] = [0.01, 0.02, 0.05, 0.10, 0.25];
}

/// Scenes that are photographs or rendered natural scenes (the 3 dB target applies to them).
const NATURAL: [&str; 2] = ["camera", "relief"];

/// One reconstruction of one acquisition.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub scene: String,
    pub size: u32,
    pub noisy: bool,
    pub ratio: f64,
    pub frames: u64,
    /// `adaptive_haar`, `adaptive_hadamard`, `bernoulli`, `hadamard_rd`.
    pub family: String,
    pub method: String,
    pub psnr_db: f64,
    pub ssim: f64,
    pub seconds: f64,
    pub error: Option<String>,
    /// Adaptive sessions only.
    pub planner: Option<PlannerFigures>,
}

#[derive(Clone, Debug, Serialize)]
pub struct PlannerFigures {
    pub batch_pairs: u64,
    pub batches: u64,
    pub decision_mean_ms: f64,
    pub decision_max_ms: f64,
    /// Display time of one full batch at 20 kHz binary frames.
    pub batch_display_ms: f64,
    pub memory_bytes: usize,
    /// The planner's `measured` estimate of the zero-filled image's relative error (the spec's
    /// default `error_estimate`) ...
    pub estimated_error: Option<f64>,
    /// ... the `prediction` estimate of the same session (replayed with that rule) ...
    pub prediction_estimate: Option<f64>,
    /// ... and the true relative L2 error of the zero-filled image against the scene.
    pub true_error: f64,
    /// The noise of one pair difference the pair sums show (standard deviation, frame units),
    /// against the rig's `sqrt(2) sigma`.
    pub pair_noise: Option<f64>,
    pub drawn_pair_noise: f64,
    pub stop: Option<String>,
}

/// The oracle of one basis for one scene, size and frame count (noise-free; module docs).
#[derive(Clone, Debug, Serialize)]
pub struct OracleRow {
    pub scene: String,
    pub size: u32,
    pub ratio: f64,
    pub frames: u64,
    /// `k' = frames / 2`: the split pairs of an adaptive session of `frames` frames.
    pub coefficients: u64,
    /// `haar` or `hadamard`.
    pub basis: String,
    /// The `k'` largest true coefficients, zero elsewhere.
    pub best_psnr_db: f64,
    /// `auto` on the split pairs of those `k'` coefficients (noise-free).
    pub best_auto_psnr_db: f64,
    /// The planner's tree rule with the true coefficients as its prediction.
    pub tree_psnr_db: f64,
    /// Shares of the energy without the mean (0..1).
    pub best_capture: f64,
    pub tree_capture: f64,
    /// The indices the planner measured in the noise-free session.
    pub planner_capture: f64,
    /// ... and in the session with read noise (30 dB).
    pub planner_capture_noisy: Option<f64>,
}

/// Indices of the `kp` largest `|c_n|` (ties: lower index first).
pub fn best_k(c: &[f64], kp: usize) -> Vec<u32> {
    let mut order: Vec<u32> = (0..c.len() as u32).collect();
    order.sort_by(|&a, &b| {
        c[b as usize]
            .abs()
            .total_cmp(&c[a as usize].abs())
            .then(a.cmp(&b))
    });
    order.truncate(kp);
    order
}

/// The planner's rule with perfect prediction: from the root, repeatedly take the largest `|c_n|`
/// (ties: coarser level, then lower index) among the indices whose parent is taken.
pub fn tree_greedy(c: &[f64], width: u32, basis: Basis, kp: usize) -> Vec<u32> {
    #[derive(PartialEq)]
    struct Key(f64, u32, u32);
    impl Eq for Key {}
    impl PartialOrd for Key {
        fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
            Some(self.cmp(other))
        }
    }
    impl Ord for Key {
        fn cmp(&self, o: &Self) -> std::cmp::Ordering {
            self.0
                .total_cmp(&o.0)
                .then(self.1.cmp(&o.1))
                .then(o.2.cmp(&self.2))
        }
    }
    let k = c.len();
    let mut children = vec![Vec::new(); k];
    for n in 1..k as u32 {
        let p = basis.parent(width, n).expect("not the root");
        children[p as usize].push(n);
    }
    let key = |n: u32| Key(c[n as usize].abs(), basis.level(width, n), n);
    let mut heap = std::collections::BinaryHeap::from([key(0)]);
    let mut taken = Vec::with_capacity(kp);
    while taken.len() < kp {
        let Some(Key(_, _, n)) = heap.pop() else {
            break;
        };
        taken.push(n);
        heap.extend(children[n as usize].iter().map(|&m| key(m)));
    }
    taken
}

/// The best quadtree a rig measuring **one frame per Haar coefficient** could show, fed the true
/// coefficients. A single 0/1 frame (a detail's `P+`) gives `y+`; `y- = S_B - y+` needs the
/// light `S_B` on the detail's block, which is known once every coarser block containing it has
/// all three details measured (then its four quadrant sums follow from its sum and its three
/// details). So the unit of choice is a block split (its three details, three frames), and a
/// block may be split once its parent is: from the root (index 0, shown as all on and all off),
/// repeatedly split the open block whose three details hold the most energy (ties: the larger
/// block, then the lower index), the last split taking only its largest details if the budget
/// ends inside it. Returns `kp` indices (index 0 first).
pub fn haar_block_greedy(c: &[f64], width: u32, kp: usize) -> Vec<u32> {
    #[derive(PartialEq)]
    struct Key(f64, u32, [u32; 3], u32, u32);
    impl Eq for Key {}
    impl PartialOrd for Key {
        fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
            Some(self.cmp(other))
        }
    }
    impl Ord for Key {
        fn cmp(&self, o: &Self) -> std::cmp::Ordering {
            self.0
                .total_cmp(&o.0)
                .then(self.1.cmp(&o.1))
                .then(o.2[0].cmp(&self.2[0]))
        }
    }
    let w = width;
    // Block of side 2^sc at block position (pr, pc): its x, y and diagonal details.
    let block = |sc: u32, pr: u32, pc: u32| {
        let h = w >> sc;
        let d = [pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc];
        let e: f64 = d.iter().map(|&n| c[n as usize] * c[n as usize]).sum();
        Key(e, sc, d, pr, pc)
    };
    let mut taken = vec![0u32];
    let m = w.trailing_zeros();
    let mut heap = std::collections::BinaryHeap::new();
    if m >= 1 {
        heap.push(block(m, 0, 0));
    }
    while taken.len() < kp {
        let Some(Key(_, sc, mut d, pr, pc)) = heap.pop() else {
            break;
        };
        d.sort_by(|&a, &b| c[b as usize].abs().total_cmp(&c[a as usize].abs()));
        for n in d {
            if taken.len() < kp {
                taken.push(n);
            }
        }
        if sc >= 2 {
            for (dr, dc) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                heap.push(block(sc - 1, 2 * pr + dr, 2 * pc + dc));
            }
        }
    }
    taken.truncate(kp.min(c.len()));
    taken
}

/// Share of the energy without the mean in `selected`.
pub fn capture(c: &[f64], selected: &[u32]) -> f64 {
    let total: f64 = c[1..].iter().map(|v| v * v).sum();
    let got: f64 = selected
        .iter()
        .filter(|&&n| n != 0)
        .map(|&n| c[n as usize] * c[n as usize])
        .sum();
    if total > 0.0 { got / total } else { 1.0 }
}

/// The image of the coefficients `selected` (zero elsewhere): the zero-filled inverse.
pub fn zero_filled(c: &[f64], selected: &[u32], width: usize, haar: bool) -> Vec<f32> {
    let mut kept = vec![0.0; c.len()];
    for &n in selected {
        kept[n as usize] = c[n as usize];
    }
    let mut image = vec![0.0; c.len()];
    if haar {
        Wavelet2d::haar(width, width).adjoint(&kept, &mut image);
    } else {
        image.copy_from_slice(&kept);
        fwht(&mut image);
        image.iter_mut().for_each(|v| *v /= width as f64);
    }
    image.iter().map(|&v| v as f32).collect()
}

/// The scene's transport, row-major, values in [0, 1].
pub fn scene(name: &str, size: u32) -> anyhow::Result<Vec<f32>> {
    if name == "relief" {
        // The demo relief seen by a detector up and to the left: shading and cast shadows.
        let d = helmholtz_sim::scene::unit_vector([-0.4, -0.3, 1.0]);
        let t = Relief::demo(size, size, 3).detector_transport(d);
        let max = t.iter().cloned().fold(0.0, f64::max).max(f64::MIN_POSITIVE);
        return Ok(t.iter().map(|&v| (v / max) as f32).collect());
    }
    Ok(Target::load(name, size, size)?.transport(1.0))
}

/// Read noise of every frame: row `i`, detector stream of `seed`.
fn read_noise(sigma: f64, seed: u64, frame: u64) -> f64 {
    if sigma == 0.0 {
        return 0.0;
    }
    sigma * SplitMix64::stream(seed, 24, frame).normal()
}

/// The orthonormal coefficients of the scene in the family's basis (by index) and the gain and
/// support sum of each index's split pair.
pub struct Exact {
    pub coefficients: Vec<f64>,
    /// Summed-area table of t, `(W + 1)^2`.
    integral: Vec<f64>,
    total: f64,
    width: usize,
    haar: bool,
}

impl Exact {
    pub fn new(truth: &[f64], width: usize, haar: bool) -> Exact {
        let k = width * width;
        let mut coefficients = vec![0.0; k];
        if haar {
            Wavelet2d::haar(width, width).apply(truth, &mut coefficients);
        } else {
            coefficients.copy_from_slice(truth);
            fwht(&mut coefficients);
            coefficients.iter_mut().for_each(|c| *c /= width as f64);
        }
        let s = width + 1;
        let mut integral = vec![0.0; s * s];
        for y in 0..width {
            for x in 0..width {
                integral[(y + 1) * s + x + 1] =
                    truth[y * width + x] + integral[y * s + x + 1] + integral[(y + 1) * s + x]
                        - integral[y * s + x];
            }
        }
        Exact {
            coefficients,
            integral,
            total: truth.iter().sum(),
            width,
            haar,
        }
    }

    /// `(y+, y-)` without noise for basis index `n`.
    pub fn pair(&self, n: u32) -> (f64, f64) {
        let w = self.width;
        let (gain, support) = if self.haar {
            let f = HaarFunction::new(w as u32, n);
            let (x0, y0, side) = (f.x0 as usize, f.y0 as usize, f.side() as usize);
            let s = w + 1;
            let at = |x: usize, y: usize| self.integral[y * s + x];
            let sum = at(x0 + side, y0 + side) - at(x0, y0 + side) - at(x0 + side, y0) + at(x0, y0);
            (side as f64, sum)
        } else {
            (w as f64, self.total)
        };
        let diff = gain * self.coefficients[n as usize];
        ((support + diff) / 2.0, (support - diff) / 2.0)
    }
}

struct Session {
    spec: PatternSpec,
    frames: Vec<f64>,
    figures: PlannerFigures,
    /// The planner's prediction-filled image ([`Planner::predicted_image`]).
    predicted: Vec<f32>,
    /// The basis indices measured, in order.
    indices: Vec<u32>,
}

/// One simulated adaptive session of `scene` (as the bench runs it: read noise at 30 dB of a
/// half-lit bucket when `noisy`), for probes (`examples/adaptive_one.rs`): the resolved spec, the
/// frames and the truth.
pub fn probe_session(
    scene_name: &str,
    size: u32,
    ratio: f64,
    noisy: bool,
    family: Family,
) -> anyhow::Result<(PatternSpec, Vec<f64>, Vec<f32>)> {
    let (spec, frames, truth, _) =
        probe_session_at(scene_name, size, ratio, noisy.then_some(30.0), family)?;
    Ok((spec, frames, truth))
}

/// The read noise `snr_db` below a half-lit bucket of the scene `truth`:
/// `10^(-snr_db / 20) (sum t) / 2`, the same on every frame.
pub fn read_noise_sigma(truth: &[f64], snr_db: f64) -> f64 {
    10f64.powf(-snr_db / 20.0) * truth.iter().sum::<f64>() / 2.0
}

/// [`probe_session`] with the read noise `snr_db` below a half-lit bucket (`None`: noise-free):
/// ([`read_noise_sigma`]). Also returns that `sigma`.
pub fn probe_session_at(
    scene_name: &str,
    size: u32,
    ratio: f64,
    snr_db: Option<f64>,
    family: Family,
) -> anyhow::Result<(PatternSpec, Vec<f64>, Vec<f32>, f64)> {
    let truth32 = scene(scene_name, size)?;
    let truth: Vec<f64> = truth32.iter().map(|&v| v as f64).collect();
    let k = (size * size) as u64;
    let frames = ((ratio * k as f64).round() as u64).max(2) & !1;
    let sigma = snr_db.map_or(0.0, |db| read_noise_sigma(&truth, db));
    let s = run_adaptive(family, &truth, size, frames, sigma)?;
    Ok((s.spec, s.frames, truth32, sigma))
}

/// A simulated rig through the planner: the service's loop (poll until none, observe the oldest).
fn run_adaptive(
    family: Family,
    truth: &[f64],
    size: u32,
    frames: u64,
    sigma: f64,
) -> anyhow::Result<Session> {
    let haar = matches!(family, Family::AdaptiveHaar { .. });
    let spec = PatternSpec::new(family.clone(), size, size, frames, 0)?;
    let exact = Exact::new(truth, size as usize, haar);
    let mut planner = Planner::new(&spec, 1)?;
    let mut queue = std::collections::VecDeque::new();
    let mut values = Vec::with_capacity(frames as usize);
    loop {
        while let Some(b) = planner.poll() {
            queue.push_back(b);
        }
        let Some(batch) = queue.pop_front() else {
            break;
        };
        // Two frames an index, or with single frames one (its P+) but index 0's two.
        let mut batch_values = Vec::with_capacity(batch.rows as usize);
        let mut frame = batch.first_row;
        for &n in &batch.indices {
            let (plus, minus) = exact.pair(n);
            batch_values.push(plus + read_noise(sigma, 7, frame));
            frame += 1;
            if !planner.single_frames() || n == 0 {
                batch_values.push(minus + read_noise(sigma, 7, frame));
                frame += 1;
            }
        }
        planner.observe(&batch_values)?;
        values.extend_from_slice(&batch_values);
    }
    let stats = planner.decision_stats();
    let observed = &planner.indices()[..planner.observed_pairs() as usize];
    let image = zero_filled(planner.coefficients(0), observed, size as usize, haar);
    let true_error = (image
        .iter()
        .zip(truth)
        .map(|(&a, &b)| (a as f64 - b).powi(2))
        .sum::<f64>()
        / truth.iter().map(|b| b * b).sum::<f64>())
    .sqrt();
    let prediction = PatternSpec::new(
        family.with_error_estimate(ErrorEstimate::Prediction),
        size,
        size,
        frames,
        0,
    )?;
    let (replayed, _) = helmholtz_recon::adaptive::replay(&prediction, 1, &values)?;
    let figures = PlannerFigures {
        batch_pairs: planner.batch_pairs(),
        batches: stats.batches,
        decision_mean_ms: stats.total.as_secs_f64() * 1e3 / stats.batches.max(1) as f64,
        decision_max_ms: stats.max.as_secs_f64() * 1e3,
        batch_display_ms: if planner.single_frames() { 1.0 } else { 2.0 }
            * planner.batch_pairs() as f64
            * 0.05,
        memory_bytes: planner.memory_bytes(),
        estimated_error: planner.estimated_error(),
        prediction_estimate: replayed.estimated_error(),
        true_error,
        pair_noise: planner.pair_noise(0).map(|(s, _)| s),
        drawn_pair_noise: 2f64.sqrt() * sigma,
        stop: planner.finished().map(|s| match s {
            StopReason::Budget => "budget".into(),
            StopReason::TargetError => "target_error".into(),
        }),
    };
    let predicted = planner
        .predicted_image(0)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let indices = planner.indices().to_vec();
    let spec = spec.with_indices(Arc::from(indices.clone()))?;
    Ok(Session {
        spec,
        frames: values,
        figures,
        predicted,
        indices,
    })
}

pub fn reconstruct(
    spec: &PatternSpec,
    values: &[f64],
    method: &str,
    truth: &[f32],
) -> (f64, f64, f64, Option<String>) {
    reconstruct_with(spec, values, method, &serde_json::Value::Null, truth)
}

/// [`reconstruct`] with `params`.
pub fn reconstruct_with(
    spec: &PatternSpec,
    values: &[f64],
    method: &str,
    params: &serde_json::Value,
    truth: &[f32],
) -> (f64, f64, f64, Option<String>) {
    let problem = Problem {
        spec,
        channels: 1,
        rows: values.len() as u64,
    };
    let config = MethodConfig::parse(method, params).expect("known method");
    let started = Instant::now();
    let r = recon::reconstruct(
        &problem,
        &config,
        &mut SliceSource::new(values, 1, 4096),
        &Control::new(),
    );
    let seconds = started.elapsed().as_secs_f64();
    match r {
        Ok(r) => {
            let image = &r.images[0].data;
            let w = spec.width() as usize;
            (
                metrics::psnr(image, truth),
                metrics::ssim(image, truth, w, w),
                seconds,
                None,
            )
        }
        Err(e) => (f64::NAN, f64::NAN, seconds, Some(e.to_string())),
    }
}

pub fn run(opts: &Options) -> anyhow::Result<Vec<Row>> {
    let contention = machine::Contention::start();
    let mut rows = Vec::new();
    let mut oracles: Vec<OracleRow> = Vec::new();
    for &size in &opts.sizes {
        anyhow::ensure!(
            size.is_power_of_two(),
            "sizes must be powers of two, got {size}"
        );
        let k = (size * size) as u64;
        for name in &opts.scenes {
            let truth32 = scene(name, size).with_context(|| format!("scene {name}"))?;
            let truth: Vec<f64> = truth32.iter().map(|&v| v as f64).collect();
            let exact_haar = Exact::new(&truth, size as usize, true);
            let exact_wh = Exact::new(&truth, size as usize, false);
            for noisy in [false, true] {
                let sigma = if noisy {
                    read_noise_sigma(&truth, 30.0)
                } else {
                    0.0
                };
                for &ratio in &opts.ratios {
                    let frames = ((ratio * k as f64).round() as u64).max(2) & !1;
                    let mut push = |family: &str,
                                    method: &str,
                                    spec: &PatternSpec,
                                    values: &[f64],
                                    planner: Option<PlannerFigures>,
                                    image: Option<&[f32]>| {
                        let (psnr_db, ssim, seconds, error) = match image {
                            Some(image) => (
                                metrics::psnr(image, &truth32),
                                metrics::ssim(image, &truth32, size as usize, size as usize),
                                0.0,
                                None,
                            ),
                            // `auto` told the rig's read noise (`read_noise`, the drawn sigma).
                            None if method == AUTO_DECLARED => reconstruct_with(
                                spec,
                                values,
                                "auto",
                                &serde_json::json!({ "read_noise": sigma }),
                                &truth32,
                            ),
                            None => reconstruct(spec, values, method, &truth32),
                        };
                        eprintln!(
                            "{name:>7} {size}x{size} {:>5} {:>5.1} % {frames:>6} frames  {family:<17} {method:<6} {psnr_db:>6.2} dB  {seconds:>7.3} s{}",
                            if noisy { "noisy" } else { "clean" },
                            100.0 * ratio,
                            error
                                .as_deref()
                                .map(|e| format!("  ({e})"))
                                .unwrap_or_default()
                        );
                        rows.push(Row {
                            scene: name.clone(),
                            size,
                            noisy,
                            ratio,
                            frames,
                            family: family.into(),
                            method: method.into(),
                            psnr_db,
                            ssim,
                            seconds,
                            error,
                            planner,
                        });
                    };
                    for family in [
                        Family::adaptive(true, 0, 0.0, opts.persistence),
                        Family::adaptive(false, 0, 0.0, opts.persistence),
                        Family::adaptive(true, 0, 0.0, opts.persistence)
                            .with_frames(AdaptiveFrames::Single),
                    ] {
                        let single = family.adaptive_frames() == Some(AdaptiveFrames::Single);
                        let label = if single { HAAR_SINGLE } else { family.name() };
                        let haar = matches!(family, Family::AdaptiveHaar { .. });
                        let s = run_adaptive(family, &truth, size, frames, sigma)?;
                        let basis_name = if haar { "haar" } else { "hadamard" };
                        let exact = if haar { &exact_haar } else { &exact_wh };
                        let c = &exact.coefficients;
                        let planner_capture = capture(c, &s.indices);
                        if single {
                            // The oracle tables are the split pairs' (the single-frame ones:
                            // `examples/single_frame.rs`).
                        } else if noisy {
                            if let Some(o) = oracles.iter_mut().find(|o| {
                                o.scene == *name
                                    && o.size == size
                                    && o.ratio == ratio
                                    && o.basis == basis_name
                            }) {
                                o.planner_capture_noisy = Some(planner_capture);
                            }
                        } else {
                            let kp = (frames / 2).min(k) as usize;
                            let basis = if haar { Basis::Haar } else { Basis::Hadamard };
                            let best = best_k(c, kp);
                            let tree = tree_greedy(c, size, basis, kp);
                            let psnr = |sel: &[u32]| {
                                metrics::psnr(&zero_filled(c, sel, size as usize, haar), &truth32)
                            };
                            // `auto` on the oracle's coefficients, measured as split pairs.
                            let oracle_spec = PatternSpec::new(
                                Family::adaptive(haar, 0, 0.0, None),
                                size,
                                size,
                                2 * kp as u64,
                                0,
                            )?
                            .with_indices(Arc::from(best.clone()))?;
                            let oracle_values: Vec<f64> = best
                                .iter()
                                .flat_map(|&n| {
                                    let (plus, minus) = exact.pair(n);
                                    [plus, minus]
                                })
                                .collect();
                            let (best_auto_psnr_db, _, best_auto_seconds, _) =
                                reconstruct(&oracle_spec, &oracle_values, "auto", &truth32);
                            let o = OracleRow {
                                scene: name.clone(),
                                size,
                                ratio,
                                frames,
                                coefficients: kp as u64,
                                basis: basis_name.into(),
                                best_psnr_db: psnr(&best),
                                best_auto_psnr_db,
                                tree_psnr_db: psnr(&tree),
                                best_capture: capture(c, &best),
                                tree_capture: capture(c, &tree),
                                planner_capture,
                                planner_capture_noisy: None,
                            };
                            eprintln!(
                                "{name:>7} {size}x{size} clean {:>5.1} % {frames:>6} frames  oracle {basis_name:<8} best {:>6.2} dB (auto {:>6.2} dB, {best_auto_seconds:.3} s) tree {:>6.2} dB  capture best {:.4} tree {:.4} planner {:.4}",
                                100.0 * ratio,
                                o.best_psnr_db,
                                o.best_auto_psnr_db,
                                o.tree_psnr_db,
                                o.best_capture,
                                o.tree_capture,
                                o.planner_capture
                            );
                            oracles.push(o);
                        }
                        push(
                            label,
                            "direct",
                            &s.spec,
                            &s.frames,
                            Some(s.figures.clone()),
                            None,
                        );
                        push(label, "auto", &s.spec, &s.frames, None, None);
                        if single && noisy {
                            push(label, AUTO_DECLARED, &s.spec, &s.frames, None, None);
                        }
                        push(
                            label,
                            "predicted",
                            &s.spec,
                            &s.frames,
                            None,
                            Some(&s.predicted),
                        );
                    }
                    let noise_free = NoiseModel::default();
                    for (label, family) in [
                        ("bernoulli", Family::Bernoulli { fill: 0.5 }),
                        (
                            "hadamard_rd",
                            Family::Hadamard {
                                ordering: HadamardOrdering::RussianDoll,
                            },
                        ),
                    ] {
                        let spec = PatternSpec::new(family, size, size, frames, 1)?;
                        let clean = simulate(&spec, &[&truth32], &noise_free, None).values;
                        let values: Vec<f64> = clean
                            .iter()
                            .enumerate()
                            .map(|(i, v)| v + read_noise(sigma, 7, i as u64))
                            .collect();
                        push(label, "auto", &spec, &values, None, None);
                    }
                }
            }
        }
    }
    let machine = contention.finish();
    std::fs::create_dir_all(&opts.out)?;
    std::fs::write(
        opts.out.join("benchmarks-adaptive.json"),
        serde_json::to_string_pretty(&serde_json::json!({
            "command": "cargo run --release -p helmholtz-bench -- --preset adaptive",
            "machine": machine,
            "rows": rows,
            "oracle": oracles,
        }))?,
    )?;
    std::fs::write(
        opts.out.join("benchmarks-adaptive.md"),
        markdown(&rows, &oracles, opts, &machine::sentence(&machine)),
    )?;
    Ok(rows)
}

fn find<'a>(rows: &'a [Row], r: &Row, family: &str, method: &str) -> Option<&'a Row> {
    rows.iter().find(|x| {
        x.scene == r.scene
            && x.size == r.size
            && x.noisy == r.noisy
            && x.ratio == r.ratio
            && x.family == family
            && x.method == method
    })
}

fn best_of(rows: &[Row], r: &Row, which: &[(&str, &str)]) -> f64 {
    which
        .iter()
        .filter_map(|(f, m)| find(rows, r, f, m))
        .map(|x| x.psnr_db)
        .filter(|p| p.is_finite())
        .fold(f64::NEG_INFINITY, f64::max)
}

/// The method label of `auto` with the drawn read noise declared (`read_noise`).
const AUTO_DECLARED: &str = "auto_read_noise";
const ADAPTIVE: [(&str, &str); 10] = [
    ("adaptive_haar", "direct"),
    ("adaptive_haar", "auto"),
    ("adaptive_haar", "predicted"),
    ("adaptive_hadamard", "direct"),
    ("adaptive_hadamard", "auto"),
    ("adaptive_hadamard", "predicted"),
    (HAAR_SINGLE, "direct"),
    (HAAR_SINGLE, "auto"),
    (HAAR_SINGLE, "predicted"),
    (HAAR_SINGLE, AUTO_DECLARED),
];

/// The rows' family label of `adaptive_haar` with single frames.
const HAAR_SINGLE: &str = "adaptive_haar_single";
const FIXED: [(&str, &str); 2] = [("bernoulli", "auto"), ("hadamard_rd", "auto")];

fn markdown(rows: &[Row], oracles: &[OracleRow], opts: &Options, machine: &str) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Adaptive acquisition: PSNR against frames\n");
    let _ = writeln!(
        md,
        "Generated by `cargo run --release -p helmholtz-bench -- --preset adaptive --out docs` \
         (module docs of `bench/src/adaptive.rs` for the set-up). Frames are counted the same way \
         for every family (a split pair is 2 frames; `haar 1f` = adaptive_haar with single \
         frames, one a basis function but the first). PSNR in dB against the scene (raw, no \
         fitting). `haar`/`wh` = adaptive_haar / adaptive_hadamard; `dir` = `direct` (the \
         zero-filled inverse, the adaptive scheme's own image), `auto` = `auto` on the same data, \
         `pred` = the planner's prediction-filled image (`Planner::predicted_image`: unmeasured \
         coefficients set to their bicubic prediction; not a service method yet); \
         `read_noise` = `auto` told the drawn read noise (single frames have no estimate of \
         their own; noisy tables only); \
         `bern`, `rd` = `auto` on Bernoulli 1/2 and Russian-doll Hadamard at the same frame \
         count. Noise: none, or read noise at 30 dB of a half-lit pattern's bucket.\n"
    );
    let _ = writeln!(md, "{machine}\n");
    for &size in &opts.sizes {
        for noisy in [false, true] {
            let _ = writeln!(
                md,
                "## {size}x{size}, {}\n",
                if noisy {
                    "read noise (30 dB)"
                } else {
                    "noise-free"
                }
            );
            let _ = writeln!(
                md,
                "| scene | frames | % of k | haar dir | haar auto | haar pred | wh dir | wh auto | wh pred | haar 1f dir | haar 1f auto | haar 1f auto, read_noise | bern auto | rd auto | best adaptive - best fixed |"
            );
            let _ = writeln!(
                md,
                "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
            );
            for r in rows.iter().filter(|r| {
                r.size == size
                    && r.noisy == noisy
                    && r.family == "adaptive_haar"
                    && r.method == "direct"
            }) {
                let cell = |f: &str, m: &str| {
                    find(rows, r, f, m)
                        .map(|x| format!("{:.2}", x.psnr_db))
                        .unwrap_or_else(|| "-".into())
                };
                let _ = writeln!(
                    md,
                    "| {} | {} | {:.0} % | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {:+.2} |",
                    r.scene,
                    r.frames,
                    100.0 * r.ratio,
                    cell("adaptive_haar", "direct"),
                    cell("adaptive_haar", "auto"),
                    cell("adaptive_haar", "predicted"),
                    cell("adaptive_hadamard", "direct"),
                    cell("adaptive_hadamard", "auto"),
                    cell("adaptive_hadamard", "predicted"),
                    cell(HAAR_SINGLE, "direct"),
                    cell(HAAR_SINGLE, "auto"),
                    cell(HAAR_SINGLE, AUTO_DECLARED),
                    cell("bernoulli", "auto"),
                    cell("hadamard_rd", "auto"),
                    best_of(rows, r, &ADAPTIVE) - best_of(rows, r, &FIXED)
                );
            }
            let _ = writeln!(md);
        }
    }

    oracle_tables(&mut md, rows, oracles, opts);

    let _ = writeln!(md, "## The issue's targets\n");
    let _ = writeln!(
        md,
        "- **A**: the best adaptive result at 5 % of k reaches the best non-adaptive `auto` at 10 % \
         (the same PSNR with at most half the frames).\n- **B**: on natural scenes ({}), the best \
         adaptive result at 2 % beats the best non-adaptive `auto` at 2 % by at least 3 dB.\n",
        NATURAL.join(", ")
    );
    let _ = writeln!(
        md,
        "| size | noise | scene | A: adaptive 5 % | fixed 10 % | A met | B: adaptive 2 % - fixed 2 % | B met |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|");
    let at = |r: &Row, ratio: f64| {
        rows.iter()
            .find(|x| {
                x.scene == r.scene && x.size == r.size && x.noisy == r.noisy && x.ratio == ratio
            })
            .cloned()
    };
    for r in rows
        .iter()
        .filter(|r| r.family == "adaptive_haar" && r.method == "direct" && r.ratio == 0.10)
    {
        let (Some(r5), Some(r2)) = (at(r, 0.05), at(r, 0.02)) else {
            continue;
        };
        let a5 = best_of(rows, &r5, &ADAPTIVE);
        let f10 = best_of(rows, r, &FIXED);
        let gain2 = best_of(rows, &r2, &ADAPTIVE) - best_of(rows, &r2, &FIXED);
        let natural = NATURAL.contains(&r.scene.as_str());
        let _ = writeln!(
            md,
            "| {} | {} | {} | {a5:.2} | {f10:.2} | {} | {gain2:+.2} | {} |",
            r.size,
            if r.noisy { "30 dB" } else { "none" },
            r.scene,
            if a5 >= f10 { "yes" } else { "no" },
            if !natural {
                "(not natural)"
            } else if gain2 >= 3.0 {
                "yes"
            } else {
                "no"
            }
        );
    }

    oracle_targets(&mut md, rows, oracles);

    let _ = writeln!(md, "\n## The planner: decision time and memory\n");
    let _ = writeln!(
        md,
        "Decision = the prediction after each observed batch plus the selection of the next \
         (`Planner::decision_stats`), one bucket channel, automatic batches. Display = one full \
         batch at 20 kHz binary frames (2 frames of 50 us per pair): with two batches outstanding \
         the decision for batch b + 2 runs while batch b + 1 is shown, so the DMD idles only if a \
         decision outlasts a batch's display.\n"
    );
    let _ = writeln!(
        md,
        "| size | family | frames | batch pairs | batches | decision mean ms | decision max ms | batch display ms | max / display | planner MiB |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|");
    for r in rows
        .iter()
        .filter(|r| r.planner.is_some() && !r.noisy && r.scene == opts.scenes[0])
    {
        let p = r.planner.as_ref().expect("filtered");
        let _ = writeln!(
            md,
            "| {0}x{0} | {1} | {2} | {3} | {4} | {5:.3} | {6:.3} | {7:.2} | {8:.2} | {9:.2} |",
            r.size,
            r.family,
            r.frames,
            p.batch_pairs,
            p.batches,
            p.decision_mean_ms,
            p.decision_max_ms,
            p.batch_display_ms,
            p.decision_max_ms / p.batch_display_ms,
            p.memory_bytes as f64 / (1 << 20) as f64
        );
    }
    error_estimates(&mut md, rows);
    md
}

/// The planner's error estimates against the true error of its zero-filled image.
fn error_estimates(md: &mut String, rows: &[Row]) {
    let _ = writeln!(md, "\n## Error estimate: the planner's against the truth\n");
    let _ = writeln!(
        md,
        "What `target_error` compares with: the planner's estimate of the relative L2 error of \
         its zero-filled image (`direct`) at the end of the session, against that image's true \
         relative error. `measured` = the default `error_estimate` (PATTERNS.md, \"Error \
         estimate\"), `prediction` = the rule of sessions stored before it (the same session \
         replayed with it). Ratio = estimate / truth: below 1 a `target_error` stop fires with \
         an image worse than asked. `noise` = the pair-difference noise the pair sums show \
         against the drawn `sqrt(2) sigma`.\n"
    );
    let _ = writeln!(
        md,
        "| size | noise | scene | family | frames | true error | measured | ratio | prediction | ratio | noise shown / drawn |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|");
    let (mut measured, mut prediction) = (Vec::new(), Vec::new());
    for r in rows.iter().filter(|r| r.method == "direct") {
        let Some(p) = r.planner.as_ref() else {
            continue;
        };
        let ratio = |e: Option<f64>| e.map(|e| e / p.true_error);
        let (m, q) = (ratio(p.estimated_error), ratio(p.prediction_estimate));
        measured.extend(m);
        prediction.extend(q);
        let f = |v: Option<f64>, digits: usize| {
            v.map(|v| format!("{v:.digits$}")).unwrap_or("-".into())
        };
        let _ = writeln!(
            md,
            "| {0}x{0} | {1} | {2} | {3} | {4} | {5:.4} | {6} | {7} | {8} | {9} | {10} |",
            r.size,
            if r.noisy { "30 dB" } else { "none" },
            r.scene,
            r.family,
            r.frames,
            p.true_error,
            f(p.estimated_error, 4),
            f(m, 2),
            f(p.prediction_estimate, 4),
            f(q, 2),
            if r.noisy {
                format!("{} / {:.2}", f(p.pair_noise, 2), p.drawn_pair_noise)
            } else {
                f(p.pair_noise, 2)
            }
        );
    }
    let span = |v: &[f64]| {
        let lo = v.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let below = v.iter().filter(|&&x| x < 1.0).count();
        format!("{lo:.2} to {hi:.2}, below 1 in {below} of {}", v.len())
    };
    let _ = writeln!(
        md,
        "\nRatio estimate / truth: `measured` {}; `prediction` {}.",
        span(&measured),
        span(&prediction)
    );
}

fn oracle_find<'a>(oracles: &'a [OracleRow], r: &Row, basis: &str) -> Option<&'a OracleRow> {
    oracles
        .iter()
        .find(|o| o.scene == r.scene && o.size == r.size && o.ratio == r.ratio && o.basis == basis)
}

/// The oracle's PSNR and energy tables, one pair per size (noise-free).
fn oracle_tables(md: &mut String, rows: &[Row], oracles: &[OracleRow], opts: &Options) {
    if oracles.is_empty() {
        return;
    }
    let _ = writeln!(
        md,
        "## Oracle: the best k' = frames / 2 true coefficients\n"
    );
    let _ = writeln!(
        md,
        "Noise-free. `k'` = the split pairs an adaptive session of that many frames measures. \
         `best` = the k' largest coefficients of the true scene (mean included), zero elsewhere, \
         inverted: the best image any scheme measuring k' functions of that basis and \
         reconstructing linearly can make. `best auto` = `auto` on the split pairs of those k' \
         coefficients (a non-linear reconstruction of the oracle's data). `tree` = the planner's tree rule fed the true \
         coefficients (from the root, always the largest |c| among the indices whose parent is \
         taken; `Basis::parent`). `planner` = `direct` of the adaptive session above (the \
         zero-filled image of what the planner measured). `fixed` = the best non-adaptive `auto` \
         (Bernoulli or Russian-doll Hadamard) at the same frame count. Haar = the basis of \
         `adaptive_haar` (`Wavelet2d::haar`), WH = that of `adaptive_hadamard` (`fwht / W`). \
         Energy: the share of the scene's energy without the mean (sum of c_n^2 over n != 0, the \
         same in both bases) in the coefficients of each set; the planner's sets are the indices \
         of its noise-free and its 30 dB session.\n"
    );
    for &size in &opts.sizes {
        let base: Vec<&Row> = rows
            .iter()
            .filter(|r| {
                r.size == size && !r.noisy && r.family == "adaptive_haar" && r.method == "direct"
            })
            .collect();
        if base.is_empty() {
            continue;
        }
        let _ = writeln!(md, "### {size}x{size}: PSNR (dB)\n");
        let _ = writeln!(
            md,
            "| scene | frames | % of k | k' | haar best | haar best auto | haar tree | haar planner | wh best | wh best auto | wh tree | wh planner | fixed auto | best oracle - fixed |"
        );
        let _ = writeln!(
            md,
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
        );
        for r in &base {
            let (Some(h), Some(w)) = (
                oracle_find(oracles, r, "haar"),
                oracle_find(oracles, r, "hadamard"),
            ) else {
                continue;
            };
            let cell = |f: &str, m: &str| {
                find(rows, r, f, m)
                    .map(|x| format!("{:.2}", x.psnr_db))
                    .unwrap_or_else(|| "-".into())
            };
            let fixed = best_of(rows, r, &FIXED);
            let _ = writeln!(
                md,
                "| {} | {} | {:.0} % | {} | {:.2} | {:.2} | {:.2} | {} | {:.2} | {:.2} | {:.2} | {} | {:.2} | {:+.2} |",
                r.scene,
                r.frames,
                100.0 * r.ratio,
                h.coefficients,
                h.best_psnr_db,
                h.best_auto_psnr_db,
                h.tree_psnr_db,
                cell("adaptive_haar", "direct"),
                w.best_psnr_db,
                w.best_auto_psnr_db,
                w.tree_psnr_db,
                cell("adaptive_hadamard", "direct"),
                fixed,
                h.best_psnr_db.max(w.best_psnr_db) - fixed
            );
        }
        let _ = writeln!(md);
        let _ = writeln!(
            md,
            "### {size}x{size}: share of the energy without the mean (%)\n"
        );
        let _ = writeln!(
            md,
            "| scene | frames | % of k | haar best | haar tree | haar planner | haar planner 30 dB | wh best | wh tree | wh planner | wh planner 30 dB |"
        );
        let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|");
        let pct = |v: Option<f64>| {
            v.map(|v| format!("{:.2}", 100.0 * v))
                .unwrap_or_else(|| "-".into())
        };
        for r in &base {
            let (Some(h), Some(w)) = (
                oracle_find(oracles, r, "haar"),
                oracle_find(oracles, r, "hadamard"),
            ) else {
                continue;
            };
            let _ = writeln!(
                md,
                "| {} | {} | {:.0} % | {} | {} | {} | {} | {} | {} | {} | {} |",
                r.scene,
                r.frames,
                100.0 * r.ratio,
                pct(Some(h.best_capture)),
                pct(Some(h.tree_capture)),
                pct(Some(h.planner_capture)),
                pct(h.planner_capture_noisy),
                pct(Some(w.best_capture)),
                pct(Some(w.tree_capture)),
                pct(Some(w.planner_capture)),
                pct(w.planner_capture_noisy),
            );
        }
        let _ = writeln!(md);
    }
}

/// Targets A and B with the oracle (best of the two bases' best k') in place of the adaptive
/// schemes: reachable at all with these bases and a linear reconstruction (noise-free)?
fn oracle_targets(md: &mut String, rows: &[Row], oracles: &[OracleRow]) {
    if oracles.is_empty() {
        return;
    }
    let _ = writeln!(
        md,
        "\nWith the oracle in place of the adaptive schemes (noise-free; `oracle` = the better of \
         Haar and WH best k' (zero-filled); `oracle auto` = the better `auto` on them; `tree` = the \
         better tree rule; `planner` = the better `direct`; \"reachable (linear)\" compares the \
         zero-filled oracle):\n"
    );
    let _ = writeln!(
        md,
        "| size | scene | A: oracle 5 % | oracle auto 5 % | tree 5 % | planner 5 % | fixed 10 % | A reachable (linear) | B: oracle 2 % - fixed 2 % | oracle auto 2 % - fixed 2 % | tree 2 % - fixed 2 % | B reachable (linear) |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|---|");
    let at = |r: &Row, ratio: f64| {
        rows.iter().find(|x| {
            x.scene == r.scene
                && x.size == r.size
                && !x.noisy
                && x.ratio == ratio
                && x.family == "adaptive_haar"
                && x.method == "direct"
        })
    };
    // 0: best k', 1: tree, 2: auto on the best k'.
    let best = |r: &Row, which: u8| {
        ["haar", "hadamard"]
            .iter()
            .filter_map(|b| oracle_find(oracles, r, b))
            .map(|o| match which {
                0 => o.best_psnr_db,
                1 => o.tree_psnr_db,
                _ => o.best_auto_psnr_db,
            })
            .filter(|p| p.is_finite())
            .fold(f64::NEG_INFINITY, f64::max)
    };
    const DIRECT: [(&str, &str); 2] =
        [("adaptive_haar", "direct"), ("adaptive_hadamard", "direct")];
    for r in rows.iter().filter(|r| {
        !r.noisy && r.family == "adaptive_haar" && r.method == "direct" && r.ratio == 0.10
    }) {
        let (Some(r5), Some(r2)) = (at(r, 0.05), at(r, 0.02)) else {
            continue;
        };
        let o5 = best(r5, 0);
        let f10 = best_of(rows, r, &FIXED);
        let f2 = best_of(rows, r2, &FIXED);
        let natural = NATURAL.contains(&r.scene.as_str());
        let _ = writeln!(
            md,
            "| {} | {} | {o5:.2} | {:.2} | {:.2} | {:.2} | {f10:.2} | {} | {:+.2} | {:+.2} | {:+.2} | {} |",
            r.size,
            r.scene,
            best(r5, 2),
            best(r5, 1),
            best_of(rows, r5, &DIRECT),
            if o5 >= f10 { "yes" } else { "no" },
            best(r2, 0) - f2,
            best(r2, 2) - f2,
            best(r2, 1) - f2,
            if !natural {
                "(not natural)"
            } else if best(r2, 0) - f2 >= 3.0 {
                "yes"
            } else {
                "no"
            }
        );
    }
}
