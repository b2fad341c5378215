//! Walsh-Hadamard row orderings (PATTERNS.md, "hadamard").
//!
//! A 2D Hadamard pattern is named by its natural row index `n = u * W + v` (u: vertical, v:
//! horizontal Sylvester index) and has `h(x, y) = (-1)^(popcount(u & y) + popcount(v & x))`, which
//! equals row `n` of the k x k Sylvester matrix at column `y * W + x`.

use serde::{Deserialize, Serialize};

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum HadamardOrdering {
    /// Sylvester (Kronecker) order: row r is natural index r.
    #[default]
    Natural,
    /// Walsh order of the whole k-point matrix: row r has r sign changes along the flattened
    /// (row-major) pattern; natural index = bitrev(gray(r)).
    Sequency,
    /// 2D sequency diagonals: by (su + sv, su), su/sv the per-axis sequencies.
    Zigzag,
    /// Nested dyadic levels: by (max(bitlen(su), bitlen(sv)), su + sv, su). After 4^j rows every
    /// Walsh function of a 2^j x 2^j grid is measured (the exact block-averaged image).
    RussianDoll,
    /// By number of constant pieces (su + 1)(sv + 1), then su (Yu et al. 2019 "cake cutting").
    CakeCutting,
}

impl HadamardOrdering {
    pub const ALL: [HadamardOrdering; 5] = [
        HadamardOrdering::Natural,
        HadamardOrdering::Sequency,
        HadamardOrdering::Zigzag,
        HadamardOrdering::RussianDoll,
        HadamardOrdering::CakeCutting,
    ];

    pub fn name(self) -> &'static str {
        match self {
            HadamardOrdering::Natural => "natural",
            HadamardOrdering::Sequency => "sequency",
            HadamardOrdering::Zigzag => "zigzag",
            HadamardOrdering::RussianDoll => "russian_doll",
            HadamardOrdering::CakeCutting => "cake_cutting",
        }
    }
}

/// Reverses the lowest `bits` bits of `x`.
#[inline]
pub fn bit_reverse(x: u64, bits: u32) -> u64 {
    if bits == 0 {
        0
    } else {
        x.reverse_bits() >> (64 - bits)
    }
}

/// Natural (Sylvester) index of the Walsh function with `sequency` sign changes, length 2^bits.
#[inline]
pub fn natural_of_sequency(sequency: u64, bits: u32) -> u64 {
    bit_reverse(sequency ^ (sequency >> 1), bits)
}

fn bit_len(x: u64) -> u32 {
    64 - x.leading_zeros()
}

/// The `(su, sv)` pairs (`su < h`, `sv < w`) in Russian-doll order, the order of the key
/// `(max(bit_len(su), bit_len(sv)), su + sv, su)`, generated level by level without sorting:
/// level `l` is the square `[0, 2^l)^2` (clipped to the grid) minus the square of level `l - 1`,
/// walked by anti-diagonal `d = su + sv`, then by `su`.
fn russian_doll_pairs(w: u64, h: u64) -> Vec<(u64, u64)> {
    let mut out = Vec::with_capacity((w * h) as usize);
    let levels = bit_len(h - 1).max(bit_len(w - 1));
    for l in 0..=levels {
        let side = 1u64 << l;
        let inner = if l == 0 { 0 } else { side / 2 };
        let (hu, wv) = (side.min(h), side.min(w));
        for d in 0..hu + wv - 1 {
            for su in d.saturating_sub(wv - 1)..=d.min(hu - 1) {
                let sv = d - su;
                if su >= inner || sv >= inner {
                    out.push((su, sv));
                }
            }
        }
    }
    out
}

/// Maps row indices of an ordering to natural indices. Natural and sequency are closed forms; the
/// 2D orderings sort the k (su, sv) pairs once by their key (planned once, then O(1) per row).
#[derive(Clone, Debug)]
pub struct HadamardPlan {
    width_bits: u32,
    height_bits: u32,
    ordering: HadamardOrdering,
    table: Option<Vec<u32>>,
}

impl HadamardPlan {
    pub fn new(width: u32, height: u32, ordering: HadamardOrdering) -> Self {
        assert!(width.is_power_of_two() && height.is_power_of_two());
        let width_bits = width.trailing_zeros();
        let height_bits = height.trailing_zeros();
        let table = match ordering {
            HadamardOrdering::Natural | HadamardOrdering::Sequency => None,
            _ => {
                let (w, h) = (width as u64, height as u64);
                let mut pairs: Vec<(u64, u64)> = if ordering == HadamardOrdering::RussianDoll {
                    russian_doll_pairs(w, h)
                } else {
                    (0..h)
                        .flat_map(|su| (0..w).map(move |sv| (su, sv)))
                        .collect()
                };
                match ordering {
                    HadamardOrdering::Zigzag => pairs.sort_by_key(|&(su, sv)| (su + sv, su)),
                    // Generated in order (measured: sorting took 3-4 ms at 256x256, more
                    // than the zero-filled inverse it plans for).
                    HadamardOrdering::RussianDoll => {}
                    HadamardOrdering::CakeCutting => {
                        pairs.sort_by_key(|&(su, sv)| ((su + 1) * (sv + 1), su))
                    }
                    _ => unreachable!(),
                }
                Some(
                    pairs
                        .into_iter()
                        .map(|(su, sv)| {
                            let u = natural_of_sequency(su, height_bits);
                            let v = natural_of_sequency(sv, width_bits);
                            (u * w + v) as u32
                        })
                        .collect(),
                )
            }
        };
        HadamardPlan {
            width_bits,
            height_bits,
            ordering,
            table,
        }
    }

    /// Natural index `u * W + v` of row `row` (0 <= row < k) in this plan's ordering.
    #[inline]
    pub fn natural_index(&self, row: u64) -> u64 {
        match (&self.table, self.ordering) {
            (Some(table), _) => table[row as usize] as u64,
            (None, HadamardOrdering::Sequency) => {
                natural_of_sequency(row, self.width_bits + self.height_bits)
            }
            (None, _) => row,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn walsh_1d(n: u64, len: u64) -> Vec<i32> {
        (0..len)
            .map(|x| {
                if (n & x).count_ones().is_multiple_of(2) {
                    1
                } else {
                    -1
                }
            })
            .collect()
    }

    fn sign_changes(v: &[i32]) -> usize {
        v.windows(2).filter(|w| w[0] != w[1]).count()
    }

    #[test]
    fn sequency_row_has_that_many_sign_changes() {
        for bits in 0..=8 {
            let len = 1u64 << bits;
            for s in 0..len {
                let n = natural_of_sequency(s, bits);
                assert_eq!(
                    sign_changes(&walsh_1d(n, len)),
                    s as usize,
                    "bits {bits} s {s}"
                );
            }
        }
    }

    #[test]
    fn every_ordering_is_a_permutation() {
        for &(w, h) in &[(1u32, 1u32), (8, 8), (16, 4), (2, 32)] {
            for ordering in HadamardOrdering::ALL {
                let plan = HadamardPlan::new(w, h, ordering);
                let k = (w * h) as u64;
                let mut seen = vec![false; k as usize];
                for r in 0..k {
                    let n = plan.natural_index(r);
                    assert!(!seen[n as usize], "{ordering:?} repeats {n}");
                    seen[n as usize] = true;
                }
            }
        }
    }

    #[test]
    fn russian_doll_levels_are_complete_block_bases() {
        // After 4^j rows, the measured set is exactly the Walsh functions constant on
        // (W/2^j) x (H/2^j) blocks.
        let (w, h) = (16u32, 16u32);
        let plan = HadamardPlan::new(w, h, HadamardOrdering::RussianDoll);
        for j in 0..=4u32 {
            let rows = 1u64 << (2 * j);
            let block = (w >> j) as u64;
            for r in 0..rows {
                let n = plan.natural_index(r);
                let (u, v) = (n / w as u64, n % w as u64);
                for y in 0..h as u64 {
                    for x in 0..w as u64 {
                        let s = ((u & y).count_ones() + (v & x).count_ones()) % 2;
                        let (by, bx) = (y / block * block, x / block * block);
                        let s0 = ((u & by).count_ones() + (v & bx).count_ones()) % 2;
                        assert_eq!(s, s0, "level {j} row {r} not constant on blocks");
                    }
                }
            }
        }
    }

    #[test]
    fn generated_pairs_are_the_sorted_order() {
        for (w, h) in [
            (1u64, 1u64),
            (2, 1),
            (1, 8),
            (4, 4),
            (16, 4),
            (8, 32),
            (64, 64),
            (256, 128),
        ] {
            let mut sorted: Vec<(u64, u64)> = (0..h)
                .flat_map(|su| (0..w).map(move |sv| (su, sv)))
                .collect();
            sorted.sort_by_key(|&(su, sv)| (bit_len(su).max(bit_len(sv)), su + sv, su));
            assert_eq!(russian_doll_pairs(w, h), sorted, "{w}x{h}");
        }
    }
}
