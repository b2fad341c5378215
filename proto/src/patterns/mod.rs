//! The seed -> pattern generator: the exact definition is `proto/PATTERNS.md`.
//!
//! Pattern `i` is a pure function of `(spec, i)`: no state carries from one pattern to the next, so
//! patterns can be generated in any order and in parallel. `PatternGenerator` only precomputes
//! what depends on the spec alone (the Hadamard ordering table, the Bernoulli fill digits).

pub mod adaptive;
mod convert;
pub mod hadamard;
pub mod rng;
mod spec;

pub use adaptive::HaarFunction;
pub use convert::ProtoSpecError;
pub use hadamard::{HadamardOrdering, HadamardPlan};
pub use spec::{
    AdaptiveFrames, ErrorEstimate, FILL_BITS, Family, HAAR_PERSISTENCE, HADAMARD_PERSISTENCE,
    MAX_COUNT, MAX_PIXELS, MAX_SIDE, PatternSpec, SpecError, fill_quantum,
};

use rng::stream_word;

/// Which Hadamard row a split frame shows, and with which polarity.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SplitFrame {
    /// Row index in the spec's ordering (frame / 2).
    pub row: u64,
    /// Natural (Sylvester) index `u * W + v` of that row.
    pub natural: u64,
    /// True for P+ = (1 + h) / 2 (even frames), false for P- = (1 - h) / 2 (odd frames).
    pub positive: bool,
}

/// Generates patterns of one spec. Cheap to clone; `Send + Sync`, so one generator can serve
/// many threads.
#[derive(Clone, Debug)]
pub struct PatternGenerator {
    spec: PatternSpec,
    kind: Kind,
}

#[derive(Clone, Debug)]
enum Kind {
    Raster {
        block: u32,
        blocks_x: u64,
        blocks: u64,
    },
    /// Binary digits q_1..q_d of the quantised fill (q = 0.q_1 q_2 ... q_d, q_d = 1).
    Bernoulli {
        digits: Vec<bool>,
    },
    Hadamard {
        plan: HadamardPlan,
    },
    Speckle {
        grain: u32,
        cells_x: u64,
        cells: u64,
    },
    /// Pair `r` shows basis function `indices[r]` (None: an unresolved spec, no frames).
    Adaptive {
        haar: bool,
        /// Single frames (PATTERNS.md, "Single frames"): frame `f >= 2` shows index `f - 1`.
        single: bool,
        indices: Option<std::sync::Arc<[u32]>>,
    },
}

/// The family has grey levels; it cannot be packed as bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("this pattern family has grey levels, not bits")]
pub struct NotBinary;

impl PatternGenerator {
    pub fn new(spec: &PatternSpec) -> Self {
        let kind = match *spec.family() {
            Family::Raster { block, .. } => {
                let (_, bx, by) = spec.raster_grid().expect("raster");
                Kind::Raster {
                    block,
                    blocks_x: bx as u64,
                    blocks: bx as u64 * by as u64,
                }
            }
            Family::Bernoulli { fill } => {
                let q = fill_quantum(fill);
                let d = FILL_BITS - q.trailing_zeros();
                let odd = q >> q.trailing_zeros();
                let digits = (1..=d).map(|j| (odd >> (d - j)) & 1 == 1).collect();
                Kind::Bernoulli { digits }
            }
            Family::Hadamard { ordering } => Kind::Hadamard {
                plan: HadamardPlan::new(spec.width(), spec.height(), ordering),
            },
            Family::AdaptiveHaar { .. } | Family::AdaptiveHadamard { .. } => Kind::Adaptive {
                haar: matches!(spec.family(), Family::AdaptiveHaar { .. }),
                single: spec.adaptive_single(),
                indices: spec.adaptive_indices().map(Into::into),
            },
            Family::Speckle { grain } => {
                let cx = spec.width().div_ceil(grain) as u64;
                let cy = spec.height().div_ceil(grain) as u64;
                Kind::Speckle {
                    grain,
                    cells_x: cx,
                    cells: cx * cy,
                }
            }
        };
        PatternGenerator {
            spec: spec.clone(),
            kind,
        }
    }

    pub fn spec(&self) -> &PatternSpec {
        &self.spec
    }

    /// 64-bit words per packed pattern: ceil(k / 64).
    pub fn words_per_pattern(&self) -> usize {
        self.spec.pixels().div_ceil(64)
    }

    /// For Hadamard and resolved adaptive Hadamard specs: the row and polarity of `frame`.
    pub fn split_frame(&self, frame: u64) -> Option<SplitFrame> {
        let row = frame / 2;
        let natural = match &self.kind {
            Kind::Hadamard { plan } => plan.natural_index(row),
            Kind::Adaptive {
                haar: false,
                single: false,
                indices: Some(indices),
            } => *indices.get(row as usize)? as u64,
            _ => return None,
        };
        Some(SplitFrame {
            row,
            natural,
            positive: frame.is_multiple_of(2),
        })
    }

    /// For a resolved adaptive spec: the basis index frame `frame` shows (half of a split pair,
    /// or with single frames its `P+` but for index 0).
    pub fn adaptive_index(&self, frame: u64) -> Option<u32> {
        match &self.kind {
            Kind::Adaptive {
                indices: Some(indices),
                single,
                ..
            } => indices
                .get(adaptive_frame(*single, frame).0 as usize)
                .copied(),
            _ => None,
        }
    }

    /// Raster: index of the block pattern `i` lights (patterns cycle through the blocks).
    pub fn raster_block(&self, i: u64) -> Option<u64> {
        match &self.kind {
            Kind::Raster { blocks, .. } => Some(i % blocks),
            _ => None,
        }
    }

    /// Pattern `i` as values in [0, 1], row-major (`out.len() == width * height`).
    pub fn fill_values(&self, i: u64, out: &mut [f32]) {
        let k = self.spec.pixels();
        assert_eq!(out.len(), k, "output must hold width * height values");
        match &self.kind {
            Kind::Speckle {
                grain,
                cells_x,
                cells,
            } => {
                let w = self.spec.width() as usize;
                let g = *grain as usize;
                let base = i.wrapping_mul(*cells);
                for (y, row) in out.chunks_exact_mut(w).enumerate() {
                    let cy = (y / g) as u64;
                    for (x, px) in row.iter_mut().enumerate() {
                        let cell = cy * cells_x + (x / g) as u64;
                        *px = speckle_level(stream_word(self.spec.seed(), base.wrapping_add(cell)));
                    }
                }
            }
            _ => {
                let mut words = vec![0u64; self.words_per_pattern()];
                self.fill_bits(i, &mut words).expect("binary family");
                for (p, px) in out.iter_mut().enumerate() {
                    *px = ((words[p / 64] >> (p % 64)) & 1) as f32;
                }
            }
        }
    }

    /// Pattern `i` of a binary family, packed: pixel p is bit (p % 64) of word p / 64; bits past
    /// k in the last word are zero.
    pub fn fill_bits(&self, i: u64, out: &mut [u64]) -> Result<(), NotBinary> {
        let k = self.spec.pixels();
        let nw = self.words_per_pattern();
        assert_eq!(out.len(), nw, "output must hold ceil(k / 64) words");
        match &self.kind {
            Kind::Speckle { .. } => return Err(NotBinary),
            Kind::Bernoulli { digits } => {
                let d = digits.len() as u64;
                let seed = self.spec.seed();
                let first = i.wrapping_mul(nw as u64).wrapping_mul(d);
                for (w, word) in out.iter_mut().enumerate() {
                    let base = first.wrapping_add(w as u64 * d);
                    let mut r = 0u64;
                    for j in (0..digits.len()).rev() {
                        let v = stream_word(seed, base.wrapping_add(j as u64));
                        r = if digits[j] { v | r } else { v & r };
                    }
                    *word = r;
                }
            }
            Kind::Raster {
                block,
                blocks_x,
                blocks,
            } => {
                out.fill(0);
                let b = i % blocks;
                let (bx, by) = (b % blocks_x, b / blocks_x);
                let (w, h) = (self.spec.width() as u64, self.spec.height() as u64);
                let block = *block as u64;
                for y in by * block..((by + 1) * block).min(h) {
                    for x in bx * block..((bx + 1) * block).min(w) {
                        let p = (y * w + x) as usize;
                        out[p / 64] |= 1 << (p % 64);
                    }
                }
            }
            Kind::Adaptive {
                haar,
                single,
                indices,
            } => {
                let Some(indices) = indices else {
                    panic!(
                        "{} frame {i}: the spec is not resolved (no pattern indices yet; \
                         see PatternSpec::with_indices)",
                        self.spec.family().name()
                    );
                };
                let (position, positive) = adaptive_frame(*single, i);
                let Some(&n) = indices.get(position as usize) else {
                    panic!(
                        "{} frame {i} does not exist: the session showed {} {}",
                        self.spec.family().name(),
                        indices.len(),
                        if *single { "indices" } else { "split pairs" }
                    );
                };
                let w = self.spec.width();
                let want = if positive { 1 } else { -1 };
                out.fill(0);
                if *haar {
                    let f = HaarFunction::new(w, n);
                    for y in f.y0..f.y0 + f.side() {
                        for x in f.x0..f.x0 + f.side() {
                            if f.sign(x, y) == want {
                                let p = (y * w + x) as usize;
                                out[p / 64] |= 1 << (p % 64);
                            }
                        }
                    }
                } else {
                    for y in 0..w {
                        for x in 0..w {
                            if adaptive::walsh_sign(w, n, x, y) == want {
                                let p = (y * w + x) as usize;
                                out[p / 64] |= 1 << (p % 64);
                            }
                        }
                    }
                }
            }
            Kind::Hadamard { plan } => {
                assert!(
                    i < 2 * k as u64,
                    "hadamard frame {i} does not exist: a {}x{} spec has 2k = {} frames",
                    self.spec.width(),
                    self.spec.height(),
                    2 * k
                );
                let w = self.spec.width() as u64;
                let n = plan.natural_index(i / 2);
                let (u, v) = (n / w, n % w);
                let positive = i.is_multiple_of(2);
                out.fill(0);
                // h = +1 (pixel of P+) where popcount(u & y) + popcount(v & x) is even.
                for y in 0..self.spec.height() as u64 {
                    let row_parity = (u & y).count_ones() & 1;
                    for x in 0..w {
                        let even = ((v & x).count_ones() & 1) == row_parity;
                        if even == positive {
                            let p = (y * w + x) as usize;
                            out[p / 64] |= 1 << (p % 64);
                        }
                    }
                }
            }
        }
        let tail = k % 64;
        if tail != 0 {
            out[nw - 1] &= (1u64 << tail) - 1;
        }
        Ok(())
    }
}

/// Grey level of one speckle cell: the top 24 bits of its word, scaled by 2^-24 (exact in f32).
#[inline]
pub fn speckle_level(word: u64) -> f32 {
    (word >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
}

/// Which index of an adaptive session's sequence frame `frame` shows, and whether it is the
/// index's `P+`: split pairs `(frame / 2, frame even)`; single frames (PATTERNS.md, "Single
/// frames") index 0's pair in frames 0 and 1, then `(frame - 1, true)`.
pub fn adaptive_frame(single: bool, frame: u64) -> (u64, bool) {
    if !single {
        (frame / 2, frame.is_multiple_of(2))
    } else if frame < 2 {
        (0, frame == 0)
    } else {
        (frame - 1, true)
    }
}

#[cfg(test)]
mod tests;
