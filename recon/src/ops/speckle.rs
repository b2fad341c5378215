//! Grey-level (speckle) patterns: a dense `n x cells` matrix of f32 levels, generated once.
//!
//! A speckle pattern is constant on `grain x grain` cells (clipped at the right and bottom
//! edges), so `P = S C` with `C` the pixel -> cell summing map and `S` the `n x cells` levels: the
//! matrix stores cells, not pixels (a factor `grain^2` less memory and work). Levels are exact in
//! f32 (24-bit fractions); products accumulate in f64. 4 bytes per pattern-cell: 128 x 128 at
//! 10 % is 107 MB, 256 x 256 at 10 % 1.7 GB (refused above [`super::MEMORY_LIMIT`]).
//!
//! `apply`: rows in parallel, each a dot product with the cell sums of `x`; `adjoint`: bands of
//! cells in parallel, each accumulating `y_i S_i` over all rows. Batched forms read the matrix
//! once per group of up to four vectors. Memory-bound: about the time to stream the matrix.

use helmholtz_proto::patterns::rng::stream_word;
use helmholtz_proto::patterns::speckle_level;
use helmholtz_proto::{Family, PatternSpec};
use rayon::prelude::*;

use super::OpError;
use super::scratch::Pool;
use crate::linop::LinearOperator;

/// Cells per adjoint task.
const BAND: usize = 1024;
/// Rows per forward task.
const ROW_TASK: usize = 16;

#[derive(Debug)]
pub struct SpeckleOperator {
    width: u32,
    height: u32,
    grain: u32,
    rows: usize,
    cells: usize,
    /// Cell of every pixel; empty when grain is 1 (cell = pixel).
    pixel_cell: Vec<u32>,
    /// Row-major `rows x cells` levels.
    values: Vec<f32>,
    pool: Pool,
}

impl SpeckleOperator {
    /// Patterns `0..rows` of a speckle spec.
    pub fn from_spec(spec: &PatternSpec, rows: u64) -> Result<Self, OpError> {
        let Family::Speckle { grain } = *spec.family() else {
            return Err(OpError::WrongFamily {
                want: "speckle",
                got: spec.family().name(),
            });
        };
        super::check_rows(spec, rows)?;
        let (w, h) = (spec.width(), spec.height());
        let cx = w.div_ceil(grain) as usize;
        let cells = cx * h.div_ceil(grain) as usize;
        super::check_memory(rows as usize * cells * 4)?;
        let seed = spec.seed();
        let mut values = vec![0f32; rows as usize * cells];
        values
            .par_chunks_mut(cells.max(1))
            .enumerate()
            .with_min_len(8)
            .for_each(|(i, row)| {
                let base = (i as u64).wrapping_mul(cells as u64);
                for (c, v) in row.iter_mut().enumerate() {
                    *v = speckle_level(stream_word(seed, base.wrapping_add(c as u64)));
                }
            });
        Ok(Self::from_cells(w, h, grain, rows as usize, values))
    }

    /// From levels: `rows` patterns of `ceil(W/grain) * ceil(H/grain)` cells each, row-major
    /// cells (`cell = (y / grain) * ceil(W / grain) + x / grain`).
    pub fn from_cells(width: u32, height: u32, grain: u32, rows: usize, values: Vec<f32>) -> Self {
        let cx = width.div_ceil(grain) as usize;
        let cells = cx * height.div_ceil(grain) as usize;
        assert_eq!(
            values.len(),
            rows * cells,
            "speckle levels must be rows x cells"
        );
        let g = grain as usize;
        let pixel_cell = if grain == 1 {
            Vec::new()
        } else {
            (0..height as usize)
                .flat_map(|y| (0..width as usize).map(move |x| ((y / g) * cx + x / g) as u32))
                .collect()
        };
        SpeckleOperator {
            width,
            height,
            grain,
            rows,
            cells,
            pixel_cell,
            values,
            pool: Pool::new(),
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn grain(&self) -> u32 {
        self.grain
    }
    /// The `rows x cells` levels.
    pub fn levels(&self) -> &[f32] {
        &self.values
    }
    pub fn memory_bytes(&self) -> usize {
        self.values.len() * 4 + self.pixel_cell.len() * 4
    }

    fn k(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// `L` vectors (back to back, length k) to cell sums (back to back, length cells).
    fn to_cells(&self, xs: &[f64], out: &mut [f64], l: usize) {
        let k = self.k();
        for v in 0..l {
            let (x, o) = (
                &xs[v * k..(v + 1) * k],
                &mut out[v * self.cells..(v + 1) * self.cells],
            );
            o.fill(0.0);
            for (&c, &xv) in self.pixel_cell.iter().zip(x) {
                o[c as usize] += xv;
            }
        }
    }

    fn forward<const L: usize>(&self, xs: &[f64], ys: &mut [f64]) {
        let (n, cells) = (self.rows, self.cells);
        let mut cell_buf;
        let xc: &[f64] = if self.grain == 1 {
            xs
        } else {
            cell_buf = self.pool.take(L * cells);
            self.to_cells(xs, &mut cell_buf, L);
            &cell_buf
        };
        let mut inter = self.pool.take(n * L);
        let (inter_rows, _) = inter.as_chunks_mut::<L>();
        let body = |(t, out): (usize, &mut [[f64; L]])| {
            for (j, o) in out.iter_mut().enumerate() {
                let i = t * ROW_TASK + j;
                let row = &self.values[i * cells..(i + 1) * cells];
                *o = dot_rows::<L>(row, xc, cells);
            }
        };
        if n * cells >= 1 << 16 {
            inter_rows
                .par_chunks_mut(ROW_TASK)
                .enumerate()
                .for_each(body);
        } else {
            inter_rows.chunks_mut(ROW_TASK).enumerate().for_each(body);
        }
        for l in 0..L {
            for (i, y) in ys[l * n..(l + 1) * n].iter_mut().enumerate() {
                *y = inter[i * L + l];
            }
        }
    }

    fn backward<const L: usize>(&self, ys: &[f64], xs: &mut [f64]) {
        let (n, cells, k) = (self.rows, self.cells, self.k());
        // Interleaved accumulators [cells][L], banded.
        let mut acc = self.pool.take(cells * L);
        let (acc_cells, _) = acc.as_chunks_mut::<L>();
        let body = |(b, band): (usize, &mut [[f64; L]])| {
            let c0 = b * BAND;
            for i in 0..n {
                let w: [f64; L] = std::array::from_fn(|l| ys[l * n + i]);
                let row = &self.values[i * cells + c0..i * cells + c0 + band.len()];
                for (a, &s) in band.iter_mut().zip(row) {
                    let s = s as f64;
                    for l in 0..L {
                        a[l] += w[l] * s;
                    }
                }
            }
        };
        if n * cells >= 1 << 16 {
            acc_cells.par_chunks_mut(BAND).enumerate().for_each(body);
        } else {
            acc_cells.chunks_mut(BAND).enumerate().for_each(body);
        }
        for l in 0..L {
            let x = &mut xs[l * k..(l + 1) * k];
            if self.grain == 1 {
                for (xj, a) in x.iter_mut().zip(acc.chunks_exact(L)) {
                    *xj = a[l];
                }
            } else {
                for (xj, &c) in x.iter_mut().zip(&self.pixel_cell) {
                    *xj = acc[c as usize * L + l];
                }
            }
        }
    }

    fn batched(&self, ins: &[f64], outs: &mut [f64], batch: usize, forward: bool) {
        let (ilen, olen) = if forward {
            (self.k(), self.rows)
        } else {
            (self.rows, self.k())
        };
        assert_eq!(ins.len(), ilen * batch);
        assert_eq!(outs.len(), olen * batch);
        let mut done = 0;
        while done < batch {
            let l = if batch - done >= 4 {
                4
            } else if batch - done >= 2 {
                2
            } else {
                1
            };
            let i = &ins[done * ilen..(done + l) * ilen];
            let o = &mut outs[done * olen..(done + l) * olen];
            match (l, forward) {
                (4, true) => self.forward::<4>(i, o),
                (2, true) => self.forward::<2>(i, o),
                (_, true) => self.forward::<1>(i, o),
                (4, false) => self.backward::<4>(i, o),
                (2, false) => self.backward::<2>(i, o),
                (_, false) => self.backward::<1>(i, o),
            }
            done += l;
        }
    }
}

/// Dot products of one f32 row with `L` f64 vectors (back to back, `cells` each); four running
/// sums per vector.
#[inline]
fn dot_rows<const L: usize>(row: &[f32], xs: &[f64], cells: usize) -> [f64; L] {
    std::array::from_fn(|l| {
        let x = &xs[l * cells..(l + 1) * cells];
        let mut s = [0f64; 4];
        let (rc, rr) = row.as_chunks::<4>();
        let (xc, xr) = x.as_chunks::<4>();
        for (r4, x4) in rc.iter().zip(xc) {
            for q in 0..4 {
                s[q] += r4[q] as f64 * x4[q];
            }
        }
        let tail: f64 = rr.iter().zip(xr).map(|(&a, &b)| a as f64 * b).sum();
        (s[0] + s[1]) + (s[2] + s[3]) + tail
    })
}

impl LinearOperator for SpeckleOperator {
    fn rows(&self) -> usize {
        self.rows
    }
    fn cols(&self) -> usize {
        self.k()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.batched(x, y, 1, true);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        self.batched(y, x, 1, false);
    }
    fn apply_batch(&self, xs: &[f64], ys: &mut [f64], batch: usize) {
        self.batched(xs, ys, batch, true);
    }
    fn adjoint_batch(&self, ys: &[f64], xs: &mut [f64], batch: usize) {
        self.batched(ys, xs, batch, false);
    }
    /// Up to 4 vectors share a pass over the patterns.
    fn batching_pays(&self) -> bool {
        true
    }
}
