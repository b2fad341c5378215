//! Packed 0/1 matrices and their product with real vectors by byte look-up tables.
//!
//! # Layout
//!
//! A [`BitMatrix`] is built from row-major packed rows: column `c` of a row is bit `c % 64` of
//! word `c / 64` (the pattern generator's layout, so a pattern is a row). Internally the words
//! are stored in column blocks of [`BLOCK_WORDS`] words (128 columns): block `b` holds, for every
//! row in turn, that row's `BLOCK_WORDS` words of the block, so the product kernel streams each
//! block as one contiguous run of memory. (Measured: 2.5-4x faster than row-major rows, where
//! every row's slice of a block is a separate cache line and page.)
//!
//! # Kernel
//!
//! `out = B v` (and batched, `L` vectors at once): for every byte of columns (8 columns) build the
//! table of the 256 subset sums of those 8 entries of `v` (255 additions; an entry is `[f64; L]`,
//! so one look-up serves all `L` vectors), then each row adds one table entry per byte of its
//! bits: `rows * cols / 8` look-ups instead of `rows * cols` multiply-adds. Table building costs
//! `32 * cols * L` additions, negligible once `rows` is more than a few hundred. A block's 16
//! tables (32 KiB for one vector) stay in L1 (48 KiB per core here) while its rows stream
//! through. About 0.2-0.3 ns per look-up and thread here, 0.15 ns per look-up and vector in
//! batches of four. Measured with `ops::bench::bench_bits_kernel`, 1638 x 16384 bits, best of 5,
//! three interleaved runs: blocks of 2 words take 0.35-0.52 ms per apply and 0.40-0.53 ms per
//! adjoint, blocks of 4 words (64 KiB tables, spilling to L2) 0.51-0.77 and 0.62-0.84 ms;
//! blocks of 1 word are no faster than 2, and neither are tables of 2 blocks per pass.
//!
//! # AVX-512 kernel
//!
//! Where the CPU has AVX-512F ([`Kernel::Nibbles`], chosen at run time), the tables are of
//! nibbles instead: the 16 subset sums of 4 columns fill two registers, and `vpermi2pd` looks
//! up 8 rows' nibbles at once (8 tables, 32 columns, per pass over a block's rows; the rows'
//! words come from the same block layout, two loads and a permute per 8 rows). One vector per
//! pass, so a vector's product is the same alone or in a batch; the sums are taken in another
//! order than the byte kernel's, so the two differ by rounding. Measured in one run of
//! `bench_bits_kernel` (1638 x 16384, two threads, per vector): nibbles 0.20-0.21 ms per apply
//! and 0.22-0.23 ms per adjoint, bytes 0.52-0.53 and 0.48-0.55 ms one vector at a time and
//! 0.32-0.35 and 0.28-0.35 ms in batches of four (two runs). With it, batching no longer pays
//! ([`LinearOperator::batching_pays`](crate::linop::LinearOperator::batching_pays)).
//!
//! Threads (rayon) take disjoint ranges of column blocks, each with its own tables and output
//! partial, summed at the end (`rows * L` additions per thread). Splitting rows instead makes
//! each thread build every table; measured on the 16384 x 1638 adjoint (13 blocks), it was no
//! faster. Small products run on the calling thread.

use rayon::prelude::*;

use super::scratch::Pool;

/// Words (of 64 columns) per column block: 2, so that one vector's tables (32 KiB) fit L1.
pub const BLOCK_WORDS: usize = 2;

/// A packed 0/1 matrix (see the module docs for the layout).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BitMatrix {
    rows: usize,
    cols: usize,
    /// Words per row in the row-major form: ceil(cols / 64).
    words: usize,
    /// Column blocks: ceil(words / BLOCK_WORDS).
    blocks: usize,
    /// Block-major: `data[(b * rows + r) * BLOCK_WORDS + j]` = word `b * BLOCK_WORDS + j` of row r.
    data: Vec<u64>,
}

/// Products smaller than this (rows x words x vectors) run on one thread.
const PARALLEL_MIN_WORDS: usize = 1 << 13;

/// The product kernels (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// Byte tables in memory, any CPU; batches of up to 4 vectors share a pass.
    Bytes,
    /// Nibble tables in AVX-512 registers, 8 rows at a time; one vector per pass.
    Nibbles,
}

impl Kernel {
    /// [`Kernel::Nibbles`] where the CPU has AVX-512F (and `HELMHOLTZ_SIMD` allows it),
    /// [`Kernel::Bytes`] elsewhere.
    pub fn best() -> Kernel {
        if crate::simd::avx512() {
            Kernel::Nibbles
        } else {
            Kernel::Bytes
        }
    }
}

impl BitMatrix {
    /// From row-major packed words (`ceil(cols / 64)` per row). Bits past `cols` are cleared.
    pub fn new(rows: usize, cols: usize, mut row_major: Vec<u64>) -> Self {
        let words = cols.div_ceil(64);
        assert_eq!(
            row_major.len(),
            rows * words,
            "bit matrix needs rows * ceil(cols / 64) words"
        );
        let tail = cols % 64;
        if tail != 0 {
            for row in row_major.chunks_exact_mut(words) {
                row[words - 1] &= (1u64 << tail) - 1;
            }
        }
        let blocks = words.div_ceil(BLOCK_WORDS);
        let mut data = vec![0u64; blocks * rows * BLOCK_WORDS];
        if rows > 0 && blocks > 0 {
            data.par_chunks_mut(rows * BLOCK_WORDS)
                .enumerate()
                .for_each(|(b, block)| {
                    let w0 = b * BLOCK_WORDS;
                    let n = BLOCK_WORDS.min(words - w0);
                    for (r, dst) in block.chunks_exact_mut(BLOCK_WORDS).enumerate() {
                        dst[..n].copy_from_slice(&row_major[r * words + w0..r * words + w0 + n]);
                    }
                });
        }
        BitMatrix {
            rows,
            cols,
            words,
            blocks,
            data,
        }
    }

    /// Rows produced in parallel by `fill(r, row_words)` (e.g. `PatternGenerator::fill_bits`),
    /// `row_words.len() == ceil(cols / 64)`, written straight into the block layout.
    pub fn from_fn(rows: usize, cols: usize, fill: impl Fn(usize, &mut [u64]) + Sync) -> Self {
        let words = cols.div_ceil(64);
        let blocks = words.div_ceil(BLOCK_WORDS);
        let mut data = vec![0u64; blocks * rows * BLOCK_WORDS];
        if rows > 0 && blocks > 0 {
            // Task t fills rows t*per..(t+1)*per: in every block, one contiguous run.
            let per = 64usize;
            let tasks = rows.div_ceil(per);
            let mut runs: Vec<Vec<&mut [u64]>> =
                (0..tasks).map(|_| Vec::with_capacity(blocks)).collect();
            for block in data.chunks_mut(rows * BLOCK_WORDS) {
                for (t, run) in block.chunks_mut(per * BLOCK_WORDS).enumerate() {
                    runs[t].push(run);
                }
            }
            runs.into_par_iter().enumerate().for_each(|(t, mut runs)| {
                let mut row = vec![0u64; words];
                for i in 0..per.min(rows - t * per) {
                    row.fill(0);
                    fill(t * per + i, &mut row);
                    let tail = cols % 64;
                    if tail != 0 {
                        row[words - 1] &= (1u64 << tail) - 1;
                    }
                    for (b, run) in runs.iter_mut().enumerate() {
                        let w0 = b * BLOCK_WORDS;
                        let n = BLOCK_WORDS.min(words - w0);
                        run[i * BLOCK_WORDS..i * BLOCK_WORDS + n].copy_from_slice(&row[w0..w0 + n]);
                    }
                }
            });
        }
        BitMatrix {
            rows,
            cols,
            words,
            blocks,
            data,
        }
    }

    pub fn rows(&self) -> usize {
        self.rows
    }
    pub fn cols(&self) -> usize {
        self.cols
    }
    /// Words per row in the row-major form, `ceil(cols / 64)`.
    pub fn words_per_row(&self) -> usize {
        self.words
    }

    /// Word `w` of row `r` in the row-major form.
    #[inline]
    pub fn word(&self, r: usize, w: usize) -> u64 {
        self.data[((w / BLOCK_WORDS) * self.rows + r) * BLOCK_WORDS + w % BLOCK_WORDS]
    }

    #[inline]
    pub fn get(&self, r: usize, c: usize) -> bool {
        (self.word(r, c / 64) >> (c % 64)) & 1 == 1
    }

    /// Row `r` as row-major words.
    pub fn row_words(&self, r: usize) -> Vec<u64> {
        (0..self.words).map(|w| self.word(r, w)).collect()
    }

    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.data.len() * 8
    }

    /// Number of set bits in each row.
    pub fn row_sums(&self) -> Vec<f64> {
        let mut sums = vec![0u64; self.rows];
        if self.rows > 0 {
            for block in self.data.chunks_exact(self.rows * BLOCK_WORDS) {
                for (s, row) in sums.iter_mut().zip(block.chunks_exact(BLOCK_WORDS)) {
                    *s += row.iter().map(|w| w.count_ones() as u64).sum::<u64>();
                }
            }
        }
        sums.into_iter().map(|s| s as f64).collect()
    }

    /// The transpose (`cols x rows`), by 64 x 64 bit-block transposes, written straight into
    /// the block layout; output column blocks in parallel.
    pub fn transpose(&self) -> BitMatrix {
        let (rows, cols) = (self.rows, self.cols);
        let twords = rows.div_ceil(64); // words per row of the transpose
        let tblocks = twords.div_ceil(BLOCK_WORDS);
        let mut data = vec![0u64; tblocks * cols * BLOCK_WORDS];
        if tblocks > 0 && cols > 0 {
            // Output block tb: transposed rows j (0..cols), words tb*BLOCK_WORDS + q, i.e. our
            // rows (tb*BLOCK_WORDS + q)*64 + i, at data[(tb*cols + j)*BLOCK_WORDS + q].
            data.par_chunks_mut(cols * BLOCK_WORDS)
                .enumerate()
                .for_each(|(tb, out)| {
                    let mut block = [0u64; 64];
                    for q in 0..BLOCK_WORDS {
                        let rb = tb * BLOCK_WORDS + q;
                        if rb >= twords {
                            break;
                        }
                        for w in 0..self.words {
                            for (i, v) in block.iter_mut().enumerate() {
                                let r = rb * 64 + i;
                                *v = if r < rows { self.word(r, w) } else { 0 };
                            }
                            transpose64(&mut block);
                            // block[j] bit i = element (rb*64 + i, w*64 + j).
                            for (j, &v) in block.iter().enumerate().take(cols - w * 64) {
                                out[(w * 64 + j) * BLOCK_WORDS + q] = v;
                            }
                        }
                    }
                });
        }
        BitMatrix {
            rows: cols,
            cols: rows,
            words: twords,
            blocks: tblocks,
            data,
        }
    }

    /// `out = B v` for one vector (`v.len() == cols`, `out.len() == rows`, overwritten).
    pub fn matvec(&self, v: &[f64], out: &mut [f64], pool: &Pool) {
        self.matvec_batch(v, out, 1, pool);
    }

    /// `batch` products at once: `vs` holds `batch` vectors of length `cols` back to back, `out`
    /// receives `batch` vectors of length `rows`. With the byte kernel groups of 4 (then 2, 1)
    /// vectors share one pass over the bits; the nibble kernel takes one pass per vector.
    pub fn matvec_batch(&self, vs: &[f64], out: &mut [f64], batch: usize, pool: &Pool) {
        self.matvec_batch_with(vs, out, batch, pool, Kernel::best());
    }

    /// [`BitMatrix::matvec_batch`] with the given kernel. [`Kernel::Nibbles`] panics unless the
    /// AVX-512 kernels are on (the CPU has AVX-512F and `HELMHOLTZ_SIMD` allows them).
    pub fn matvec_batch_with(
        &self,
        vs: &[f64],
        out: &mut [f64],
        batch: usize,
        pool: &Pool,
        kernel: Kernel,
    ) {
        assert_eq!(
            vs.len(),
            self.cols * batch,
            "input must hold batch * cols values"
        );
        assert_eq!(
            out.len(),
            self.rows * batch,
            "output must hold batch * rows values"
        );
        let (mut done, rows, cols) = (0, self.rows, self.cols);
        if kernel == Kernel::Nibbles {
            assert!(crate::simd::avx512(), "the nibble kernel needs AVX-512F");
            // One vector per pass: a vector's product is the same alone or in a batch.
            for l in 0..batch {
                let o = &mut out[l * rows..(l + 1) * rows];
                self.product::<1>(&vs[l * cols..(l + 1) * cols], o, pool, kernel);
            }
            return;
        }
        while done < batch {
            let left = batch - done;
            let v = &vs[done * cols..];
            let o = &mut out[done * rows..];
            done += if left >= 4 {
                self.product::<4>(&v[..4 * cols], &mut o[..4 * rows], pool, kernel);
                4
            } else if left >= 2 {
                self.product::<2>(&v[..2 * cols], &mut o[..2 * rows], pool, kernel);
                2
            } else {
                self.product::<1>(&v[..cols], &mut o[..rows], pool, kernel);
                1
            };
        }
    }

    /// `L` vectors (back to back in `vs`) through one pass; writes `out` (back to back).
    fn product<const L: usize>(&self, vs: &[f64], out: &mut [f64], pool: &Pool, kernel: Kernel) {
        let (rows, blocks) = (self.rows, self.blocks);
        if rows == 0 {
            return;
        }
        if blocks == 0 {
            out.fill(0.0);
            return;
        }
        let table_len = BLOCK_WORDS * 8 * 256 * L;
        let threads = rayon::current_num_threads().max(1);
        // Not `* L`: the split over threads (and so the order of the partial sums) must not
        // depend on the batch, so that a vector's product is the same alone or in a batch.
        let parts = if rows * self.words < PARALLEL_MIN_WORDS || threads == 1 {
            1
        } else {
            threads.min(blocks)
        };
        let part_len = rows * L;
        let mut partials = pool.take(parts * part_len);
        let run = |p: usize, partial: &mut [f64]| {
            let b0 = p * blocks / parts;
            let b1 = (p + 1) * blocks / parts;
            if kernel == Kernel::Nibbles {
                debug_assert_eq!(L, 1);
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `matvec_batch_with` checked that the CPU has AVX-512F.
                unsafe {
                    self.kernel_nibbles(vs, b0, b1, partial)
                };
                return;
            }
            let mut tables = pool.take(table_len);
            let (tables, _) = tables.as_chunks_mut::<L>();
            let (acc, _) = partial.as_chunks_mut::<L>();
            self.kernel::<L>(vs, b0, b1, tables, acc);
        };
        if parts == 1 {
            run(0, &mut partials);
        } else {
            partials
                .par_chunks_mut(part_len)
                .enumerate()
                .for_each(|(p, part)| run(p, part));
        }
        // out[l * rows + r] = sum over parts of partial[p][r * L + l].
        let (first, rest) = partials.split_at(part_len);
        for l in 0..L {
            let o = &mut out[l * rows..(l + 1) * rows];
            for (r, v) in o.iter_mut().enumerate() {
                *v = first[r * L + l];
            }
            for part in rest.chunks_exact(part_len) {
                for (r, v) in o.iter_mut().enumerate() {
                    *v += part[r * L + l];
                }
            }
        }
    }

    /// Adds, for every row, the contribution of column blocks `b0..b1` to `acc[row]`.
    fn kernel<const L: usize>(
        &self,
        vs: &[f64],
        b0: usize,
        b1: usize,
        tables: &mut [[f64; L]],
        acc: &mut [[f64; L]],
    ) {
        let rows = self.rows;
        for b in b0..b1 {
            build_tables::<L>(vs, self.cols, b * BLOCK_WORDS * 64, tables);
            let (tabs, _) = tables.as_chunks::<256>();
            let (tabs8, _) = tabs.as_chunks::<8>();
            let tabs8: &[[[[f64; L]; 256]; 8]; BLOCK_WORDS] = tabs8[..BLOCK_WORDS]
                .try_into()
                .expect("tables hold one block");
            let block = &self.data[b * rows * BLOCK_WORDS..(b + 1) * rows * BLOCK_WORDS];
            let (block, _) = block.as_chunks::<BLOCK_WORDS>();
            for (a, row) in acc.iter_mut().zip(block) {
                let (mut s0, mut s1) = ([0.0; L], [0.0; L]);
                for (&word, t) in row.iter().zip(tabs8) {
                    let b = word.to_le_bytes();
                    let x0 = add(t[0][b[0] as usize], t[1][b[1] as usize]);
                    let x1 = add(t[2][b[2] as usize], t[3][b[3] as usize]);
                    let x2 = add(t[4][b[4] as usize], t[5][b[5] as usize]);
                    let x3 = add(t[6][b[6] as usize], t[7][b[7] as usize]);
                    s0 = add(s0, add(x0, x1));
                    s1 = add(s1, add(x2, x3));
                }
                *a = add(*a, add(s0, s1));
            }
        }
    }
}

impl BitMatrix {
    /// [`Kernel::Nibbles`]: adds, for every row, the contribution of column blocks `b0..b1` of
    /// one vector `v` to `acc[row]`. Per quarter block (32 columns, half a word): the 16 subset
    /// sums of each 4 columns (8 tables, 16 registers), then for 8 rows at a time their words
    /// (two loads and a permute from the block layout), each nibble shifted into place and
    /// looked up in 8 lanes at once (`vpermi2pd`: the low 4 bits of a lane pick one of 16
    /// entries, higher bits are ignored), the 8 look-ups summed as a tree and added to the
    /// rows' sums. Rows past the last multiple of 8 take the same sums one by one.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn kernel_nibbles(&self, v: &[f64], b0: usize, b1: usize, acc: &mut [f64]) {
        use std::arch::x86_64::*;
        const _: () = assert!(BLOCK_WORDS == 2, "the loads below take 8 rows of 2 words");
        let (rows, cols) = (self.rows, self.cols);
        let groups = rows / 8;
        let mut tab = [0.0f64; 8 * 16];
        // Word 0 and word 1 of rows 0..8 from the 16 words of 8 consecutive rows.
        let even = _mm512_set_epi64(14, 12, 10, 8, 6, 4, 2, 0);
        let odd = _mm512_set_epi64(15, 13, 11, 9, 7, 5, 3, 1);
        for b in b0..b1 {
            let block = &self.data[b * rows * BLOCK_WORDS..(b + 1) * rows * BLOCK_WORDS];
            for quarter in 0..4 {
                let c0 = b * BLOCK_WORDS * 64 + quarter * 32;
                for (n, t) in tab.chunks_exact_mut(16).enumerate() {
                    t[0] = 0.0;
                    for bit in 0..4 {
                        let c = c0 + 4 * n + bit;
                        let w = if c < cols { v[c] } else { 0.0 };
                        let half = 1 << bit;
                        for i in 0..half {
                            t[half + i] = t[i] + w;
                        }
                    }
                }
                // SAFETY (all loads and stores below): `tab` holds 128 values; a group's 16
                // words lie inside `block` (g < rows / 8); `acc` holds `rows` values.
                let lo: [__m512d; 8] =
                    std::array::from_fn(|n| unsafe { _mm512_loadu_pd(tab.as_ptr().add(16 * n)) });
                let hi: [__m512d; 8] = std::array::from_fn(|n| unsafe {
                    _mm512_loadu_pd(tab.as_ptr().add(16 * n + 8))
                });
                let (word, high) = (quarter / 2, quarter % 2 == 1);
                let pick = if word == 0 { even } else { odd };
                for g in 0..groups {
                    let p = unsafe { block.as_ptr().add(g * 8 * BLOCK_WORDS) } as *const __m512i;
                    let (a, c) = unsafe { (_mm512_loadu_si512(p), _mm512_loadu_si512(p.add(1))) };
                    let mut idx = _mm512_permutex2var_epi64(a, pick, c);
                    if high {
                        idx = _mm512_srli_epi64::<32>(idx);
                    }
                    let l0 = _mm512_permutex2var_pd(lo[0], idx, hi[0]);
                    let l1 = _mm512_permutex2var_pd(lo[1], _mm512_srli_epi64::<4>(idx), hi[1]);
                    let l2 = _mm512_permutex2var_pd(lo[2], _mm512_srli_epi64::<8>(idx), hi[2]);
                    let l3 = _mm512_permutex2var_pd(lo[3], _mm512_srli_epi64::<12>(idx), hi[3]);
                    let l4 = _mm512_permutex2var_pd(lo[4], _mm512_srli_epi64::<16>(idx), hi[4]);
                    let l5 = _mm512_permutex2var_pd(lo[5], _mm512_srli_epi64::<20>(idx), hi[5]);
                    let l6 = _mm512_permutex2var_pd(lo[6], _mm512_srli_epi64::<24>(idx), hi[6]);
                    let l7 = _mm512_permutex2var_pd(lo[7], _mm512_srli_epi64::<28>(idx), hi[7]);
                    let sum = _mm512_add_pd(
                        _mm512_add_pd(_mm512_add_pd(l0, l1), _mm512_add_pd(l2, l3)),
                        _mm512_add_pd(_mm512_add_pd(l4, l5), _mm512_add_pd(l6, l7)),
                    );
                    let o = unsafe { acc.as_mut_ptr().add(8 * g) };
                    unsafe { _mm512_storeu_pd(o, _mm512_add_pd(_mm512_loadu_pd(o), sum)) };
                }
                for (r, a) in acc.iter_mut().enumerate().take(rows).skip(8 * groups) {
                    let w = block[r * BLOCK_WORDS + word] >> if high { 32 } else { 0 };
                    let l = |n: usize| tab[16 * n + ((w >> (4 * n)) & 15) as usize];
                    *a += ((l(0) + l(1)) + (l(2) + l(3))) + ((l(4) + l(5)) + (l(6) + l(7)));
                }
            }
        }
    }
}

#[inline(always)]
fn add<const L: usize>(a: [f64; L], b: [f64; L]) -> [f64; L] {
    std::array::from_fn(|l| a[l] + b[l])
}

/// Tables for bytes of columns starting at `col0` (`tables.len() / 256` bytes): entry `s` of the
/// table of byte `b` is the sum over the set bits i of s of `v[col0 + 8b + i]`, per vector.
fn build_tables<const L: usize>(vs: &[f64], cols: usize, col0: usize, tables: &mut [[f64; L]]) {
    for (b, t) in tables.chunks_exact_mut(256).enumerate() {
        t[0] = [0.0; L];
        for bit in 0..8 {
            let c = col0 + 8 * b + bit;
            let w: [f64; L] =
                std::array::from_fn(|l| if c < cols { vs[l * cols + c] } else { 0.0 });
            let half = 1 << bit;
            let (lo, hi) = t.split_at_mut(half);
            for (h, &l) in hi[..half].iter_mut().zip(lo.iter()) {
                *h = add(l, w);
            }
        }
    }
}

/// In-place transpose of a 64 x 64 bit block: bit j of `a[i]` <-> bit i of `a[j]`.
fn transpose64(a: &mut [u64; 64]) {
    let mut j = 32usize;
    let mut m: u64 = 0x0000_0000_FFFF_FFFF;
    while j != 0 {
        let mut k = 0usize;
        while k < 64 {
            let t = ((a[k] >> j) ^ a[k + j]) & m;
            a[k + j] ^= t;
            a[k] ^= t << j;
            k = (k + j + 1) & !j;
        }
        j >>= 1;
        m ^= m << j;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linop::test_vector;

    fn random_bits(rows: usize, cols: usize, seed: u64) -> BitMatrix {
        BitMatrix::from_fn(rows, cols, |r, row| {
            for (w, v) in row.iter_mut().enumerate() {
                *v = helmholtz_proto::patterns::rng::stream_word(seed, (r * 1000 + w) as u64);
            }
        })
    }

    #[test]
    fn transpose_matches_bits() {
        for (rows, cols) in [(1, 1), (3, 70), (64, 64), (130, 65), (200, 300), (7, 129)] {
            let b = random_bits(rows, cols, rows as u64);
            let t = b.transpose();
            assert_eq!((t.rows(), t.cols()), (cols, rows));
            for r in 0..rows {
                for c in 0..cols {
                    assert_eq!(b.get(r, c), t.get(c, r), "{rows}x{cols} ({r},{c})");
                }
            }
            // Padding bits stay clear; the row-major constructor gives the same matrix.
            assert_eq!(t.transpose(), b);
            let row_major: Vec<u64> = (0..rows).flat_map(|r| b.row_words(r)).collect();
            assert_eq!(BitMatrix::new(rows, cols, row_major), b);
        }
    }

    /// Both kernels where the CPU runs both.
    fn kernels() -> Vec<Kernel> {
        let mut k = vec![Kernel::Bytes];
        if crate::simd::avx512() {
            k.push(Kernel::Nibbles);
        }
        k
    }

    #[test]
    fn product_matches_naive_for_every_group_size() {
        let pool = Pool::new();
        // Row counts below, at and past multiples of 8 (the nibble kernel's groups), partial
        // last words and blocks, several blocks per thread.
        for (rows, cols) in [
            (5, 3),
            (33, 64),
            (17, 200),
            (300, 1000),
            (1000, 520),
            (8, 129),
            (16, 256),
            (23, 4100),
        ] {
            let b = random_bits(rows, cols, 9);
            for (kernel, batch) in kernels()
                .into_iter()
                .flat_map(|k| [1, 2, 3, 4, 7].map(|b| (k, b)))
            {
                let vs = test_vector(cols * batch, 3);
                let mut out = vec![f64::NAN; rows * batch];
                b.matvec_batch_with(&vs, &mut out, batch, &pool, kernel);
                for l in 0..batch {
                    for r in 0..rows {
                        let want: f64 = (0..cols)
                            .filter(|&c| b.get(r, c))
                            .map(|c| vs[l * cols + c])
                            .sum();
                        let got = out[l * rows + r];
                        assert!(
                            (got - want).abs() < 1e-12,
                            "{kernel:?} {rows}x{cols} b{batch} {got} {want}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn a_vector_gets_the_same_bits_alone_or_in_a_batch() {
        let pool = Pool::new();
        let (rows, cols) = (1003, 2100);
        let b = random_bits(rows, cols, 5);
        for kernel in kernels() {
            let vs = test_vector(cols * 3, 7);
            let mut batch = vec![0.0; rows * 3];
            b.matvec_batch_with(&vs, &mut batch, 3, &pool, kernel);
            for l in 0..3 {
                let mut one = vec![0.0; rows];
                b.matvec_batch_with(&vs[l * cols..(l + 1) * cols], &mut one, 1, &pool, kernel);
                assert!(
                    one.iter()
                        .zip(&batch[l * rows..])
                        .all(|(a, c)| a.to_bits() == c.to_bits()),
                    "{kernel:?} vector {l}"
                );
            }
        }
    }
}
