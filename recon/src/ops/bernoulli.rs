//! Binary pattern operators: `y = P x`, `P` the `n x k` 0/1 matrix of the first `n` patterns.
//!
//! Planned once: the patterns are generated (in parallel) and packed in two layouts, pattern-major
//! (`P`, rows = patterns, for `apply`) and pixel-major (`P^T`, for `adjoint`), 2 bits of memory
//! per pattern-pixel in all (128 x 128 at 10 %: 6.7 MB; 256 x 256 at 10 %: 107 MB). Both products
//! are the byte-table kernel of [`super::bits`]: `n k / 8` table look-ups, multithreaded, with
//! batched forms (up to four vectors per pass over the bits). The dense product is never faster
//! at the sizes measured (see `ops::bench`), so there is no dense path.
//!
//! Works for any binary family: Bernoulli, raster, or raw Hadamard P+/P- frames (for Hadamard
//! data the [`super::HadamardOperator`] on differences is the better operator).

use helmholtz_proto::{PatternGenerator, PatternSpec};

use super::OpError;
use super::bits::BitMatrix;
use super::scratch::Pool;
use crate::linop::LinearOperator;

/// `n x k` 0/1 pattern matrix with fast forward and adjoint products (see the module docs).
#[derive(Debug)]
pub struct BernoulliOperator {
    patterns: BitMatrix,
    pixels: BitMatrix,
    row_sums: Vec<f64>,
    pool: Pool,
}

/// The same operator under the name that says what it accepts: any 0/1 pattern family.
pub type BinaryOperator = BernoulliOperator;

impl BernoulliOperator {
    /// Patterns `0..rows` of a binary family (`rows <= spec.count()`).
    pub fn from_spec(spec: &PatternSpec, rows: u64) -> Result<Self, OpError> {
        if !spec.family().is_binary() {
            return Err(OpError::NotBinary(spec.family().name()));
        }
        super::check_rows(spec, rows)?;
        let k = spec.pixels();
        super::check_memory(2 * rows as usize * k.div_ceil(64) * 8)?;
        let generator = PatternGenerator::new(spec);
        let patterns = BitMatrix::from_fn(rows as usize, k, |i, words| {
            generator.fill_bits(i as u64, words).expect("binary family");
        });
        Ok(Self::from_bit_matrix(patterns))
    }

    /// From packed patterns: `rows` patterns of `cols` pixels, `ceil(cols / 64)` words each,
    /// pixel p = bit p % 64 of word p / 64 (bits past `cols` are ignored).
    pub fn from_bits(rows: usize, cols: usize, words: Vec<u64>) -> Self {
        Self::from_bit_matrix(BitMatrix::new(rows, cols, words))
    }

    pub fn from_bit_matrix(patterns: BitMatrix) -> Self {
        let pixels = patterns.transpose();
        let row_sums = patterns.row_sums();
        BernoulliOperator {
            patterns,
            pixels,
            row_sums,
            pool: Pool::new(),
        }
    }

    /// The operator of a subset of the rows, in the given order (e.g. the fitting rows of a
    /// hold-out split). Repeats are allowed.
    pub fn select_rows(&self, rows: &[usize]) -> Self {
        let p = &self.patterns;
        let words = p.words_per_row();
        let selected = BitMatrix::from_fn(rows.len(), p.cols(), |i, out| {
            for (w, o) in out.iter_mut().enumerate().take(words) {
                *o = p.word(rows[i], w);
            }
        });
        Self::from_bit_matrix(selected)
    }

    /// Pattern-major bits (row i = pattern i).
    pub fn patterns(&self) -> &BitMatrix {
        &self.patterns
    }

    /// `R_i`: number of lit pixels of each pattern.
    pub fn row_sums(&self) -> &[f64] {
        &self.row_sums
    }

    /// Number of patterns lighting each pixel (`P^T 1`).
    pub fn column_sums(&self) -> Vec<f64> {
        self.pixels.row_sums()
    }

    /// Heap bytes held by both bit layouts.
    pub fn memory_bytes(&self) -> usize {
        self.patterns.memory_bytes() + self.pixels.memory_bytes()
    }
}

impl LinearOperator for BernoulliOperator {
    fn rows(&self) -> usize {
        self.patterns.rows()
    }
    fn cols(&self) -> usize {
        self.patterns.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.patterns.matvec(x, y, &self.pool);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        self.pixels.matvec(y, x, &self.pool);
    }
    fn apply_batch(&self, xs: &[f64], ys: &mut [f64], batch: usize) {
        self.patterns.matvec_batch(xs, ys, batch, &self.pool);
    }
    fn adjoint_batch(&self, ys: &[f64], xs: &mut [f64], batch: usize) {
        self.pixels.matvec_batch(ys, xs, batch, &self.pool);
    }
    /// The portable kernel serves up to 4 vectors per pass; the AVX-512 one takes a pass per
    /// vector ([`Kernel`](super::bits::Kernel)).
    fn batching_pays(&self) -> bool {
        super::bits::Kernel::best() == super::bits::Kernel::Bytes
    }
}
