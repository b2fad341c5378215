//! The packed-bit and grey-level kernels of the correlators (module docs of [`super`],
//! "Kernel"): subset-sum tables and the byte-column bit transpose of the accumulation, the
//! pattern sums `R` (population counts, grey-level sums) and the pattern-times-image dot
//! products of the held-out features (nibble tables).

/// `lut[s] = (sum of w0[b], sum of w1[b])` over the bits b set in s.
pub(super) fn build_lut(w0: &[f64], w1: &[f64], lut: &mut [[f64; 2]; 256]) {
    lut[0] = [0.0; 2];
    for b in 0..8 {
        let half = 1usize << b;
        for s in 0..half {
            lut[half + s] = [lut[s][0] + w0[b], lut[s][1] + w1[b]];
        }
    }
}

/// One stage of eight 8 x 8 bit transposes per byte column, on all lanes: rows `r` and `r + j`
/// (bit j of r clear) swap the bits at in-byte positions `i + j` of row r with those at `i` of
/// row r + j (`mask` selects the positions i with bit j clear).
#[inline(always)]
pub(super) fn transpose_stage(rows: &mut [[u64; 8]; 8], j: usize, mask: u64) {
    for r in (0..8).filter(|r| r & j == 0) {
        let (lo, hi) = rows.split_at_mut(r + j);
        for (a, b) in lo[r].iter_mut().zip(hi[0].iter_mut()) {
            let t = ((*a >> j) ^ *b) & mask;
            *b ^= t;
            *a ^= t << j;
        }
    }
}

#[inline(always)]
pub(super) fn add2(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] + b[0], a[1] + b[1]]
}

/// The bit kernel. For every word of 64 pixels: load the 64 patterns' words as
/// `rows[b][g]` = pattern `8g + b`, transpose every byte column as an 8 x 8 bit matrix (the
/// eight groups g in parallel lanes), after which byte c of `rows[b][g]` holds pixel `8c + b` of
/// patterns `8g..8g+8` (pattern `8g + i` at bit i): the index into table g of each column pair.
/// (A full 64 x 64 transpose is not needed, only these bytes.)
pub(super) fn bit_kernel(
    bits: &[u64],
    stride: usize,
    nw: usize,
    luts: &[[[f64; 2]; 256]],
    acc: &mut [[f64; 2]],
    padded: usize,
) {
    let pairs = luts.len() / 8;
    let mut rows = [[0u64; 8]; 8];
    for w in 0..nw {
        for (b, row) in rows.iter_mut().enumerate() {
            for (g, v) in row.iter_mut().enumerate() {
                *v = bits[(8 * g + b) * stride + w];
            }
        }
        transpose_stage(&mut rows, 4, 0x0F0F_0F0F_0F0F_0F0F);
        transpose_stage(&mut rows, 2, 0x3333_3333_3333_3333);
        transpose_stage(&mut rows, 1, 0x5555_5555_5555_5555);
        // keys[b][g][c]: byte c of rows[b][g].
        let mut keys = [[[0u8; 8]; 8]; 8];
        for (kb, row) in keys.iter_mut().zip(&rows) {
            for (k, v) in kb.iter_mut().zip(row) {
                *k = v.to_le_bytes();
            }
        }
        for p in 0..pairs {
            let l: &[[[f64; 2]; 256]; 8] = luts[p * 8..p * 8 + 8].try_into().unwrap();
            let acc = &mut acc[p * padded + w * 64..p * padded + w * 64 + 64];
            for (b, k) in keys.iter().enumerate() {
                for c in 0..8 {
                    let key = |g: usize| k[g][c] as usize;
                    let s01 = add2(l[0][key(0)], l[1][key(1)]);
                    let s23 = add2(l[2][key(2)], l[3][key(3)]);
                    let s45 = add2(l[4][key(4)], l[5][key(5)]);
                    let s67 = add2(l[6][key(6)], l[7][key(7)]);
                    let a = &mut acc[8 * c + b];
                    *a = add2(*a, add2(add2(s01, s23), add2(s45, s67)));
                }
            }
        }
    }
}

pub(super) fn has_popcnt() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("popcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        true
    }
}

/// Set bits in `words`; `popcnt`: the CPU has the instruction (see [`has_popcnt`]).
pub(super) fn count_ones(words: &[u64], popcnt: bool) -> u64 {
    #[cfg(target_arch = "x86_64")]
    if popcnt {
        #[target_feature(enable = "popcnt")]
        fn with_popcnt(words: &[u64]) -> u64 {
            words.iter().map(|w| w.count_ones() as u64).sum()
        }
        // SAFETY: the caller checked that the CPU has POPCNT.
        return unsafe { with_popcnt(words) };
    }
    let _ = popcnt;
    words.iter().map(|w| w.count_ones() as u64).sum()
}

/// Sum of grey levels in f64, eight running sums (not one long dependency chain).
pub(super) fn sum_values(values: &[f32]) -> f64 {
    let mut lanes = [0f64; 8];
    let chunks = values.chunks_exact(8);
    let tail: f64 = chunks.remainder().iter().map(|&v| v as f64).sum();
    for c in chunks {
        for (l, &v) in lanes.iter_mut().zip(c) {
            *l += v as f64;
        }
    }
    lanes.iter().sum::<f64>() + tail
}

/// `table[j][s]`: the sum of `t[4j + b]` over the bits b set in s (pixels past `t` are 0), for
/// the `16 nw` nibbles of a packed pattern.
pub(super) fn nibble_table(t: &[f64], nw: usize) -> Vec<[f64; 16]> {
    (0..nw * 16)
        .map(|j| {
            let mut e = [0.0; 16];
            for s in 1..16usize {
                let b = s.trailing_zeros() as usize;
                e[s] = e[s & (s - 1)] + t.get(4 * j + b).copied().unwrap_or(0.0);
            }
            e
        })
        .collect()
}

/// `dots[j] = p_j . t` for the packed binary patterns `bits` (pattern j at `bits[j * nw..]`),
/// with `table` = [`nibble_table`] of t. Word-major, so each word's 16 table rows serve every
/// pattern while in cache.
pub(super) fn dot_bits(bits: &[u64], nw: usize, table: &[[f64; 16]], dots: &mut [f64]) {
    dots.fill(0.0);
    for (w, table) in table.chunks_exact(16).enumerate() {
        let table: &[[f64; 16]; 16] = table.try_into().unwrap();
        for (d, words) in dots.iter_mut().zip(bits.chunks_exact(nw)) {
            let word = words[w];
            let e = |i: usize| table[i][((word >> (4 * i)) & 15) as usize];
            let s0 = (e(0) + e(1)) + (e(2) + e(3));
            let s1 = (e(4) + e(5)) + (e(6) + e(7));
            let s2 = (e(8) + e(9)) + (e(10) + e(11));
            let s3 = (e(12) + e(13)) + (e(14) + e(15));
            *d += (s0 + s1) + (s2 + s3);
        }
    }
}

/// `p . t` of grey levels, eight running sums.
pub(super) fn dot_values(values: &[f32], t: &[f64]) -> f64 {
    let mut lanes = [0f64; 8];
    let (chunks, tail) = (values.chunks_exact(8), t.chunks_exact(8));
    let rest: f64 = chunks
        .remainder()
        .iter()
        .zip(tail.remainder())
        .map(|(&v, &t)| v as f64 * t)
        .sum();
    for (c, t) in chunks.zip(tail) {
        for ((l, &v), &t) in lanes.iter_mut().zip(c).zip(t) {
            *l += v as f64 * t;
        }
    }
    lanes.iter().sum::<f64>() + rest
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops read best in the reference computations
mod tests {
    use super::*;
    use crate::testutil::{Rng, random_scene};

    #[test]
    fn byte_column_transpose_gives_the_lut_keys() {
        let mut rng = Rng::new(5);
        let mut rows = [[0u64; 8]; 8];
        for v in rows.iter_mut().flatten() {
            *v = rng.next_u64();
        }
        let orig = rows;
        transpose_stage(&mut rows, 4, 0x0F0F_0F0F_0F0F_0F0F);
        transpose_stage(&mut rows, 2, 0x3333_3333_3333_3333);
        transpose_stage(&mut rows, 1, 0x5555_5555_5555_5555);
        // Byte c of rows[b][g], bit i = pixel 8c + b of pattern 8g + i (= orig[i][g]).
        for b in 0..8 {
            for g in 0..8 {
                for c in 0..8 {
                    for i in 0..8 {
                        let got = (rows[b][g] >> (8 * c + i)) & 1;
                        let want = (orig[i][g] >> (8 * c + b)) & 1;
                        assert_eq!(got, want, "b {b} g {g} c {c} i {i}");
                    }
                }
            }
        }
    }

    #[test]
    fn lut_holds_subset_sums() {
        let w0 = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0];
        let w1 = [-1.0; 8];
        let mut lut = [[0.0; 2]; 256];
        build_lut(&w0, &w1, &mut lut);
        for (s, v) in lut.iter().enumerate() {
            assert_eq!(*v, [s as f64, -(s.count_ones() as f64)]);
        }
    }

    #[test]
    fn nibble_table_dot_matches_the_plain_dot() {
        let t = random_scene(150, -1.0, 1.0, 3);
        let table = nibble_table(&t, 3);
        let mut rng = Rng::new(4);
        // 20 patterns of 150 pixels (3 words; bits past 150 clear), every other one with its
        // last word clear.
        let mut bits = Vec::new();
        for j in 0..20 {
            let last = if j % 2 == 0 {
                rng.next_u64() & ((1 << 22) - 1)
            } else {
                0
            };
            bits.extend([rng.next_u64(), rng.next_u64(), last]);
        }
        let mut dots = vec![0.0; 20];
        dot_bits(&bits, 3, &table, &mut dots);
        for (j, words) in bits.chunks_exact(3).enumerate() {
            let plain: f64 = (0..150)
                .filter(|&x| words[x / 64] >> (x % 64) & 1 == 1)
                .map(|x| t[x])
                .sum();
            assert!(
                (dots[j] - plain).abs() < 1e-12,
                "pattern {j}: {} vs {plain}",
                dots[j]
            );
        }
        let v: Vec<f32> = (0..150).map(|i| (i % 9) as f32 / 8.0).collect();
        let plain: f64 = v.iter().zip(&t).map(|(&v, &t)| v as f64 * t).sum();
        assert!((dot_values(&v, &t) - plain).abs() < 1e-12);
    }
}
