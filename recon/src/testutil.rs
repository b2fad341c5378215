//! Test helpers: a deterministic random stream and a bucket simulator built on the pattern
//! generator (c_i = gain_i * t . p_i + offset, one `t` per channel).

use helmholtz_proto::patterns::rng::stream_word;
use helmholtz_proto::{PatternGenerator, PatternSpec};

use super::{BucketBlock, BucketSource, Control, SourceError};

/// Counter-based SplitMix64 stream.
pub(crate) struct Rng {
    seed: u64,
    counter: u64,
}

impl Rng {
    pub(crate) fn new(seed: u64) -> Self {
        Rng { seed, counter: 0 }
    }
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.counter += 1;
        stream_word(self.seed, self.counter)
    }
    /// Uniform in [0, 1).
    pub(crate) fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
    /// Standard normal (Box-Muller).
    pub(crate) fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// `k` values uniform in [lo, hi).
pub(crate) fn random_scene(k: usize, lo: f64, hi: f64, seed: u64) -> Vec<f64> {
    let mut rng = Rng::new(seed);
    (0..k).map(|_| lo + (hi - lo) * rng.uniform()).collect()
}

/// Buckets for rows `0..rows`, row-major `rows x channels`:
/// `c[i][j] = gain(i) * (t_j . p_i) + offset`.
pub(crate) fn simulate(
    spec: &PatternSpec,
    scenes: &[Vec<f64>],
    rows: u64,
    gain: impl Fn(u64) -> f64,
    offset: f64,
) -> Vec<f64> {
    let generator = PatternGenerator::new(spec);
    let k = spec.pixels();
    let mut p = vec![0f32; k];
    let mut out = Vec::with_capacity(rows as usize * scenes.len());
    for i in 0..rows {
        generator.fill_values(i, &mut p);
        let g = gain(i);
        for t in scenes {
            let dot: f64 = t.iter().zip(&p).map(|(&a, &b)| a * b as f64).sum();
            out.push(g * dot + offset);
        }
    }
    out
}

/// Pearson correlation of two equally long sequences.
pub(crate) fn pearson(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (&x, &y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}

pub(crate) fn to_f64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

/// A source that delivers hand-made blocks (malformed ones included), then `None`.
pub(crate) struct BlockList(pub std::collections::VecDeque<BucketBlock>);

impl BucketSource for BlockList {
    fn next_block(&mut self) -> Result<Option<BucketBlock>, SourceError> {
        Ok(self.0.pop_front())
    }
}

/// Wraps a source and raises the cancel flag after `after` blocks.
pub(crate) struct CancelAfter<'a, S> {
    pub inner: S,
    pub control: &'a Control,
    pub after: usize,
    pub seen: usize,
}

impl<S: BucketSource> BucketSource for CancelAfter<'_, S> {
    fn next_block(&mut self) -> Result<Option<BucketBlock>, SourceError> {
        self.seen += 1;
        if self.seen > self.after {
            self.control.cancel();
        }
        self.inner.next_block()
    }
}
