//! Exact inverses of complete raster and Hadamard (split-pair) sets.
//!
//! - Raster (block b): pattern i lights block `i % blocks`; `t` per block = mean over all repeats
//!   of that block's bucket / number of pixels in the block (edge blocks may be smaller), spread
//!   over the block's pixels. With b = 1 this is `t` exactly; with b > 1 it is the block average.
//! - Hadamard split pairs: frame 2r shows `P+ = (1 + h_r)/2`, frame 2r + 1 `P- = (1 - h_r)/2`, so
//!   `d_r = y+ - y- = h_r . t` (a constant dark level cancels). Placing `d_r` at the natural
//!   (Sylvester) index `n` of row r and applying the k-point FWHT gives `H d = k t`, `t` in
//!   row-major order (`h_n(x, y)` is row n of the Sylvester matrix at column `y W + x`).
//!   The pair sums `s_r = y+ + y- = 1 . t + 2 dark` are constant unless the source drifts: their
//!   spread is reported as a drift monitor, and the P- frame of natural row 0 (all-off) as the dark
//!   level.
//!
//! Streaming, O(k * channels) memory: raster keeps one sum per block and channel, Hadamard one
//! value per row and channel plus the pending P+ frame.

use helmholtz_proto::{Family, PatternGenerator};
use serde_json::{Map, Value, json};

use super::fwht::fwht;
use super::noise;
use super::stream::RowStream;
use super::{
    BucketSource, Control, DualImage, MethodConfig, Problem, ReconError, Reconstruction, Report,
};

/// Runs the exact inverse (see the module docs) for [`MethodConfig::Direct`],
/// [`MethodConfig::ZeroFilled`] or [`MethodConfig::Levels`]. Errors as for the correlators; a
/// family other than raster or Hadamard, or an incomplete set for `direct`, is
/// [`ReconError::Unsolvable`].
pub fn run(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
) -> Result<Reconstruction, ReconError> {
    config.check(problem)?;
    let stream = RowStream::new(source, control, problem.channels, problem.rows)?;
    let k = problem.spec.pixels();
    let (images, details) = match (problem.spec.family(), config) {
        (Family::Raster { .. }, MethodConfig::Direct) => raster(problem, stream, control)?,
        (Family::Hadamard { .. }, MethodConfig::Direct) => hadamard(problem, stream, control, k)?,
        // The adaptive scheme's own image: the zero-filled inverse of the pairs it chose.
        (Family::AdaptiveHadamard { .. }, MethodConfig::Direct | MethodConfig::ZeroFilled) => {
            let pairs = (problem.rows / 2) as usize;
            let mut out = hadamard(problem, stream, control, pairs)?;
            out.1.insert("family".into(), json!("adaptive_hadamard"));
            out.1.insert("pairs_used".into(), json!(pairs));
            out.1.insert("pairs_missing".into(), json!(k - pairs));
            out
        }
        (Family::AdaptiveHaar { .. }, MethodConfig::Direct | MethodConfig::ZeroFilled) => {
            adaptive_haar(problem, stream, control)?
        }
        (Family::Hadamard { .. }, MethodConfig::ZeroFilled) => {
            let mut out = hadamard(problem, stream, control, (problem.rows / 2) as usize)?;
            out.1.insert("pairs_used".into(), json!(problem.rows / 2));
            out.1.insert(
                "pairs_missing".into(),
                json!(k as u64 - (problem.rows / 2).min(k as u64)),
            );
            out
        }
        (Family::Hadamard { .. }, MethodConfig::Levels { level }) => {
            let (w, h) = (
                problem.spec.width() as usize,
                problem.spec.height() as usize,
            );
            let available = (problem.rows / 2) as usize;
            let complete: Vec<u32> = (0..=12u32)
                .filter(|&j| {
                    level_pairs(w, h, j) <= available && (j == 0 || level_pairs(w, h, j - 1) < k)
                })
                .collect();
            let finest = *complete
                .last()
                .expect("level 0 needs one pair and check() refused zero rows");
            let j = match level {
                None => finest,
                Some(j) if complete.contains(j) => *j,
                Some(j) => {
                    return Err(ReconError::Unsolvable(format!(
                        "level {j} is not complete: it needs {} pairs ({} frames), the session has {available} pairs; complete levels: {complete:?}",
                        level_pairs(w, h, *j),
                        2 * level_pairs(w, h, *j)
                    )));
                }
            };
            let mut out = hadamard(problem, stream, control, level_pairs(w, h, j))?;
            out.1.insert("level".into(), json!(j));
            out.1
                .insert("resolution".into(), json!([w.min(1 << j), h.min(1 << j)]));
            out.1
                .insert("block".into(), json!([(w >> j).max(1), (h >> j).max(1)]));
            out.1
                .insert("pairs_used".into(), json!(level_pairs(w, h, j)));
            out.1.insert(
                "complete_levels".into(),
                Value::Array(complete.iter().map(|&j| json!({"level": j, "resolution": [w.min(1 << j), h.min(1 << j)], "pairs": level_pairs(w, h, j)})).collect()),
            );
            out
        }
        (other, _) => {
            return Err(ReconError::Unsolvable(format!(
                "{} inverts raster or hadamard sets, not {}",
                config.name(),
                other.name()
            )));
        }
    };
    control.set_progress(1.0);
    Ok(Reconstruction {
        images,
        report: Report {
            method: config.name().into(),
            params: config.params_json(),
            rows_used: problem.rows,
            iterations: 1,
            details,
            held_out: None,
            held_out_unavailable: Some(format!(
                "{} is an exact inverse: each image value comes from its own rows alone (a raster block, a \
                 Hadamard coefficient), so no other row predicts a held-out one; cs, tv or auto on this \
                 session report a held-out error",
                config.name()
            )),
        },
    })
}

/// Split pairs in the Russian-doll levels `0..=j` of a `w x h` image (power-of-two sides):
/// `min(2^j, h) * min(2^j, w)` (PATTERNS.md).
pub fn level_pairs(w: usize, h: usize, j: u32) -> usize {
    let side = 1usize << j.min(40);
    side.min(w) * side.min(h)
}

type Output = (Vec<DualImage>, Map<String, Value>);

fn raster(
    problem: &Problem,
    mut stream: RowStream,
    control: &Control,
) -> Result<Output, ReconError> {
    let spec = problem.spec;
    let m = problem.channels;
    let (block, bx, by) = spec.raster_grid().expect("raster");
    let (block, bx, by) = (block as usize, bx as usize, by as usize);
    let blocks = bx * by;
    let generator = PatternGenerator::new(spec);
    let mut sums = vec![0.0f64; blocks * m];
    let mut counts = vec![0u64; blocks];
    while let Some(b) = stream.next_block()? {
        for (i, row) in b.values.chunks_exact(m).enumerate() {
            let blk = generator
                .raster_block(b.first_row + i as u64)
                .expect("raster") as usize;
            counts[blk] += 1;
            for (s, v) in sums[blk * m..(blk + 1) * m].iter_mut().zip(row) {
                *s += v;
            }
        }
        control.set_progress(stream.rows_seen() as f64 / stream.total() as f64);
    }
    let (w, h) = (spec.width() as usize, spec.height() as usize);
    // t per block and channel: mean bucket / pixels in the block.
    let mut values = vec![0.0f64; blocks * m];
    for blk in 0..blocks {
        let (cx, cy) = (blk % bx, blk / bx);
        let pixels = (block.min(w - cx * block) * block.min(h - cy * block)) as f64;
        debug_assert!(counts[blk] > 0, "check() guarantees a complete scan");
        for ch in 0..m {
            values[blk * m + ch] = sums[blk * m + ch] / counts[blk] as f64 / pixels;
        }
    }
    let images = (0..m)
        .map(|ch| {
            let data = (0..w * h)
                .map(|p| {
                    let blk = (p / w / block) * bx + (p % w) / block;
                    values[blk * m + ch] as f32
                })
                .collect();
            DualImage {
                width: spec.width(),
                height: spec.height(),
                data,
            }
        })
        .collect();
    let (lo, hi) = (
        counts.iter().min().copied().unwrap_or(0),
        counts.iter().max().copied().unwrap_or(0),
    );
    let mut details = Map::new();
    details.insert("family".into(), json!("raster"));
    details.insert("block".into(), json!(block));
    details.insert("blocks".into(), json!(blocks));
    details.insert("complete_scans".into(), json!(lo));
    details.insert("max_repeats".into(), json!(hi));
    Ok((images, details))
}

/// Running mean, spread and range of the pair sums (Welford).
#[derive(Clone, Debug, Default)]
struct PairStats {
    n: u64,
    mean: f64,
    m2: f64,
    min: f64,
    max: f64,
}

impl PairStats {
    fn push(&mut self, x: f64) {
        if self.n == 0 {
            self.min = x;
            self.max = x;
        }
        self.n += 1;
        let d = x - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (x - self.mean);
        self.min = self.min.min(x);
        self.max = self.max.max(x);
    }
    /// Population standard deviation / |mean|.
    fn rel_std(&self) -> f64 {
        (self.m2 / self.n as f64).sqrt() / self.mean.abs()
    }
    /// Largest |s_r - mean| / |mean|.
    fn max_rel_dev(&self) -> f64 {
        (self.max - self.mean).max(self.mean - self.min) / self.mean.abs()
    }
}

/// Non-finite values (0/0 on a dark session) become null in the report.
fn finite(v: f64) -> Value {
    if v.is_finite() { json!(v) } else { Value::Null }
}

/// The Hadamard inverse from the first `pairs` split pairs (`k`: all, the exact inverse; fewer:
/// the zero-filled inverse, which at a complete Russian-doll level is the exact block average).
fn hadamard(
    problem: &Problem,
    mut stream: RowStream,
    control: &Control,
    pairs: usize,
) -> Result<Output, ReconError> {
    let spec = problem.spec;
    let m = problem.channels;
    let k = spec.pixels();
    let generator = PatternGenerator::new(spec);
    // d[ch * k + natural] = y+ - y-.
    let mut d = vec![0.0f64; m * k];
    let mut positive = vec![0.0f64; m];
    let mut have_positive = false;
    let mut dark = vec![f64::NAN; m];
    let mut stats = vec![PairStats::default(); m];
    // The pair sums in arrival order, per channel: the noise estimate ([`noise::from_pair_sums`]).
    let mut sums: Vec<Vec<f64>> = vec![Vec::new(); m];
    // Pairs measured other than the mean's (natural 0): the coefficients whose noise the
    // image's variation about its mean carries.
    let mut detail_pairs = 0usize;
    let frames = 2 * pairs.min(k) as u64;
    while let Some(b) = stream.next_block()? {
        for (i, row) in b.values.chunks_exact(m).enumerate() {
            let frame = b.first_row + i as u64;
            if frame >= frames {
                break; // only the first 2k frames are needed
            }
            let sf = generator.split_frame(frame).expect("hadamard");
            if sf.positive {
                positive.copy_from_slice(row);
                have_positive = true;
                continue;
            }
            debug_assert!(have_positive, "frames arrive in order, P+ first");
            let n = sf.natural as usize;
            detail_pairs += usize::from(n != 0);
            for ch in 0..m {
                let (yp, ym) = (positive[ch], row[ch]);
                d[ch * k + n] = yp - ym;
                stats[ch].push(yp + ym);
                sums[ch].push(yp + ym);
                if n == 0 {
                    dark[ch] = ym; // P- of the all-ones row lights nothing
                }
            }
            have_positive = false;
        }
        control.set_progress(0.95 * stream.rows_seen() as f64 / stream.total() as f64);
    }
    let root = 1.0 / (k as f64).sqrt();
    let noise: Vec<Option<noise::NoiseEstimate>> = (0..m)
        .map(|ch| {
            let data: Vec<f64> = d[ch * k..(ch + 1) * k].iter().map(|v| v * root).collect();
            noise::from_pair_sums(&sums[ch], root, &data)
        })
        .collect();
    // Each measured coefficient (in the data's units, `(y+ - y-) / sqrt(k)`) carries the
    // noise `sigma` of one datum; the inverse is orthonormal, so the image's variation about its
    // mean is their energy (the unmeasured ones are 0).
    let shares: Vec<Option<f64>> = noise
        .iter()
        .enumerate()
        .map(|(ch, e)| {
            let energy: f64 = d[ch * k + 1..(ch + 1) * k]
                .iter()
                .map(|v| (v * root).powi(2))
                .sum();
            e.and_then(|e| noise::noise_share(detail_pairs as f64 * e.sigma * e.sigma, energy))
        })
        .collect();
    let scale = 1.0 / k as f64;
    let images = d
        .chunks_exact_mut(k)
        .map(|t| {
            if control.is_cancelled() {
                return Err(ReconError::Cancelled);
            }
            fwht(t);
            let data = t.iter().map(|v| (v * scale) as f32).collect();
            Ok(DualImage {
                width: spec.width(),
                height: spec.height(),
                data,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut details = Map::new();
    details.insert("family".into(), json!("hadamard"));
    details.insert(
        "dark_level".into(),
        Value::Array(dark.iter().map(|&v| finite(v)).collect()),
    );
    details.insert(
        "pair_sum_mean".into(),
        Value::Array(stats.iter().map(|s| finite(s.mean)).collect()),
    );
    details.insert(
        "pair_sum_rel_std".into(),
        Value::Array(stats.iter().map(|s| finite(s.rel_std())).collect()),
    );
    details.insert(
        "pair_sum_max_rel_dev".into(),
        Value::Array(stats.iter().map(|s| finite(s.max_rel_dev())).collect()),
    );
    // Per channel, in the units of (y+ - y-) / sqrt(k); for the exact inverse this is also
    // each pixel's noise (the transform is orthonormal).
    details.insert("noise_estimate".into(), json!(noise));
    noisy_image_warning(&mut details, &shares);
    Ok((images, details))
}

/// At or above this share of the image's variation about its mean in noise
/// ([`noise::noise_share`]), a linear inverse is mostly noise and the report says so.
pub const NOISY_IMAGE_SHARE: f64 = 0.5;

/// Records each channel's [`noise::noise_share`] as `details.noise_share` and, where one reaches
/// [`NOISY_IMAGE_SHARE`], a warning (`details.warnings`, which clients show): a linear inverse
/// passes every measured coefficient's noise into the image, which the user cannot see from the
/// image alone.
fn noisy_image_warning(details: &mut Map<String, Value>, shares: &[Option<f64>]) {
    details.insert(
        "noise_share".into(),
        Value::Array(
            shares
                .iter()
                .map(|v| v.map_or(Value::Null, finite))
                .collect(),
        ),
    );
    let worst = shares
        .iter()
        .enumerate()
        .filter_map(|(ch, v)| v.map(|v| (ch, v)))
        .max_by(|a, b| a.1.total_cmp(&b.1));
    if let Some((ch, share)) = worst.filter(|w| w.1 >= NOISY_IMAGE_SHARE) {
        let which = if shares.len() > 1 {
            format!(" (channel {ch})")
        } else {
            String::new()
        };
        let pct = if share >= 1.0 {
            "all".to_string()
        } else {
            format!("{:.0} %", 100.0 * share)
        };
        details.insert(
            "warnings".into(),
            json!([format!(
                "the detector noise the pair sums show is {pct} of this image's variation about its \
                 mean{which}: an inverse passes every measured coefficient's noise into the image; \
                 tv and cs (and auto on an incomplete set, which shrinks the coefficients by their \
                 signal-to-noise ratio) keep less of it"
            )]),
        );
    }
}

/// The zero-filled Haar inverse of a resolved adaptive_haar session's pairs: coefficient
/// `(y+ - y-) / 2^s` at its Mallat index (`ops::haar`), then the inverse orthonormal transform.
fn adaptive_haar(
    problem: &Problem,
    mut stream: RowStream,
    control: &Control,
) -> Result<Output, ReconError> {
    use crate::linop::LinearOperator;
    let spec = problem.spec;
    let m = problem.channels;
    let k = spec.pixels();
    let w = spec.width();
    let indices = spec
        .adaptive_indices()
        .expect("check() requires a resolved spec");
    let pairs = (problem.rows / 2) as usize;
    let mut coefficients = vec![0.0f64; m * k];
    let mut positive = vec![0.0f64; m];
    let mut dark = vec![f64::NAN; m];
    // Per pair: its support's key and gain ([`noise::haar_support`]), and per channel its sum
    // `y+ + y-`, for the noise estimate.
    let mut support = Vec::with_capacity(pairs);
    let mut gains = Vec::with_capacity(pairs);
    let mut sums: Vec<Vec<f64>> = vec![Vec::with_capacity(pairs); m];
    while let Some(b) = stream.next_block()? {
        for (i, row) in b.values.chunks_exact(m).enumerate() {
            let frame = b.first_row + i as u64;
            let pair = (frame / 2) as usize;
            if pair >= pairs {
                break;
            }
            if frame.is_multiple_of(2) {
                positive.copy_from_slice(row);
                continue;
            }
            let n = indices[pair];
            let (key, gain) = noise::haar_support(w, n);
            support.push(key);
            gains.push((n != 0).then_some(gain));
            for ch in 0..m {
                sums[ch].push(positive[ch] + row[ch]);
                coefficients[ch * k + n as usize] = (positive[ch] - row[ch]) / gain;
                if n == 0 {
                    dark[ch] = row[ch]; // P- of the scaling function lights nothing
                }
            }
        }
        control.set_progress(0.95 * stream.rows_seen() as f64 / stream.total() as f64);
    }
    // Each detail coefficient `(y+ - y-) / g` carries the pair's noise over `g`; the pairs of
    // one support give that noise ([`noise::from_support_groups`]).
    let support_noise: Vec<Option<noise::SupportNoise>> = sums
        .iter()
        .map(|s| noise::from_support_groups(s, &support))
        .collect();
    let shares: Vec<Option<f64>> = support_noise
        .iter()
        .zip(coefficients.chunks_exact(k))
        .map(|(e, c)| {
            let e = (*e)?;
            let variance: f64 = gains
                .iter()
                .flatten()
                .map(|g| e.pair_variance / (g * g))
                .sum();
            noise::noise_share(variance, c[1..].iter().map(|v| v * v).sum())
        })
        .collect();
    let wavelet = crate::transforms::wavelet::Wavelet2d::haar(w as usize, w as usize);
    let mut image = vec![0.0f64; k];
    let mut images = Vec::with_capacity(m);
    for c in coefficients.chunks_exact(k) {
        if control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        wavelet.adjoint(c, &mut image);
        images.push(DualImage {
            width: w,
            height: w,
            data: image.iter().map(|&v| v as f32).collect(),
        });
    }
    let mut details = Map::new();
    details.insert("family".into(), json!("adaptive_haar"));
    details.insert("pairs_used".into(), json!(pairs));
    details.insert("pairs_missing".into(), json!(k - pairs));
    details.insert(
        "dark_level".into(),
        Value::Array(dark.iter().map(|&v| finite(v)).collect()),
    );
    // Per channel (`null` where no support was shown twice): the variance of one pair's
    // `y+ + y-`, and so of its `y+ - y-`.
    details.insert("support_noise".into(), json!(support_noise));
    noisy_image_warning(&mut details, &shares);
    Ok((images, details))
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops read best in the reference computations
mod tests {
    use super::*;
    use crate::linop::LinearOperator;
    use crate::metrics::relative_error;
    use crate::testutil::{BlockList, CancelAfter, random_scene, simulate};
    use crate::{BucketBlock, SliceSource, reconstruct};
    use helmholtz_proto::{HadamardOrdering, PatternSpec};

    fn solve(
        spec: &PatternSpec,
        buckets: &[f64],
        channels: usize,
        block_rows: usize,
    ) -> Reconstruction {
        let rows = (buckets.len() / channels) as u64;
        let problem = Problem {
            spec,
            channels,
            rows,
        };
        let mut src = SliceSource::new(buckets, channels, block_rows);
        let control = Control::new();
        let r = reconstruct(&problem, &MethodConfig::Direct, &mut src, &control).unwrap();
        assert_eq!(control.progress(), 1.0);
        r
    }

    fn f32s(v: &[f64]) -> Vec<f32> {
        v.iter().map(|&x| x as f32).collect()
    }

    /// Block averages of t for a raster grid of side `b`.
    fn block_average(t: &[f64], w: usize, h: usize, b: usize) -> Vec<f64> {
        let bx = w.div_ceil(b);
        let mut sum = vec![0.0; bx * h.div_ceil(b)];
        let mut cnt = vec![0.0; sum.len()];
        for y in 0..h {
            for x in 0..w {
                let blk = (y / b) * bx + x / b;
                sum[blk] += t[y * w + x];
                cnt[blk] += 1.0;
            }
        }
        (0..w * h)
            .map(|p| {
                let blk = (p / w / b) * bx + (p % w) / b;
                sum[blk] / cnt[blk]
            })
            .collect()
    }

    #[test]
    fn raster_block_one_returns_t() {
        let (w, h) = (12u32, 7u32);
        let k = (w * h) as usize;
        let spec =
            PatternSpec::new(Family::Raster { block: 1, scans: 1 }, w, h, k as u64, 0).unwrap();
        let t = random_scene(k, 0.0, 1.0, 1);
        let buckets = simulate(&spec, std::slice::from_ref(&t), k as u64, |_| 1.0, 0.0);
        let r = solve(&spec, &buckets, 1, 10);
        assert!(relative_error(&r.images[0].data, &f32s(&t)) < 1e-6);
        assert_eq!(r.report.details["complete_scans"], json!(1));
    }

    #[test]
    fn raster_blocks_with_edges_and_repeats() {
        // 10 x 7 with block 3: a 4 x 3 grid whose last column is 1 wide and last row 1 tall.
        let (w, h, b) = (10u32, 7u32, 3u32);
        let blocks = 12u64;
        let k = (w * h) as usize;
        let t = random_scene(k, 0.0, 1.0, 2);
        let want = f32s(&block_average(&t, w as usize, h as usize, b as usize));
        // One scan, then 2.5 scans with per-scan gains that average to 1 on every block.
        let spec = PatternSpec::new(Family::raster_covering(b, w, h, 1000), w, h, 1000, 0).unwrap();
        let one = simulate(&spec, std::slice::from_ref(&t), blocks, |_| 1.0, 0.0);
        let r = solve(&spec, &one, 1, 5);
        assert!(relative_error(&r.images[0].data, &want) < 1e-6);
        // Repeats 0, 1, 2 of each block with gains 0.9, 1.1, 1.0 (blocks 6.. only get 2).
        let rows = 2 * blocks + blocks / 2;
        let gains = [0.9, 1.1, 1.0];
        let rep = simulate(
            &spec,
            std::slice::from_ref(&t),
            rows,
            |i| gains[(i / blocks) as usize],
            0.0,
        );
        let r = solve(&spec, &rep, 1, 7);
        assert!(relative_error(&r.images[0].data, &want) < 1e-6);
        assert_eq!(r.report.details["complete_scans"], json!(2));
        assert_eq!(r.report.details["max_repeats"], json!(3));
        // Blocks 0..6 were shown three times (gains 0.9, 1.1, 1.0), blocks 6..12 twice (0.9,
        // 1.1): both average to t, which a wrong divisor (scans, rows) would not give.
    }

    #[test]
    fn hadamard_every_ordering_and_shape_is_exact() {
        for &(w, h) in &[(8u32, 8u32), (16, 4), (2, 32), (1, 1), (32, 32), (64, 32)] {
            let k = (w * h) as usize;
            let t = random_scene(k, 0.0, 1.0, w as u64 * 1000 + h as u64);
            for ordering in HadamardOrdering::ALL {
                let spec =
                    PatternSpec::new(Family::Hadamard { ordering }, w, h, 2 * k as u64, 5).unwrap();
                let buckets = simulate(&spec, std::slice::from_ref(&t), 2 * k as u64, |_| 1.0, 0.0);
                let r = solve(&spec, &buckets, 1, 37);
                let err = relative_error(&r.images[0].data, &f32s(&t));
                assert!(err < 1e-4, "{w}x{h} {ordering:?}: relative error {err}");
                assert!((r.report.details["pair_sum_rel_std"][0].as_f64().unwrap()) < 1e-9);
                assert!(r.report.details["dark_level"][0].as_f64().unwrap().abs() < 1e-12);
            }
        }
    }

    #[test]
    fn hadamard_dark_offset_cancels_and_is_reported() {
        let (w, h) = (16u32, 8u32);
        let k = (w * h) as usize;
        let t = random_scene(k, 0.0, 1.0, 3);
        let spec = PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::CakeCutting,
            },
            w,
            h,
            2 * k as u64,
            0,
        )
        .unwrap();
        let clean = simulate(&spec, std::slice::from_ref(&t), 2 * k as u64, |_| 1.0, 0.0);
        let dark = 7.5;
        let offset: Vec<f64> = clean.iter().map(|v| v + dark).collect();
        let a = solve(&spec, &clean, 1, 100);
        let b = solve(&spec, &offset, 1, 100);
        let diff = relative_error(&b.images[0].data, &a.images[0].data);
        assert!(diff < 1e-6, "offset changed the image by {diff}");
        assert!(relative_error(&b.images[0].data, &f32s(&t)) < 1e-4);
        let d = b.report.details["dark_level"][0].as_f64().unwrap();
        assert!((d - dark).abs() < 1e-9, "dark {d}");
        // Pair sums: 1.t + 2 dark, constant.
        let sum_t: f64 = t.iter().sum();
        let mean = b.report.details["pair_sum_mean"][0].as_f64().unwrap();
        assert!((mean - (sum_t + 2.0 * dark)).abs() < 1e-9);
    }

    #[test]
    fn hadamard_pair_sums_monitor_drift() {
        let (w, h) = (8u32, 8u32);
        let k = (w * h) as usize;
        let t = random_scene(k, 0.5, 1.0, 4);
        let spec = PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::Natural,
            },
            w,
            h,
            128,
            0,
        )
        .unwrap();
        // Gain ramps linearly 1.0 -> 1.2 over the frames; both frames of a pair see nearly the
        // same gain, so s_r ~ g_r (1 . t).
        let n = 2 * k as u64;
        let buckets = simulate(
            &spec,
            std::slice::from_ref(&t),
            n,
            |i| 1.0 + 0.2 * i as f64 / n as f64,
            0.0,
        );
        let r = solve(&spec, &buckets, 1, 16);
        let dev = r.report.details["pair_sum_max_rel_dev"][0]
            .as_f64()
            .unwrap();
        let std = r.report.details["pair_sum_rel_std"][0].as_f64().unwrap();
        let mean = r.report.details["pair_sum_mean"][0].as_f64().unwrap();
        // The statistics of the pair sums, computed here the plain way.
        let sums: Vec<f64> = buckets.chunks_exact(2).map(|p| p[0] + p[1]).collect();
        let m = sums.iter().sum::<f64>() / k as f64;
        let sd = (sums.iter().map(|s| (s - m).powi(2)).sum::<f64>() / k as f64).sqrt();
        let worst = sums.iter().map(|s| (s - m).abs()).fold(0.0, f64::max);
        assert!((mean - m).abs() < 1e-9 * m);
        assert!((std - sd / m).abs() < 1e-9, "rel std {std} vs {}", sd / m);
        assert!(
            (dev - worst / m).abs() < 1e-9,
            "max rel dev {dev} vs {}",
            worst / m
        );
        // And they see the ramp: range ~0.2 about a mean ~1.1 (+-0.091), std = range / sqrt(12).
        assert!((dev - 0.1 / 1.1).abs() < 0.005, "max rel dev {dev}");
        assert!(
            (std - 0.2 / 1.1 / 12f64.sqrt()).abs() < 0.003,
            "rel std {std}"
        );
    }

    #[test]
    fn multichannel_direct() {
        let (w, h) = (8u32, 4u32);
        let k = (w * h) as usize;
        let scenes = [random_scene(k, 0.0, 1.0, 5), random_scene(k, 0.0, 3.0, 6)];
        for family in [
            Family::Hadamard {
                ordering: HadamardOrdering::Zigzag,
            },
            Family::Raster { block: 1, scans: 1 },
        ] {
            let count = if matches!(family, Family::Raster { .. }) {
                k as u64
            } else {
                2 * k as u64
            };
            let spec = PatternSpec::new(family, w, h, count, 0).unwrap();
            let buckets = simulate(&spec, &scenes, count, |_| 1.0, 0.25);
            let r = solve(&spec, &buckets, 2, 9);
            assert_eq!(r.images.len(), 2);
            for ch in 0..2 {
                let want: Vec<f32> = if spec.family().name() == "raster" {
                    // Raster has no dark cancellation: the offset appears in t.
                    scenes[ch].iter().map(|&v| (v + 0.25) as f32).collect()
                } else {
                    f32s(&scenes[ch])
                };
                assert!(
                    relative_error(&r.images[ch].data, &want) < 1e-5,
                    "{} ch {ch}",
                    spec.family().name()
                );
            }
        }
    }

    fn run_config(
        spec: &PatternSpec,
        buckets: &[f64],
        config: &MethodConfig,
    ) -> Result<Reconstruction, ReconError> {
        let problem = Problem {
            spec,
            channels: 1,
            rows: buckets.len() as u64,
        };
        reconstruct(
            &problem,
            config,
            &mut SliceSource::new(buckets, 1, 13),
            &Control::new(),
        )
    }

    #[test]
    fn levels_give_the_exact_block_average_at_every_complete_level() {
        // Square and non-square (64 x 16: levels hold min(2^j, H) * min(2^j, W) pairs).
        for &(w, h) in &[(32usize, 32usize), (64, 16)] {
            let k = w * h;
            let t = random_scene(k, 0.0, 1.0, 11);
            let ordering = HadamardOrdering::RussianDoll;
            let spec = PatternSpec::new(
                Family::Hadamard { ordering },
                w as u32,
                h as u32,
                2 * k as u64,
                0,
            )
            .unwrap();
            let all = simulate(&spec, std::slice::from_ref(&t), 2 * k as u64, |_| 1.0, 3.0);
            let max_level = w.max(h).trailing_zeros();
            for j in 0..=max_level {
                let pairs = level_pairs(w, h, j);
                // The rows of exactly level j, then a few more frames of level j + 1 (still only
                // level j complete), as a session stopped mid-level.
                for extra in [0, 2] {
                    let frames = (2 * pairs + extra).min(2 * k);
                    let r =
                        run_config(&spec, &all[..frames], &MethodConfig::Levels { level: None })
                            .unwrap();
                    assert_eq!(
                        r.report.details["level"],
                        json!(j),
                        "{w}x{h} level {j} +{extra}"
                    );
                    let (bw, bh) = ((w >> j).max(1), (h >> j).max(1));
                    // The block average over bw x bh blocks (block_average takes square blocks,
                    // so average explicitly).
                    let mut want = vec![0.0; k];
                    for y in 0..h {
                        for x in 0..w {
                            let (bx, by) = (x / bw * bw, y / bh * bh);
                            let mut sum = 0.0;
                            for yy in by..by + bh {
                                for xx in bx..bx + bw {
                                    sum += t[yy * w + xx];
                                }
                            }
                            want[y * w + x] = sum / (bw * bh) as f64;
                        }
                    }
                    let err = relative_error(&r.images[0].data, &f32s(&want));
                    assert!(err < 1e-5, "{w}x{h} level {j}: {err}");
                    assert!(r.report.held_out.is_none() && r.report.held_out_unavailable.is_some());
                }
            }
            // An explicit coarser level from a finer session; a level not reached is refused.
            let r = run_config(&spec, &all, &MethodConfig::Levels { level: Some(1) }).unwrap();
            assert_eq!(r.report.details["resolution"], json!([2, 2]));
            let half = &all[..2 * level_pairs(w, h, 2)];
            let e = run_config(&spec, half, &MethodConfig::Levels { level: Some(3) })
                .unwrap_err()
                .to_string();
            assert!(e.contains("level 3 is not complete"), "{e}");
        }
    }

    #[test]
    fn zero_filled_is_the_projection_on_the_measured_coefficients() {
        let (w, h) = (16usize, 16usize);
        let k = w * h;
        let t = random_scene(k, 0.0, 1.0, 12);
        for ordering in [HadamardOrdering::Sequency, HadamardOrdering::Zigzag] {
            let spec = PatternSpec::new(
                Family::Hadamard { ordering },
                w as u32,
                h as u32,
                2 * k as u64,
                0,
            )
            .unwrap();
            let all = simulate(&spec, std::slice::from_ref(&t), 2 * k as u64, |_| 1.0, 0.0);
            // All pairs: the exact inverse.
            let full = run_config(&spec, &all, &MethodConfig::ZeroFilled).unwrap();
            assert!(relative_error(&full.images[0].data, &f32s(&t)) < 1e-5);
            // 40 pairs (+ an odd frame, ignored): H^T S^T S H t / k, against a dense reference.
            let r = run_config(&spec, &all[..81], &MethodConfig::ZeroFilled).unwrap();
            assert_eq!(r.report.details["pairs_used"], json!(40));
            let op = crate::ops::HadamardOperator::from_spec(&spec, 80).unwrap();
            let mut coeff = vec![0.0; 40];
            op.apply(&t, &mut coeff);
            let mut want = vec![0.0; k];
            op.adjoint(&coeff, &mut want);
            let err = relative_error(&r.images[0].data, &f32s(&want));
            assert!(err < 1e-5, "{ordering:?}: {err}");
        }
        let bern = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 8, 8, 10, 0).unwrap();
        let e = run_config(&bern, &[1.0; 10], &MethodConfig::ZeroFilled)
            .unwrap_err()
            .to_string();
        assert!(e.contains("zero_filled inverts Hadamard"), "{e}");
        let seq = PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::Sequency,
            },
            8,
            8,
            128,
            0,
        )
        .unwrap();
        let e = run_config(&seq, &[1.0; 8], &MethodConfig::Levels { level: None })
            .unwrap_err()
            .to_string();
        assert!(e.contains("russian_doll"), "{e}");
    }

    #[test]
    fn direct_refuses_incomplete_or_other_families() {
        let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 8, 8, 200, 0).unwrap();
        let problem = Problem {
            spec: &spec,
            channels: 1,
            rows: 100,
        };
        let mut src = BlockList(Default::default());
        assert!(matches!(
            run(&problem, &MethodConfig::Direct, &mut src, &Control::new()),
            Err(ReconError::Unsolvable(_))
        ));
        let spec = PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::Natural,
            },
            8,
            8,
            100,
            0,
        )
        .unwrap();
        let problem = Problem {
            spec: &spec,
            channels: 1,
            rows: 100,
        };
        assert!(matches!(
            run(&problem, &MethodConfig::Direct, &mut src, &Control::new()),
            Err(ReconError::Unsolvable(_))
        ));
        // Complete spec, but the source stops early.
        let spec = PatternSpec::new(Family::Raster { block: 1, scans: 1 }, 4, 4, 16, 0).unwrap();
        let problem = Problem {
            spec: &spec,
            channels: 1,
            rows: 16,
        };
        let mut src = BlockList(
            vec![BucketBlock {
                first_row: 0,
                values: vec![1.0; 10],
            }]
            .into(),
        );
        assert!(matches!(
            run(&problem, &MethodConfig::Direct, &mut src, &Control::new()),
            Err(ReconError::Unsolvable(_))
        ));
        // Malformed blocks.
        let problem = Problem {
            spec: &spec,
            channels: 2,
            rows: 16,
        };
        let mut src = BlockList(
            vec![BucketBlock {
                first_row: 0,
                values: vec![1.0; 9],
            }]
            .into(),
        );
        assert!(matches!(
            run(&problem, &MethodConfig::Direct, &mut src, &Control::new()),
            Err(ReconError::BadRows(_))
        ));
        let mut src = BlockList(
            vec![
                BucketBlock {
                    first_row: 0,
                    values: vec![1.0; 8],
                },
                BucketBlock {
                    first_row: 5,
                    values: vec![1.0; 8],
                },
            ]
            .into(),
        );
        assert!(matches!(
            run(&problem, &MethodConfig::Direct, &mut src, &Control::new()),
            Err(ReconError::BadRows(_))
        ));
    }

    #[test]
    fn direct_cancels() {
        let spec = PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::Natural,
            },
            16,
            16,
            512,
            0,
        )
        .unwrap();
        let buckets = vec![1.0; 512];
        let problem = Problem {
            spec: &spec,
            channels: 1,
            rows: 512,
        };
        let control = Control::new();
        let mut src = CancelAfter {
            inner: SliceSource::new(&buckets, 1, 64),
            control: &control,
            after: 2,
            seen: 0,
        };
        assert!(matches!(
            run(&problem, &MethodConfig::Direct, &mut src, &control),
            Err(ReconError::Cancelled)
        ));
    }
}
