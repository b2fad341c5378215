//! Live preview: a progressive dual image, updated row by row while a session uploads.
//!
//! A [`Preview`] is fed the session's rows in order ([`Preview::push_rows`]) and gives the image
//! of the rows seen so far at any time ([`Preview::image`]). It knows nothing of where rows come
//! from; its state is O(k) per channel whatever the number of rows, and a row costs O(k) (random
//! families, raster: O(1) once its block is known; Hadamard: O(1), the transform is paid when an
//! image is asked for). Which image depends on what the patterns allow:
//!
//! - **Bernoulli, speckle**: differential ghost imaging (DGI, Ferri 2010),
//!   `G_D(x) = <c p(x)> - (<c>/<R>) <R p(x)>` with `R_i` the pattern sum, accumulated with the
//!   bucket shifted by `a R` (`a = c_r / R_r` of the first row with `R_r > 0`) as the correlators
//!   do ([`crate::correlate`]): after every row it equals `dgi` on those rows.
//! - **Hadamard** (split pairs): the zero-filled inverse, `t = H d / k` with `d_n = y+ - y-` at the
//!   natural index of every complete pair seen and 0 elsewhere: `zero_filled` on those rows, and
//!   after all `2k` frames the exact image (`direct`).
//! - **adaptive_hadamard**: as Hadamard, at the natural indices the session chose;
//!   **adaptive_haar**: the zero-filled Haar inverse, coefficient `(y+ - y-) / 2^s` at each
//!   chosen Mallat index (`zero_filled` and `direct` on those rows). The preview needs the
//!   indices: build it from the spec resolved so far and call [`Preview::resolve`] as batches are
//!   issued.
//! - **Raster**: the running raster image, each measured block its mean bucket over its pixels and
//!   unmeasured blocks 0: after one complete scan it equals `direct`.
//!
//! A camera session (frames of m pixels) is previewed by its caller as one bucket, the sum of the
//! camera pixels (the camera as a bucket detector: by reciprocity the dual image seen from the
//! projector); the numerics here see one channel.

use helmholtz_proto::{Family, HaarFunction, PatternGenerator, PatternSpec};

use crate::DualImage;
use crate::fwht::fwht;
use crate::linop::LinearOperator;
use crate::transforms::wavelet::Wavelet2d;

/// The progressive image of one session, per channel (see the module docs).
#[derive(Clone, Debug)]
pub struct Preview {
    spec: PatternSpec,
    generator: PatternGenerator,
    channels: usize,
    rows: u64,
    state: State,
}

#[derive(Clone, Debug)]
enum State {
    Dgi(Dgi),
    Hadamard(Hadamard),
    Haar(Haar),
    Raster(Raster),
}

/// adaptive_haar: orthonormal coefficients at their Mallat index.
#[derive(Clone, Debug)]
struct Haar {
    /// `(y+ - y-) / 2^s`, channel after channel (`channels * k`).
    coefficients: Vec<f64>,
    positive: Vec<f64>,
    /// Single frames (PATTERNS.md, "Single frames"): each `y-` from its block's light. `None`
    /// for split pairs, and once a frame arrived before its index was resolved (its block's
    /// light, and so every finer one, is then unknown: the image stays as it was).
    single: Option<crate::adaptive::SingleFrameDecoder>,
}

/// DGI sums (module docs of [`crate::correlate`], "Formulas").
#[derive(Clone, Debug)]
struct Dgi {
    /// `a` per channel, fixed at the first row with `R > 0`.
    shift: Option<Vec<f64>>,
    sum_shifted: Vec<f64>,
    sum_r: f64,
    /// `sum_i c'_i p_i(x)`, channel after channel (`channels * k`).
    acc: Vec<f64>,
    /// `sum_i R_i p_i(x)`.
    base: Vec<f64>,
    /// Scratch: one pattern.
    bits: Vec<u64>,
    values: Vec<f32>,
}

#[derive(Clone, Debug)]
struct Hadamard {
    /// `y+ - y-` at the natural index, channel after channel (`channels * k`).
    d: Vec<f64>,
    /// The P+ frame of the pair in progress.
    positive: Vec<f64>,
}

#[derive(Clone, Debug)]
struct Raster {
    /// Per block and channel (`blocks * channels`).
    sums: Vec<f64>,
    counts: Vec<u64>,
}

impl Preview {
    /// An empty preview of a session of `spec` with `channels` bucket channels (>= 1).
    pub fn new(spec: &PatternSpec, channels: usize) -> Preview {
        assert!(channels > 0, "a preview needs at least one channel");
        let k = spec.pixels();
        let generator = PatternGenerator::new(spec);
        let state = match spec.family() {
            Family::Bernoulli { .. } | Family::Speckle { .. } => State::Dgi(Dgi {
                shift: None,
                sum_shifted: vec![0.0; channels],
                sum_r: 0.0,
                acc: vec![0.0; channels * k],
                base: vec![0.0; k],
                bits: vec![0; generator.words_per_pattern()],
                values: if spec.family().is_binary() {
                    Vec::new()
                } else {
                    vec![0.0; k]
                },
            }),
            Family::AdaptiveHaar { .. } => State::Haar(Haar {
                coefficients: vec![0.0; channels * k],
                positive: vec![0.0; channels],
                single: spec
                    .adaptive_single()
                    .then(|| crate::adaptive::SingleFrameDecoder::new(spec.width(), channels)),
            }),
            Family::Hadamard { .. } | Family::AdaptiveHadamard { .. } => {
                State::Hadamard(Hadamard {
                    d: vec![0.0; channels * k],
                    positive: vec![0.0; channels],
                })
            }
            Family::Raster { .. } => {
                let (_, bx, by) = spec.raster_grid().expect("raster");
                let blocks = bx as usize * by as usize;
                State::Raster(Raster {
                    sums: vec![0.0; blocks * channels],
                    counts: vec![0; blocks],
                })
            }
        };
        Preview {
            spec: spec.clone(),
            generator,
            channels,
            rows: 0,
            state,
        }
    }

    /// The reconstruction method the preview equals on the rows seen: `dgi` (Bernoulli,
    /// speckle), `zero_filled` (Hadamard) or `direct` (raster, once a scan is complete).
    pub fn method(&self) -> &'static str {
        match self.state {
            State::Dgi(_) => "dgi",
            State::Hadamard(_) | State::Haar(_) => "zero_filled",
            State::Raster(_) => "direct",
        }
    }

    /// An adaptive session: `spec` is the session's spec resolved with every index issued so
    /// far (the same declaration, and a sequence that extends the one this preview had). Rows
    /// of pairs not resolved when they are pushed are counted but never shown: resolve first.
    pub fn resolve(&mut self, spec: &PatternSpec) {
        assert!(
            spec == &self.spec,
            "a preview resolves its own session's spec"
        );
        let old = self.spec.adaptive_indices().unwrap_or(&[]);
        let new = spec.adaptive_indices().unwrap_or(&[]);
        assert!(
            new.starts_with(old),
            "an adaptive session's indices only grow"
        );
        self.spec = spec.clone();
        self.generator = PatternGenerator::new(spec);
    }

    /// Rows seen so far.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Appends the next rows (row-major, `rows x channels`, continuing at [`Preview::rows`]).
    /// Rows past the spec's count are ignored.
    pub fn push_rows(&mut self, values: &[f64]) {
        let m = self.channels;
        assert!(
            values.len().is_multiple_of(m),
            "rows must hold {m} values each"
        );
        for row in values.chunks_exact(m) {
            if self.rows >= self.spec.count() {
                return;
            }
            self.push_row(row);
            self.rows += 1;
        }
    }

    fn push_row(&mut self, c: &[f64]) {
        let i = self.rows;
        let k = self.spec.pixels();
        match &mut self.state {
            State::Dgi(s) => {
                let binary = s.values.is_empty();
                let r = if binary {
                    self.generator
                        .fill_bits(i, &mut s.bits)
                        .expect("binary family");
                    s.bits.iter().map(|w| w.count_ones() as u64).sum::<u64>() as f64
                } else {
                    self.generator.fill_values(i, &mut s.values);
                    s.values.iter().map(|&v| v as f64).sum()
                };
                if s.shift.is_none() && r > 0.0 {
                    s.shift = Some(c.iter().map(|v| v / r).collect());
                }
                s.sum_r += r;
                // Rows before the shift is fixed have R = 0: their shifted value is c whatever a.
                let shifted: Vec<f64> = match &s.shift {
                    Some(a) => c.iter().zip(a).map(|(v, a)| v - a * r).collect(),
                    None => c.to_vec(),
                };
                for (sum, v) in s.sum_shifted.iter_mut().zip(&shifted) {
                    *sum += v;
                }
                if r == 0.0 {
                    return; // an all-off pattern adds nothing at any pixel
                }
                if binary {
                    for (w, &word) in s.bits.iter().enumerate() {
                        let mut bits = word;
                        while bits != 0 {
                            let x = w * 64 + bits.trailing_zeros() as usize;
                            bits &= bits - 1;
                            s.base[x] += r;
                            for (ch, v) in shifted.iter().enumerate() {
                                s.acc[ch * k + x] += v;
                            }
                        }
                    }
                } else {
                    for (x, &p) in s.values.iter().enumerate() {
                        let p = p as f64;
                        s.base[x] += r * p;
                        for (ch, v) in shifted.iter().enumerate() {
                            s.acc[ch * k + x] += v * p;
                        }
                    }
                }
            }
            State::Hadamard(s) => {
                if i >= 2 * k as u64 {
                    return;
                }
                // An adaptive session's pair whose index is not resolved yet cannot be shown.
                let Some(frame) = self.generator.split_frame(i) else {
                    debug_assert!(self.spec.is_adaptive(), "hadamard frames are known");
                    return;
                };
                if frame.positive {
                    s.positive.copy_from_slice(c);
                } else {
                    let n = frame.natural as usize;
                    for (ch, (&yp, &ym)) in s.positive.iter().zip(c).enumerate() {
                        s.d[ch * k + n] = yp - ym;
                    }
                }
            }
            State::Haar(s) if self.spec.adaptive_single() => {
                let Some(n) = self.generator.adaptive_index(i) else {
                    s.single = None; // not resolved yet: counted, and nothing after it shown
                    return;
                };
                let Some(decoder) = &mut s.single else {
                    return;
                };
                let frames: Vec<f64> = if n == 0 {
                    if i == 0 {
                        s.positive.copy_from_slice(c);
                        return;
                    }
                    s.positive.iter().chain(c).copied().collect()
                } else {
                    c.to_vec()
                };
                let mut pairs = Vec::with_capacity(self.channels);
                decoder.decode(n, &frames, &mut pairs);
                let gain = HaarFunction::new(self.spec.width(), n).side() as f64;
                for (ch, (yp, ym)) in pairs.into_iter().enumerate() {
                    s.coefficients[ch * k + n as usize] = (yp - ym) / gain;
                }
            }
            State::Haar(s) => {
                let Some(n) = self.generator.adaptive_index(i) else {
                    return; // not resolved yet: counted, not shown
                };
                if i.is_multiple_of(2) {
                    s.positive.copy_from_slice(c);
                } else {
                    let gain = HaarFunction::new(self.spec.width(), n).side() as f64;
                    for (ch, (&yp, &ym)) in s.positive.iter().zip(c).enumerate() {
                        s.coefficients[ch * k + n as usize] = (yp - ym) / gain;
                    }
                }
            }
            State::Raster(s) => {
                let block = self.generator.raster_block(i).expect("raster") as usize;
                s.counts[block] += 1;
                let m = self.channels;
                for (sum, v) in s.sums[block * m..(block + 1) * m].iter_mut().zip(c) {
                    *sum += v;
                }
            }
        }
    }

    /// The image of channel `channel` from the rows seen so far (all zeros before the first).
    pub fn image(&self, channel: usize) -> DualImage {
        assert!(channel < self.channels, "no channel {channel}");
        let (w, h) = (self.spec.width() as usize, self.spec.height() as usize);
        let k = w * h;
        let data: Vec<f32> = match &self.state {
            State::Dgi(s) => {
                let n = self.rows as f64;
                if self.rows == 0 {
                    vec![0.0; k]
                } else {
                    let beta = if s.sum_r > 0.0 {
                        s.sum_shifted[channel] / s.sum_r
                    } else {
                        0.0
                    };
                    s.acc[channel * k..(channel + 1) * k]
                        .iter()
                        .zip(&s.base)
                        .map(|(a, b)| ((a - beta * b) / n) as f32)
                        .collect()
                }
            }
            State::Hadamard(s) => {
                let mut t = s.d[channel * k..(channel + 1) * k].to_vec();
                fwht(&mut t);
                let scale = 1.0 / k as f64;
                t.iter().map(|v| (v * scale) as f32).collect()
            }
            State::Haar(s) => {
                let wavelet = Wavelet2d::haar(w, h);
                let mut t = vec![0.0; k];
                wavelet.adjoint(&s.coefficients[channel * k..(channel + 1) * k], &mut t);
                t.iter().map(|&v| v as f32).collect()
            }
            State::Raster(s) => {
                let (block, bx, _) = self.spec.raster_grid().expect("raster");
                let (block, bx) = (block as usize, bx as usize);
                let m = self.channels;
                (0..k)
                    .map(|p| {
                        let (x, y) = (p % w, p / w);
                        let blk = (y / block) * bx + x / block;
                        let count = s.counts[blk];
                        if count == 0 {
                            return 0.0;
                        }
                        let (cx, cy) = (blk % bx, blk / bx);
                        let pixels = (block.min(w - cx * block) * block.min(h - cy * block)) as f64;
                        (s.sums[blk * m + channel] / count as f64 / pixels) as f32
                    })
                    .collect()
            }
        };
        DualImage {
            width: self.spec.width(),
            height: self.spec.height(),
            data,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{random_scene, simulate};
    use crate::{Control, MethodConfig, Problem, SliceSource, reconstruct};
    use helmholtz_proto::HadamardOrdering;

    /// The reference reconstruction of `rows` rows by `method`.
    fn reference(
        spec: &PatternSpec,
        buckets: &[f64],
        channels: usize,
        rows: u64,
        method: &str,
    ) -> Vec<DualImage> {
        let problem = Problem {
            spec,
            channels,
            rows,
        };
        let config = MethodConfig::parse(method, &serde_json::json!({})).unwrap();
        let used = &buckets[..rows as usize * channels];
        reconstruct(
            &problem,
            &config,
            &mut SliceSource::new(used, channels, 97),
            &Control::new(),
        )
        .unwrap()
        .images
    }

    /// Max |a - b| relative to max |b|.
    fn close(a: &DualImage, b: &DualImage, tol: f64) {
        assert_eq!((a.width, a.height), (b.width, b.height));
        let scale = b.data.iter().fold(0f64, |m, v| m.max(v.abs() as f64));
        let worst = a
            .data
            .iter()
            .zip(&b.data)
            .fold(0f64, |m, (x, y)| m.max((*x as f64 - *y as f64).abs()));
        assert!(
            worst <= tol * scale.max(1e-30),
            "differs by {worst} (scale {scale})"
        );
    }

    /// Feeds `buckets` in uneven pieces, checking against `method` at a few prefixes.
    fn check_prefixes(spec: &PatternSpec, buckets: &[f64], channels: usize, prefixes: &[u64]) {
        let mut preview = Preview::new(spec, channels);
        let method = preview.method();
        let mut fed = 0u64;
        for &end in prefixes {
            // Uneven pieces: the result must not depend on how rows are split.
            while fed < end {
                let step = (fed % 7 + 1).min(end - fed);
                preview
                    .push_rows(&buckets[fed as usize * channels..(fed + step) as usize * channels]);
                fed += step;
            }
            assert_eq!(preview.rows(), end);
            let want = reference(spec, buckets, channels, end, method);
            for (ch, image) in want.iter().enumerate() {
                close(&preview.image(ch), image, 1e-5);
            }
        }
    }

    #[test]
    fn bernoulli_preview_is_dgi_of_the_rows_so_far() {
        let spec = PatternSpec::new(Family::Bernoulli { fill: 0.3 }, 16, 12, 600, 5).unwrap();
        let scenes = [
            random_scene(192, 0.0, 1.0, 1),
            random_scene(192, 0.5, 2.0, 2),
        ];
        let c = simulate(&spec, &scenes, 600, |i| 1.0 + 0.01 * (i % 5) as f64, 3.0);
        check_prefixes(&spec, &c, 2, &[1, 64, 65, 333, 600]);
    }

    #[test]
    fn speckle_preview_is_dgi_of_the_rows_so_far() {
        let spec = PatternSpec::new(Family::Speckle { grain: 2 }, 10, 10, 300, 9).unwrap();
        let scenes = [random_scene(100, 0.0, 1.0, 3)];
        let c = simulate(&spec, &scenes, 300, |_| 1.0, 0.5);
        check_prefixes(&spec, &c, 1, &[8, 100, 300]);
    }

    #[test]
    fn hadamard_preview_is_zero_filled_and_exact_when_complete() {
        for ordering in [HadamardOrdering::Natural, HadamardOrdering::RussianDoll] {
            let spec = PatternSpec::new(Family::Hadamard { ordering }, 16, 8, 256, 0).unwrap();
            let t = random_scene(128, 0.0, 1.0, 4);
            let c = simulate(&spec, std::slice::from_ref(&t), 256, |_| 1.0, 0.2);
            // An odd prefix: the pending P+ frame of an incomplete pair is not used.
            check_prefixes(&spec, &c, 1, &[2, 33, 128, 256]);
            let mut preview = Preview::new(&spec, 1);
            preview.push_rows(&c);
            close(
                &preview.image(0),
                &reference(&spec, &c, 1, 256, "direct")[0],
                1e-6,
            );
            let exact = DualImage {
                width: 16,
                height: 8,
                data: t.iter().map(|&v| v as f32).collect(),
            };
            close(&preview.image(0), &exact, 1e-6);
        }
    }

    #[test]
    fn raster_preview_is_the_running_scan() {
        let spec = PatternSpec::new(Family::raster_covering(3, 10, 7, 24), 10, 7, 24, 0).unwrap();
        let scenes = [random_scene(70, 0.0, 1.0, 6), random_scene(70, 1.0, 2.0, 7)];
        let c = simulate(&spec, &scenes, 24, |_| 1.0, 0.0);
        // One scan is 4 x 3 = 12 blocks; the second scan repeats it.
        check_prefixes(&spec, &c, 2, &[12, 24]);
        // Mid-scan: the measured blocks are their block mean, the others 0.
        let mut preview = Preview::new(&spec, 2);
        preview.push_rows(&c[..5 * 2]);
        let image = preview.image(1);
        let full = reference(&spec, &c, 2, 12, "direct");
        for (p, (&v, &want)) in image.data.iter().zip(&full[1].data).enumerate() {
            let blk = (p / 10 / 3) * 4 + (p % 10) / 3;
            if blk < 5 {
                assert!((v - want).abs() <= 1e-6 * want.abs(), "pixel {p}");
            } else {
                assert_eq!(v, 0.0, "pixel {p}");
            }
        }
    }

    #[test]
    fn no_rows_is_a_zero_image_and_extra_rows_are_ignored() {
        let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 8, 8, 10, 1).unwrap();
        let mut preview = Preview::new(&spec, 1);
        assert!(preview.image(0).data.iter().all(|&v| v == 0.0));
        preview.push_rows(&[1.0; 12]);
        assert_eq!(preview.rows(), 10);
    }
}
