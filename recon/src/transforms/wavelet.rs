//! Orthonormal separable 2D wavelets on any `W x H`: Haar and periodic Daubechies.
//!
//! # Levels and layout
//!
//! Mallat layout. Level `l` acts on the current approximation block (`w_l x h_l`, top-left):
//! each axis of length >= 2 gets one 1D step (rows first, then columns), which writes the
//! `ceil(len / 2)` approximation coefficients first and the `floor(len / 2)` details after them;
//! an axis that has reached length 1 is left alone while the other continues. By default levels
//! run until the approximation is 1 x 1 (`ceil(log2(max(W, H)))` levels); `with_levels` caps them.
//! Every step is an orthonormal map of the block (the rest untouched), so the whole transform is
//! orthonormal: `adjoint = inverse`, norms preserved.
//!
//! # Odd lengths (any size works)
//!
//! - **Haar** is the *unbalanced* Haar basis (Girardi & Sweldens 1997): approximation coefficient
//!   `i` carries the size `a` of its support; a pair of supports `a`, `b` merges by the rotation
//!   `[A; D] = [sqrt(a) , sqrt(b); sqrt(b), -sqrt(a)] / sqrt(a + b) [s1; s2]`, which for
//!   `a = b` is the usual `(s1 +- s2) / sqrt(2)`. At an odd length the last coefficient passes to
//!   the next level unpaired (keeping its support size). Piecewise-constant images on any grid
//!   stay sparse: a constant image has exactly one nonzero coefficient for every W, H.
//! - **Daubechies** (db2: 4 taps, db4: 8 taps, 2 and 4 vanishing moments) uses periodic
//!   boundaries: `a_i = sum_t h_t x_{(2i + t) mod N}`, `d_i = sum_t g_t x_{(2i + t) mod N}`,
//!   `g_t = (-1)^t h_{L-1-t}`, orthonormal for every even `N` (also `N < L`, where the filter
//!   wraps). At an odd length the last sample passes to the approximation unchanged and the
//!   periodic step runs on the first `N - 1`: still orthonormal, at the cost of a seam at the
//!   image edge (as with any periodic wavelet on a non-periodic image).

use rayon::prelude::*;

use super::Transform;
use crate::linop::LinearOperator;
use crate::ops::scratch::Pool;

/// db4 lowpass (8 taps, 4 vanishing moments): Daubechies' minimum-phase D8 filter, computed by
/// spectral factorisation of `P(y) = 1 + 4y + 10y^2 + 20y^3` in 60-digit arithmetic and rounded
/// (orthonormality holds to 1e-16). db2 (4 taps) is the closed form `(1 +- sqrt 3, 3 +- sqrt 3) /
/// (4 sqrt 2)`, computed in [`db2`].
const DB4: [f64; 8] = [
    0.230_377_813_308_896_5,
    0.714_846_570_552_915_7,
    0.630_880_767_929_858_9,
    -0.027_983_769_416_859_854,
    -0.187_034_811_719_093_09,
    0.030_841_381_835_560_764,
    0.032_883_011_666_885_2,
    -0.010_597_401_785_069_032,
];

/// Blocks with at least this many values are split over threads.
const PARALLEL_MIN: usize = 1 << 15;
/// Rows per task in the parallel x step.
const ROWS_PER_TASK: usize = 16;

fn db2() -> [f64; 4] {
    let (s3, d) = (3f64.sqrt(), 4.0 * 2f64.sqrt());
    [
        (1.0 + s3) / d,
        (3.0 + s3) / d,
        (3.0 - s3) / d,
        (1.0 - s3) / d,
    ]
}

#[derive(Clone, Debug, PartialEq)]
enum Family {
    /// Unbalanced Haar; per axis per level the (alpha, beta) rotation of each pair.
    Haar,
    /// Periodic orthonormal filter bank: lowpass h, highpass g.
    Periodic { h: Vec<f64>, g: Vec<f64> },
}

/// One 1D step along one axis at one level.
#[derive(Clone, Debug)]
struct Step {
    len: usize,
    /// Haar only: `(alpha, beta)` per pair.
    pairs: Vec<(f64, f64)>,
}

/// An orthonormal 2D wavelet transform (see the module docs). As an operator: image (row-major,
/// `W x H`) -> coefficients (same length, Mallat layout); `adjoint` is the inverse.
#[derive(Debug)]
pub struct Wavelet2d {
    width: usize,
    height: usize,
    family: Family,
    name: &'static str,
    /// Per level: the x step and the y step (None when that axis is already length 1).
    levels: Vec<(Option<Step>, Option<Step>)>,
    pool: Pool,
}

impl Wavelet2d {
    /// Orthonormal Haar (unbalanced on odd lengths), full depth.
    pub fn haar(width: usize, height: usize) -> Self {
        Self::build(width, height, Family::Haar, "haar", usize::MAX)
    }

    /// Daubechies with 2 vanishing moments (4 taps), periodic, full depth.
    pub fn db2(width: usize, height: usize) -> Self {
        Self::periodic(width, height, &db2(), "db2")
    }

    /// Daubechies with 4 vanishing moments (8 taps), periodic, full depth.
    pub fn db4(width: usize, height: usize) -> Self {
        Self::periodic(width, height, &DB4, "db4")
    }

    fn periodic(width: usize, height: usize, h: &[f64], name: &'static str) -> Self {
        let l = h.len();
        let g = (0..l)
            .map(|t| {
                if t % 2 == 0 {
                    h[l - 1 - t]
                } else {
                    -h[l - 1 - t]
                }
            })
            .collect();
        Self::build(
            width,
            height,
            Family::Periodic { h: h.to_vec(), g },
            name,
            usize::MAX,
        )
    }

    /// The same transform with at most `levels` levels (0 = identity).
    pub fn with_levels(self, levels: usize) -> Self {
        Self::build(self.width, self.height, self.family, self.name, levels)
    }

    fn build(width: usize, height: usize, family: Family, name: &'static str, max: usize) -> Self {
        assert!(width > 0 && height > 0, "wavelet needs a non-empty image");
        let haar = family == Family::Haar;
        let mut levels = Vec::new();
        let (mut wl, mut hl) = (width, height);
        let mut sizes_x = vec![1usize; width];
        let mut sizes_y = vec![1usize; height];
        while (wl > 1 || hl > 1) && levels.len() < max {
            let sx = (wl > 1).then(|| make_step(wl, &mut sizes_x, haar));
            let sy = (hl > 1).then(|| make_step(hl, &mut sizes_y, haar));
            levels.push((sx, sy));
            wl = wl.div_ceil(2);
            hl = hl.div_ceil(2);
        }
        Wavelet2d {
            width,
            height,
            family,
            name,
            levels,
            pool: Pool::new(),
        }
    }

    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Size `(w, h)` of the final approximation block (top-left of the coefficients).
    pub fn coarse_band(&self) -> (usize, usize) {
        let (mut w, mut h) = (self.width, self.height);
        for (sx, sy) in &self.levels {
            if sx.is_some() {
                w = w.div_ceil(2);
            }
            if sy.is_some() {
                h = h.div_ceil(2);
            }
        }
        (w, h)
    }

    fn step_forward(&self, step: &Step, input: &[f64], out: &mut [f64]) {
        let n = step.len;
        let half = n / 2;
        let na = n.div_ceil(2);
        match &self.family {
            Family::Haar => {
                for (i, &(a, b)) in step.pairs.iter().enumerate() {
                    let (s1, s2) = (input[2 * i], input[2 * i + 1]);
                    out[i] = a * s1 + b * s2;
                    out[na + i] = b * s1 - a * s2;
                }
            }
            Family::Periodic { h, g } => {
                let ne = 2 * half;
                let taps = h.len();
                for i in 0..half {
                    let (mut a, mut d) = (0.0, 0.0);
                    if 2 * i + taps <= ne {
                        let x = &input[2 * i..2 * i + taps];
                        for ((&ht, &gt), &xv) in h.iter().zip(g).zip(x) {
                            a += ht * xv;
                            d += gt * xv;
                        }
                    } else {
                        for (t, (&ht, &gt)) in h.iter().zip(g).enumerate() {
                            let xv = input[(2 * i + t) % ne];
                            a += ht * xv;
                            d += gt * xv;
                        }
                    }
                    out[i] = a;
                    out[na + i] = d;
                }
            }
        }
        if n % 2 == 1 {
            out[half] = input[n - 1];
        }
    }

    fn step_inverse(&self, step: &Step, input: &[f64], out: &mut [f64]) {
        let n = step.len;
        let half = n / 2;
        let na = n.div_ceil(2);
        match &self.family {
            Family::Haar => {
                for (i, &(a, b)) in step.pairs.iter().enumerate() {
                    let (ap, de) = (input[i], input[na + i]);
                    out[2 * i] = a * ap + b * de;
                    out[2 * i + 1] = b * ap - a * de;
                }
            }
            Family::Periodic { h, g } => {
                let ne = 2 * half;
                let taps = h.len();
                out[..ne].fill(0.0);
                for i in 0..half {
                    let (a, d) = (input[i], input[na + i]);
                    if 2 * i + taps <= ne {
                        let x = &mut out[2 * i..2 * i + taps];
                        for ((&ht, &gt), xv) in h.iter().zip(g).zip(x) {
                            *xv += ht * a + gt * d;
                        }
                    } else {
                        for (t, (&ht, &gt)) in h.iter().zip(g).enumerate() {
                            out[(2 * i + t) % ne] += ht * a + gt * d;
                        }
                    }
                }
            }
        }
        if n % 2 == 1 {
            out[n - 1] = input[half];
        }
    }

    /// One x step on every row of the `wl x hl` block (row stride `width`); rows in parallel
    /// for large blocks.
    fn step_rows(&self, data: &mut [f64], wl: usize, hl: usize, step: &Step, forward: bool) {
        let w = self.width;
        let rows = |chunk: &mut [f64]| {
            let mut buf = self.pool.take(wl);
            for row in chunk.chunks_mut(w) {
                let row = &mut row[..wl];
                if forward {
                    self.step_forward(step, row, &mut buf);
                } else {
                    self.step_inverse(step, row, &mut buf);
                }
                row.copy_from_slice(&buf);
            }
        };
        // The block's rows: hl rows of stride w (the last one may be cut at wl).
        let block = &mut data[..(hl - 1) * w + wl];
        if wl * hl >= PARALLEL_MIN && rayon::current_num_threads() > 1 {
            block.par_chunks_mut(ROWS_PER_TASK * w).for_each(rows);
        } else {
            rows(block);
        }
    }

    /// One y step on the `wl x hl` block: the 1D step with whole row segments as samples
    /// (vectorised along x). Column bands in parallel for large blocks, each into its own part
    /// of `tmp`, then copied back.
    fn step_columns(
        &self,
        data: &mut [f64],
        wl: usize,
        hl: usize,
        step: &Step,
        forward: bool,
        tmp: &mut [f64],
    ) {
        let w = self.width;
        let threads = rayon::current_num_threads();
        let bands = if wl * hl >= PARALLEL_MIN && threads > 1 {
            (2 * threads).min(wl.div_ceil(8))
        } else {
            1
        };
        let bw = wl.div_ceil(bands);
        let tmp = &mut tmp[..hl * wl];
        {
            let src: &[f64] = data;
            let band = |(j, out): (usize, &mut [f64])| {
                let c0 = j * bw;
                let width = bw.min(wl - c0);
                self.column_band(src, c0, width, hl, step, forward, &mut out[..hl * width]);
            };
            if bands > 1 {
                tmp.par_chunks_mut(hl * bw).enumerate().for_each(band);
            } else {
                band((0, tmp));
            }
        }
        for (j, out) in tmp.chunks(hl * bw).enumerate() {
            let c0 = j * bw;
            let width = bw.min(wl - c0);
            for y in 0..hl {
                data[y * w + c0..y * w + c0 + width]
                    .copy_from_slice(&out[y * width..(y + 1) * width]);
            }
        }
    }

    /// The y step on columns `c0..c0 + bw` of `data` (row stride `width`) into `out` (`hl x bw`).
    #[allow(clippy::too_many_arguments)]
    fn column_band(
        &self,
        data: &[f64],
        c0: usize,
        bw: usize,
        hl: usize,
        step: &Step,
        forward: bool,
        out: &mut [f64],
    ) {
        let w = self.width;
        let n = step.len;
        debug_assert_eq!(n, hl);
        let half = n / 2;
        let na = n.div_ceil(2);
        let src = |y: usize| y * w + c0..y * w + c0 + bw;
        let dst = |y: usize| y * bw..(y + 1) * bw;
        match (&self.family, forward) {
            (Family::Haar, true) => {
                let (lo, hi) = out.split_at_mut(na * bw);
                for (i, &(a, b)) in step.pairs.iter().enumerate() {
                    let (r1, r2) = (&data[src(2 * i)], &data[src(2 * i + 1)]);
                    let (ap, de) = (&mut lo[dst(i)], &mut hi[dst(i)]);
                    for (((o1, o2), &s1), &s2) in ap.iter_mut().zip(de.iter_mut()).zip(r1).zip(r2) {
                        *o1 = a * s1 + b * s2;
                        *o2 = b * s1 - a * s2;
                    }
                }
            }
            (Family::Haar, false) => {
                for (i, &(a, b)) in step.pairs.iter().enumerate() {
                    let (ap, de) = (&data[src(i)], &data[src(na + i)]);
                    let (lo, hi) = out.split_at_mut((2 * i + 1) * bw);
                    let (o1, o2) = (&mut lo[dst(2 * i)], &mut hi[..bw]);
                    for (((x1, x2), &av), &dv) in o1.iter_mut().zip(o2.iter_mut()).zip(ap).zip(de) {
                        *x1 = a * av + b * dv;
                        *x2 = b * av - a * dv;
                    }
                }
            }
            (Family::Periodic { h, g }, true) => {
                let ne = 2 * half;
                out.fill(0.0);
                let (lo, hi) = out.split_at_mut(na * bw);
                for i in 0..half {
                    let (ap, de) = (&mut lo[dst(i)], &mut hi[dst(i)]);
                    for (t, (&ht, &gt)) in h.iter().zip(g).enumerate() {
                        let r = &data[src((2 * i + t) % ne)];
                        for ((o1, o2), &v) in ap.iter_mut().zip(de.iter_mut()).zip(r) {
                            *o1 += ht * v;
                            *o2 += gt * v;
                        }
                    }
                }
            }
            (Family::Periodic { h, g }, false) => {
                let ne = 2 * half;
                out.fill(0.0);
                for i in 0..half {
                    let (ap, de) = (&data[src(i)], &data[src(na + i)]);
                    for (t, (&ht, &gt)) in h.iter().zip(g).enumerate() {
                        let o = &mut out[dst((2 * i + t) % ne)];
                        for ((x, &av), &dv) in o.iter_mut().zip(ap).zip(de) {
                            *x += ht * av + gt * dv;
                        }
                    }
                }
            }
        }
        if n % 2 == 1 {
            // The unpaired last sample / approximation passes through.
            let (from, to) = if forward {
                (n - 1, half)
            } else {
                (half, n - 1)
            };
            out[dst(to)].copy_from_slice(&data[src(from)]);
        }
    }

    fn run(&self, input: &[f64], out: &mut [f64], forward: bool) {
        let (w, h) = (self.width, self.height);
        assert_eq!(input.len(), w * h);
        assert_eq!(out.len(), w * h);
        out.copy_from_slice(input);
        let mut tmp = self.pool.take(w * h);
        // Block size at each level.
        let (mut wl, mut hl) = (w, h);
        let mut dims = [(0usize, 0usize); 64];
        for (d, (sx, sy)) in dims.iter_mut().zip(&self.levels) {
            *d = (wl, hl);
            if sx.is_some() {
                wl = wl.div_ceil(2);
            }
            if sy.is_some() {
                hl = hl.div_ceil(2);
            }
        }
        let n = self.levels.len();
        for i in 0..n {
            let l = if forward { i } else { n - 1 - i };
            let (sx, sy) = &self.levels[l];
            let (wl, hl) = dims[l];
            // Forward: x then y; inverse: y then x.
            if forward {
                if let Some(s) = sx {
                    self.step_rows(out, wl, hl, s, true);
                }
                if let Some(s) = sy {
                    self.step_columns(out, wl, hl, s, true, &mut tmp);
                }
            } else {
                if let Some(s) = sy {
                    self.step_columns(out, wl, hl, s, false, &mut tmp);
                }
                if let Some(s) = sx {
                    self.step_rows(out, wl, hl, s, false);
                }
            }
        }
    }
}

/// The step for an axis of current length `len` whose coefficients have support sizes
/// `sizes[..len]`; updates `sizes` to the next level's.
fn make_step(len: usize, sizes: &mut [usize], haar: bool) -> Step {
    let half = len / 2;
    let mut pairs = Vec::new();
    if haar {
        pairs.reserve(half);
        for i in 0..half {
            let (a, b) = (sizes[2 * i] as f64, sizes[2 * i + 1] as f64);
            let s = (a + b).sqrt();
            pairs.push((a.sqrt() / s, b.sqrt() / s));
        }
    }
    let next: Vec<usize> = (0..len.div_ceil(2))
        .map(|i| {
            if 2 * i + 1 < len {
                sizes[2 * i] + sizes[2 * i + 1]
            } else {
                sizes[2 * i]
            }
        })
        .collect();
    sizes[..next.len()].copy_from_slice(&next);
    Step { len, pairs }
}

impl LinearOperator for Wavelet2d {
    fn rows(&self) -> usize {
        self.width * self.height
    }
    fn cols(&self) -> usize {
        self.width * self.height
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.run(x, y, true);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        self.run(y, x, false);
    }
}

impl Transform for Wavelet2d {
    fn name(&self) -> &'static str {
        self.name
    }
    fn is_orthonormal(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_are_orthonormal() {
        for h in [db2().to_vec(), DB4.to_vec()] {
            let l = h.len();
            for m in 0..l / 2 {
                let s: f64 = (0..l - 2 * m).map(|t| h[t] * h[t + 2 * m]).sum();
                let want = if m == 0 { 1.0 } else { 0.0 };
                assert!((s - want).abs() < 1e-15, "taps {l} shift {m}: {s}");
            }
            assert!((h.iter().sum::<f64>() - 2f64.sqrt()).abs() < 1e-15);
        }
    }

    #[test]
    fn unbalanced_haar_levels() {
        // Length 5: pairs (0,1), (2,3), 4 passes; then sizes 2, 2, 1 -> (2,2) pair, 1 passes...
        let t = Wavelet2d::haar(5, 1);
        assert_eq!(t.levels(), 3);
        let (sx, sy) = &t.levels[1];
        assert!(sy.is_none());
        let s = sx.as_ref().unwrap();
        assert_eq!(s.len, 3);
        assert!((s.pairs[0].0 - 0.5f64.sqrt()).abs() < 1e-16);
        let s = t.levels[2].0.as_ref().unwrap();
        assert_eq!(s.len, 2);
        // Supports 4 and 1.
        assert!((s.pairs[0].0 - (4.0f64 / 5.0).sqrt()).abs() < 1e-15);
    }
}
