//! The two adaptive bases on a `W x W` grid (`W = 2^m`) and the planner's wavelet prediction:
//! levels, the tree, the gain of a split pair, and predicted coefficients from the coarse image.
//!
//! Every number here follows `proto/PATTERNS.md` (section "The planner") operation by operation,
//! so that another implementation replays a session to the same indices.

use helmholtz_proto::{Family, HaarFunction, PatternSpec};

use crate::fwht::fwht;

/// Which basis an adaptive spec scans.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Basis {
    /// 2D orthonormal Haar, Mallat index `n = r W + c`.
    Haar,
    /// 2D Walsh-Hadamard, natural index `n = u W + v`.
    Hadamard,
}

impl Basis {
    pub fn of(spec: &PatternSpec) -> Option<Basis> {
        match spec.family() {
            Family::AdaptiveHaar { .. } => Some(Basis::Haar),
            Family::AdaptiveHadamard { .. } => Some(Basis::Hadamard),
            _ => None,
        }
    }

    /// The split-pair gain `g_n`: `y+ - y- = g_n c_n` for the orthonormal coefficient `c_n` of the
    /// transport (Haar: the support side `2^s`; Walsh-Hadamard: `W`).
    pub fn gain(self, width: u32, n: u32) -> f64 {
        match self {
            Basis::Haar => HaarFunction::new(width, n).side() as f64,
            Basis::Hadamard => width as f64,
        }
    }

    /// The level of `n`: the coefficient is a function of the block averages of the image on
    /// `2^level x 2^level` blocks and not of those on blocks twice as large. Index 0 has level
    /// `m`; level `l < m` holds `3 * 4^(m - l - 1)` indices.
    pub fn level(self, width: u32, n: u32) -> u32 {
        let m = width.trailing_zeros();
        match self {
            Basis::Haar => {
                let f = HaarFunction::new(width, n);
                if n == 0 { m } else { f.scale - 1 }
            }
            Basis::Hadamard => {
                let (u, v) = (n / width, n % width);
                let tz = |a: u32| if a == 0 { m } else { a.trailing_zeros() };
                tz(u).min(tz(v))
            }
        }
    }

    /// The parent of `n` in the coarse-to-fine tree (`None` for index 0), always of a coarser
    /// level. Haar: the coefficient of the same orientation at the next coarser scale whose
    /// support contains `n`'s (index 0 for the three coarsest details). Walsh-Hadamard: `n` with
    /// bit `level(n)` of `u` and `v` cleared.
    pub fn parent(self, width: u32, n: u32) -> Option<u32> {
        if n == 0 {
            return None;
        }
        let (r, c) = (n / width, n % width);
        Some(match self {
            Basis::Haar => {
                let s = HaarFunction::new(width, n).scale;
                let h = width >> s;
                if h == 1 {
                    0
                } else {
                    let up = |a: u32| {
                        let band = if a >= h { h / 2 } else { 0 };
                        band + (a % h) / 2
                    };
                    up(r) * width + up(c)
                }
            }
            Basis::Hadamard => {
                let bit = 1 << self.level(width, n);
                (r & !bit) * width + (c & !bit)
            }
        })
    }
}

/// Scratch for [`Predictor::predict`]: the pyramid of block averages and the upsampled level.
#[derive(Debug)]
pub struct Predictor {
    basis: Basis,
    width: u32,
    /// `pyramid[l]` = block averages on `2^l` blocks, `(W >> l)^2` values, for `l = 1..=m`
    /// (`pyramid[0]` unused).
    pyramid: Vec<Vec<f64>>,
    /// Horizontal pass of the upsampling: `N x 2N`.
    half: Vec<f64>,
    /// The upsampled level: `2N x 2N`.
    up: Vec<f64>,
}

/// Keys' cubic convolution kernel (a = -1/2) at the four taps of a 2x upsampling, in 1/128:
/// output `2j` sits at coarse coordinate `j - 1/4` (taps `j-2 .. j+1`), output `2j + 1` at
/// `j + 1/4` (taps `j-1 .. j+2`).
const EVEN_TAPS: [f64; 4] = [-3.0, 29.0, 111.0, -9.0];
const ODD_TAPS: [f64; 4] = [-9.0, 111.0, 29.0, -3.0];
const TAP_SCALE: f64 = 1.0 / 128.0;

impl Predictor {
    pub fn new(basis: Basis, width: u32) -> Predictor {
        let m = width.trailing_zeros();
        let k = width as usize * width as usize;
        let pyramid = (0..=m)
            .map(|l| {
                if l == 0 {
                    Vec::new()
                } else {
                    vec![0.0; (width as usize >> l).pow(2)]
                }
            })
            .collect();
        Predictor {
            basis,
            width,
            pyramid,
            half: vec![0.0; k / 2],
            up: vec![0.0; k],
        }
    }

    /// Bytes of scratch held.
    pub fn memory_bytes(&self) -> usize {
        8 * (self.pyramid.iter().map(Vec::len).sum::<usize>() + self.half.len() + self.up.len())
    }

    /// Predicted orthonormal coefficients of one channel into `pred` (`W^2` values, index 0 set to
    /// 0) from its observed coefficients `values` (0 where not observed): level `l` from the
    /// bicubic 2x upsampling of the zero-filled image's block averages at level `l + 1`.
    pub fn predict(&mut self, values: &[f64], pred: &mut [f64]) {
        let w = self.width as usize;
        let m = self.width.trailing_zeros() as usize;
        assert_eq!(values.len(), w * w);
        assert_eq!(pred.len(), w * w);
        pred[0] = 0.0;
        if m == 0 {
            return;
        }
        self.averages(values);
        for l in 0..m {
            let n_coarse = w >> (l + 1);
            upsample(&self.pyramid[l + 1], n_coarse, &mut self.half, &mut self.up);
            let n = 2 * n_coarse;
            let up = &mut self.up[..n * n];
            match self.basis {
                Basis::Haar => {
                    let q = 2f64.powi(l as i32 - 1);
                    let h = n_coarse;
                    for pr in 0..h {
                        for pc in 0..h {
                            let a = up[2 * pr * n + 2 * pc];
                            let b = up[2 * pr * n + 2 * pc + 1];
                            let c = up[(2 * pr + 1) * n + 2 * pc];
                            let d = up[(2 * pr + 1) * n + 2 * pc + 1];
                            pred[pr * w + h + pc] = q * ((a - b) + (c - d));
                            pred[(h + pr) * w + pc] = q * ((a + b) - (c + d));
                            pred[(h + pr) * w + h + pc] = q * ((a - b) - (c - d));
                        }
                    }
                }
                Basis::Hadamard => {
                    fwht(up);
                    let q = 2f64.powi(2 * l as i32 - m as i32);
                    for u in 0..n {
                        for v in 0..n {
                            if (u | v) & 1 == 1 {
                                pred[(u << l) * w + (v << l)] = up[u * n + v] * q;
                            }
                        }
                    }
                }
            }
        }
    }

    /// `pyramid[l]`, `l = 1..=m`: block averages of the zero-filled image on `2^l` blocks.
    fn averages(&mut self, values: &[f64]) {
        let w = self.width as usize;
        let m = self.width.trailing_zeros() as usize;
        let inv_w = 1.0 / w as f64;
        match self.basis {
            Basis::Haar => {
                self.pyramid[m][0] = values[0] * inv_w;
                // Level l from level l + 1 and the details of support 2^(l+1).
                for l in (1..m).rev() {
                    let h = w >> (l + 1);
                    let t = 2f64.powi(-(l as i32 + 1));
                    let (fine, coarse) = self.pyramid.split_at_mut(l + 1);
                    let (fine, coarse) = (&mut fine[l], &coarse[0]);
                    let n = 2 * h;
                    for pr in 0..h {
                        for pc in 0..h {
                            let a = coarse[pr * h + pc];
                            let dx = values[pr * w + h + pc];
                            let dy = values[(h + pr) * w + pc];
                            let dxy = values[(h + pr) * w + h + pc];
                            fine[2 * pr * n + 2 * pc] = a + t * ((dx + dy) + dxy);
                            fine[2 * pr * n + 2 * pc + 1] = a + t * ((dy - dx) - dxy);
                            fine[(2 * pr + 1) * n + 2 * pc] = a + t * ((dx - dy) - dxy);
                            fine[(2 * pr + 1) * n + 2 * pc + 1] = a + t * ((dxy - dx) - dy);
                        }
                    }
                }
            }
            Basis::Hadamard => {
                for l in 1..=m {
                    let n = w >> l;
                    let level = &mut self.pyramid[l];
                    for u in 0..n {
                        for v in 0..n {
                            level[u * n + v] = values[(u << l) * w + (v << l)];
                        }
                    }
                    fwht(level);
                    level.iter_mut().for_each(|a| *a *= inv_w);
                }
            }
        }
    }
}

/// Bicubic 2x upsampling of an `n x n` image (rows first, then columns; indices clamped at the
/// edges) into `up[..4 n^2]`, through `half[..2 n^2]`.
fn upsample(coarse: &[f64], n: usize, half: &mut [f64], up: &mut [f64]) {
    let at = |i: isize| i.clamp(0, n as isize - 1) as usize;
    let taps = |get: &dyn Fn(usize) -> f64, j: usize, odd: bool| {
        let (t, first) = if odd {
            (&ODD_TAPS, j as isize - 1)
        } else {
            (&EVEN_TAPS, j as isize - 2)
        };
        (((t[0] * get(at(first)) + t[1] * get(at(first + 1))) + t[2] * get(at(first + 2)))
            + t[3] * get(at(first + 3)))
            * TAP_SCALE
    };
    let n2 = 2 * n;
    for i in 0..n {
        let row = &coarse[i * n..(i + 1) * n];
        let get = |x: usize| row[x];
        for j in 0..n {
            half[i * n2 + 2 * j] = taps(&get, j, false);
            half[i * n2 + 2 * j + 1] = taps(&get, j, true);
        }
    }
    for x in 0..n2 {
        let get = |y: usize| half[y * n2 + x];
        for i in 0..n {
            up[2 * i * n2 + x] = taps(&get, i, false);
            up[(2 * i + 1) * n2 + x] = taps(&get, i, true);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_hold_three_quarters_of_each_scale_and_parents_are_coarser() {
        for basis in [Basis::Haar, Basis::Hadamard] {
            for w in [1u32, 2, 4, 8, 16] {
                let m = w.trailing_zeros();
                let k = w * w;
                let mut per_level = vec![0u32; m as usize + 1];
                for n in 0..k {
                    let l = basis.level(w, n);
                    per_level[l as usize] += 1;
                    match basis.parent(w, n) {
                        None => assert_eq!(n, 0),
                        // Haar: the next scale; Walsh-Hadamard: coarser (the root is the
                        // parent of every (0, 2^j) and (2^j, 0) and (2^j, 2^j)).
                        Some(p) => assert!(
                            basis.level(w, p) > l
                                && (basis == Basis::Hadamard || basis.level(w, p) == l + 1),
                            "{basis:?} w {w}: parent {p} of {n}"
                        ),
                    }
                }
                assert_eq!(per_level[m as usize], 1);
                for l in 0..m {
                    assert_eq!(
                        per_level[l as usize],
                        3 * 4u32.pow(m - l - 1),
                        "{basis:?} {w}"
                    );
                }
            }
        }
    }

    #[test]
    fn haar_parent_support_contains_the_child() {
        let w = 16;
        for n in 1..w * w {
            let f = HaarFunction::new(w, n);
            let p = Basis::Haar.parent(w, n).unwrap();
            let g = HaarFunction::new(w, p);
            assert!(
                g.x0 <= f.x0 && f.x0 + f.side() <= g.x0 + g.side(),
                "{n} {p}"
            );
            assert!(
                g.y0 <= f.y0 && f.y0 + f.side() <= g.y0 + g.side(),
                "{n} {p}"
            );
            if p != 0 {
                assert_eq!((f.split_x, f.split_y), (g.split_x, g.split_y));
            }
        }
    }

    /// A linear ramp is reproduced by Keys' kernel away from the clamped edges.
    #[test]
    fn upsampling_reproduces_a_ramp_inside() {
        let n = 8;
        let coarse: Vec<f64> = (0..n * n).map(|p| (p % n) as f64 * 2.0 + 1.0).collect();
        let (mut half, mut up) = (vec![0.0; 2 * n * n], vec![0.0; 4 * n * n]);
        upsample(&coarse, n, &mut half, &mut up);
        for y in 0..2 * n {
            for x in 3..2 * n - 3 {
                // Fine pixel x sits at coarse coordinate x / 2 - 1/4.
                let want = (x as f64 / 2.0 - 0.25) * 2.0 + 1.0;
                assert!((up[y * 2 * n + x] - want).abs() < 1e-12, "{x} {y}");
            }
        }
    }

    /// With every coefficient of levels >= l + 1 known, the pyramid holds the exact block
    /// averages of the image.
    #[test]
    fn pyramid_is_the_block_averages_of_the_image() {
        let w = 8usize;
        let image: Vec<f64> = (0..w * w).map(|p| ((p * 37) % 11) as f64 - 3.0).collect();
        for basis in [Basis::Haar, Basis::Hadamard] {
            let values: Vec<f64> = (0..(w * w) as u32)
                .map(|n| {
                    let mut s = 0.0;
                    for y in 0..w as u32 {
                        for x in 0..w as u32 {
                            let sign = match basis {
                                Basis::Haar => HaarFunction::new(w as u32, n).sign(x, y) as f64,
                                Basis::Hadamard => helmholtz_proto::patterns::adaptive::walsh_sign(
                                    w as u32, n, x, y,
                                ) as f64,
                            };
                            s += sign * image[y as usize * w + x as usize];
                        }
                    }
                    s / basis.gain(w as u32, n)
                })
                .collect();
            let mut p = Predictor::new(basis, w as u32);
            p.averages(&values);
            for l in 1..=3usize {
                let b = 1 << l;
                let n = w >> l;
                for i in 0..n {
                    for j in 0..n {
                        let mut s = 0.0;
                        for y in 0..b {
                            for x in 0..b {
                                s += image[(i * b + y) * w + j * b + x];
                            }
                        }
                        let want = s / (b * b) as f64;
                        let got = p.pyramid[l][i * n + j];
                        assert!((got - want).abs() < 1e-12, "{basis:?} l {l}: {got} {want}");
                    }
                }
            }
        }
    }
}
