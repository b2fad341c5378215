//! The TV prox's inner iteration in one banded, fused pass over the rows ([`tv_prox_pass`]),
//! and the two separate passes it replaces (`primal_from_dual`, `tv_dual_ascent`), kept as
//! the tests' bit-for-bit reference (its band function also gives a held total's threshold,
//! [`super::prox::Prox::hold_total`]).

use rayon::prelude::*;

use crate::simd::avx2_dispatch;
use crate::solve::grid::Grid;

/// Rows per band of the banded TV passes: about 4,096 pixels, so a band is worth a rayon task.
/// The split depends on the grid only, so the sums (taken band by band, in order) and hence
/// the results are the same whatever the number of threads.
fn band_rows(grid: Grid) -> usize {
    (4096 / grid.width.max(1)).clamp(1, grid.height.max(1))
}

/// One iteration of the TV prox in one pass over the rows: `out = clip(v - D^T u)`, then the
/// dual ascent step on `out` with the gap sums, computed row by row with a lag of one row
/// (row `y`'s ascent needs `out` rows `y` and `y + 1`, and `out` row `y + 1` needs the old `u`
/// of rows `y` and `y + 1`).
/// Bands of rows run in parallel; the dual rows a band reads across its edges are copied
/// before the pass, so every band sees the old `u` there. Same operations in the same order as
/// two separate passes (`primal_from_dual`, then `tv_dual_ascent`, kept as the tests'
/// reference): the same bits (tested), one parallel section and one sweep instead of two.
pub(super) fn tv_prox_pass(
    u: &mut [f64],
    v: &[f64],
    grid: Grid,
    nonneg: bool,
    gamma: f64,
    out: &mut [f64],
) -> (f64, f64, f64) {
    let (w, h) = (grid.width, grid.height);
    let k = grid.pixels();
    let rows = band_rows(grid);
    let band = rows * w;
    let (ux, uy) = u.split_at_mut(k);
    // Per band: the old uy row above it, and the old ux, uy rows below it.
    let edges: Vec<(Vec<f64>, Vec<f64>)> = (0..h.div_ceil(rows))
        .map(|i| {
            let (y0, y1) = (i * rows, ((i + 1) * rows).min(h));
            let above = if y0 > 0 {
                uy[(y0 - 1) * w..y0 * w].to_vec()
            } else {
                Vec::new()
            };
            let below = if y1 < h {
                [&ux[y1 * w..(y1 + 1) * w], &uy[y1 * w..(y1 + 1) * w]].concat()
            } else {
                Vec::new()
            };
            (above, below)
        })
        .collect();
    let sums: Vec<[f64; 3]> = ux
        .par_chunks_mut(band)
        .zip(uy.par_chunks_mut(band))
        .zip(out.par_chunks_mut(band))
        .enumerate()
        .map(|(i, ((ux, uy), out))| {
            let (above, below) = &edges[i];
            tv_prox_band(ux, uy, v, grid, i * rows, nonneg, gamma, above, below, out)
        })
        .collect();
    sums.iter().fold((0.0, 0.0, 0.0), |acc, s| {
        (acc.0 + s[0], acc.1 + s[1], acc.2 + s[2])
    })
}

/// `o = v_row - (D^T u)_row` (clipped at 0 if `nonneg`) for one row: `uxr` its ux row,
/// `uy_this` its uy row (`None` on the last grid row), `uy_prev` the uy row above (`None` on the
/// first grid row).
#[inline(always)]
fn primal_row(
    vr: &[f64],
    uxr: &[f64],
    uy_this: Option<&[f64]>,
    uy_prev: Option<&[f64]>,
    nonneg: bool,
    o: &mut [f64],
) {
    let w = vr.len();
    o[..w - 1]
        .iter_mut()
        .zip(&vr[..w - 1])
        .zip(&uxr[..w - 1])
        .for_each(|((o, &v), &u)| *o = v + u);
    o[w - 1] = vr[w - 1];
    o[1..]
        .iter_mut()
        .zip(&uxr[..w - 1])
        .for_each(|(o, &u)| *o -= u);
    if let Some(uy) = uy_this {
        o.iter_mut().zip(uy).for_each(|(o, &u)| *o += u);
    }
    if let Some(uy) = uy_prev {
        o.iter_mut().zip(uy).for_each(|(o, &u)| *o -= u);
    }
    if nonneg {
        o.iter_mut().for_each(|o| *o = o.max(0.0));
    }
}

/// The dual ascent step and gap terms of one row (`row` = `t` on it, `next` = `t` on the row
/// below, or `row` itself on the last grid row), accumulated into `lanes` as in
/// [`tv_dual_ascent_band`].
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn ascent_row(
    uxr: &mut [f64],
    uyr: &mut [f64],
    row: &[f64],
    next: &[f64],
    gamma: f64,
    mags: &mut [f64],
    dots: &mut [f64],
    lanes: &mut [[f64; 4]; 3],
) {
    #[inline(always)]
    fn step(a: f64, b: f64, ux: &mut f64, uy: &mut f64, gamma: f64, mag: &mut f64, dot: &mut f64) {
        *dot = *ux * a + *uy * b;
        *mag = (a * a + b * b).sqrt();
        let (nx, ny) = (*ux + 0.125 * a, *uy + 0.125 * b);
        let f = (gamma / (nx * nx + ny * ny).sqrt()).min(1.0);
        *ux = nx * f;
        *uy = ny * f;
    }
    let w = row.len();
    let n = w - 1;
    let (right, left) = (&row[1..], &row[..n]);
    for x in 0..n {
        step(
            right[x] - left[x],
            next[x] - left[x],
            &mut uxr[x],
            &mut uyr[x],
            gamma,
            &mut mags[x],
            &mut dots[x],
        );
    }
    step(
        0.0,
        next[n] - row[n],
        &mut uxr[n],
        &mut uyr[n],
        gamma,
        &mut mags[n],
        &mut dots[n],
    );
    for (m, d) in mags.chunks_exact(4).zip(dots.chunks_exact(4)) {
        for l in 0..4 {
            lanes[0][l] += m[l];
            lanes[1][l] += d[l];
            lanes[2][l] += d[l].abs();
        }
    }
    for x in 4 * (w / 4)..w {
        lanes[0][x & 3] += mags[x];
        lanes[1][x & 3] += dots[x];
        lanes[2][x & 3] += dots[x].abs();
    }
}

avx2_dispatch! {
/// [`tv_prox_pass`] on the rows `y0..` of one band (`ux`, `uy`, `out`: the band's rows; `above`:
/// the old uy row above the band, `below`: the old ux and uy rows below it, empty at the grid's
/// edges).
#[allow(clippy::too_many_arguments)]
fn tv_prox_band(ux: &mut [f64], uy: &mut [f64], v: &[f64], grid: Grid, y0: usize, nonneg: bool, gamma: f64, above: &[f64], below: &[f64], out: &mut [f64]) -> [f64; 3] {
    let (w, h) = (grid.width, grid.height);
    let rows = ux.len() / w;
    let y1 = y0 + rows;
    let mut mags = vec![0.0; w];
    let mut dots = vec![0.0; w];
    let mut lanes = [[0.0f64; 4]; 3];
    for j in 0..rows {
        let y = y0 + j;
        {
            let uy_prev = if y == 0 { None } else if j == 0 { Some(above) } else { Some(&uy[(j - 1) * w..j * w]) };
            let uy_this = (y + 1 < h).then(|| &uy[j * w..(j + 1) * w]);
            primal_row(&v[y * w..(y + 1) * w], &ux[j * w..(j + 1) * w], uy_this, uy_prev, nonneg, &mut out[j * w..(j + 1) * w]);
        }
        if j > 0 {
            let (done, this) = out.split_at(j * w);
            ascent_row(&mut ux[(j - 1) * w..j * w], &mut uy[(j - 1) * w..j * w], &done[(j - 1) * w..], &this[..w], gamma, &mut mags, &mut dots, &mut lanes);
        }
    }
    let j = rows - 1;
    let row = &out[j * w..(j + 1) * w];
    if y1 < h {
        // The first row of the next band, from the old dual rows there.
        let (bx, by) = below.split_at(w);
        let mut halo = vec![0.0; w];
        primal_row(&v[y1 * w..(y1 + 1) * w], bx, (y1 + 1 < h).then_some(by), Some(&uy[j * w..(j + 1) * w]), nonneg, &mut halo);
        ascent_row(&mut ux[j * w..(j + 1) * w], &mut uy[j * w..(j + 1) * w], row, &halo, gamma, &mut mags, &mut dots, &mut lanes);
    } else {
        ascent_row(&mut ux[j * w..(j + 1) * w], &mut uy[j * w..(j + 1) * w], row, row, gamma, &mut mags, &mut dots, &mut lanes);
    }
    let sum = |l: &[f64; 4]| (l[0] + l[1]) + (l[2] + l[3]);
    [sum(&lanes[0]), sum(&lanes[1]), sum(&lanes[2])]
}
}

/// One dual ascent step of the TV prox, fused with the gradient of the primal point `t` and
/// the duality-gap sums: with `s = D t` (forward differences, Neumann), returns
/// `(sum_i |s_i|, <u, s>, sum_i |u_i . s_i|)` at the current `u`, then sets
/// `u <- proj_{|u_i| <= gamma}(u + s / 8)`. Bands of rows run in parallel.
#[cfg(test)]
pub(super) fn tv_dual_ascent(u: &mut [f64], t: &[f64], grid: Grid, gamma: f64) -> (f64, f64, f64) {
    let w = grid.width;
    let band = band_rows(grid) * w;
    let (ux, uy) = u.split_at_mut(grid.pixels());
    let sums: Vec<[f64; 3]> = ux
        .par_chunks_mut(band)
        .zip(uy.par_chunks_mut(band))
        .enumerate()
        .map(|(i, (ux, uy))| tv_dual_ascent_band(ux, uy, t, grid, i * band / w, gamma))
        .collect();
    sums.iter().fold((0.0, 0.0, 0.0), |acc, s| {
        (acc.0 + s[0], acc.1 + s[1], acc.2 + s[2])
    })
}

avx2_dispatch! {
#[cfg(test)]
/// [`tv_dual_ascent`] on the rows `y0..` of one band (`ux`, `uy`: the band's dual values).
fn tv_dual_ascent_band(ux: &mut [f64], uy: &mut [f64], t: &[f64], grid: Grid, y0: usize, gamma: f64) -> [f64; 3] {
    let (w, h) = (grid.width, grid.height);
    // Per row, one pass without reductions (so LLVM vectorises the square roots and the
    // division) writes |s_i| and u_i . s_i; a second pass sums them on four partial sums
    // (pixel x on sum x & 3), which also breaks the floating-point dependency chains.
    let mut mags = vec![0.0; w];
    let mut dots = vec![0.0; w];
    let mut lanes = [[0.0f64; 4]; 3];
    #[inline(always)]
    fn step(a: f64, b: f64, ux: &mut f64, uy: &mut f64, gamma: f64, mag: &mut f64, dot: &mut f64) {
        *dot = *ux * a + *uy * b;
        *mag = (a * a + b * b).sqrt();
        let (nx, ny) = (*ux + 0.125 * a, *uy + 0.125 * b);
        // Branch-free (the disc test is data-dependent and mispredicts): gamma / 0 = inf -> 1.
        let f = (gamma / (nx * nx + ny * ny).sqrt()).min(1.0);
        *ux = nx * f;
        *uy = ny * f;
    }
    for (j, (uxr, uyr)) in ux.chunks_exact_mut(w).zip(uy.chunks_exact_mut(w)).enumerate() {
        let y = y0 + j;
        let r = y * w;
        let row = &t[r..r + w];
        let last = y + 1 == h;
        let next = if last { row } else { &t[r + w..r + 2 * w] };
        // b = next - row is 0 on the last row (next = row there); a = 0 on the last column.
        let n = w - 1;
        let (right, left) = (&row[1..], &row[..n]);
        for x in 0..n {
            step(right[x] - left[x], next[x] - left[x], &mut uxr[x], &mut uyr[x], gamma, &mut mags[x], &mut dots[x]);
        }
        step(0.0, next[n] - row[n], &mut uxr[n], &mut uyr[n], gamma, &mut mags[n], &mut dots[n]);
        for (m, d) in mags.chunks_exact(4).zip(dots.chunks_exact(4)) {
            for l in 0..4 {
                lanes[0][l] += m[l];
                lanes[1][l] += d[l];
                lanes[2][l] += d[l].abs();
            }
        }
        for x in 4 * (w / 4)..w {
            lanes[0][x & 3] += mags[x];
            lanes[1][x & 3] += dots[x];
            lanes[2][x & 3] += dots[x].abs();
        }
    }
    let sum = |l: &[f64; 4]| (l[0] + l[1]) + (l[2] + l[3]);
    [sum(&lanes[0]), sum(&lanes[1]), sum(&lanes[2])]
}
}

/// `out = v - D^T u`, clipped at 0 if `nonneg` (`D^T` as in `gradient_adjoint`); bands of rows
/// run in parallel.
#[cfg(test)]
pub(super) fn primal_from_dual(u: &[f64], v: &[f64], grid: Grid, nonneg: bool, out: &mut [f64]) {
    let w = grid.width;
    let band = band_rows(grid) * w;
    out.par_chunks_mut(band)
        .enumerate()
        .for_each(|(i, o)| primal_from_dual_band(u, v, grid, nonneg, i * band / w, o));
}

/// [`primal_from_dual`] in one serial pass (no parallel section: a held total's threshold
/// needs it on every inner iteration, where another section's synchronisation cost more than
/// the pass, measured on 128x128).
pub(super) fn primal_from_dual_serial(u: &[f64], v: &[f64], grid: Grid, out: &mut [f64]) {
    primal_from_dual_band(u, v, grid, false, 0, out);
}

avx2_dispatch! {
/// [`primal_from_dual`] on the rows `y0..` of one band (`out`: the band's pixels), in
/// branch-free passes.
fn primal_from_dual_band(u: &[f64], v: &[f64], grid: Grid, nonneg: bool, y0: usize, out: &mut [f64]) {
    let (w, h) = (grid.width, grid.height);
    let k = w * h;
    let (ux, uy) = u.split_at(k);
    for (j, o) in out.chunks_exact_mut(w).enumerate() {
        let y = y0 + j;
        let r = y * w;
        let vr = &v[r..r + w];
        let uxr = &ux[r..r + w];
        // D^T u = -div u, so v - D^T u = v + div u; div: +ux[x] (x < w-1), -ux[x-1] (x > 0),
        // +uy[y] (y < h-1), -uy[y-1] (y > 0).
        o[..w - 1].iter_mut().zip(&vr[..w - 1]).zip(&uxr[..w - 1]).for_each(|((o, &v), &u)| *o = v + u);
        o[w - 1] = vr[w - 1];
        o[1..].iter_mut().zip(&uxr[..w - 1]).for_each(|(o, &u)| *o -= u);
        if y + 1 < h {
            o.iter_mut().zip(&uy[r..r + w]).for_each(|(o, &u)| *o += u);
        }
        if y > 0 {
            o.iter_mut().zip(&uy[r - w..r]).for_each(|(o, &u)| *o -= u);
        }
        if nonneg {
            o.iter_mut().for_each(|o| *o = o.max(0.0));
        }
    }
}
}
