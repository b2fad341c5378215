//! What one 0/1 frame per coefficient would give adaptive acquisition (issue 24), against split
//! pairs (two frames per coefficient, today's `adaptive_haar` / `adaptive_hadamard`) and the
//! fixed families, at the same frame count, noise-free.
//!
//! `cargo run --release -p helmholtz-bench --example single_frame -- SIZE SCENE[,SCENE..] [RATIO,..]`
//!
//! A split pair measures `y+` and `y-`; `y+ + y-` is the light on the function's support. Where
//! that light is already known, one frame (`P+`) measures the coefficient: `y- = S - y+`.
//! - Walsh-Hadamard: every support is the whole grid, whose light (and the dark level) index 0's
//!   pair (all on, all off) measures; so `F` frames measure `F - 1` coefficients
//!   (`2 y+ - y_on - y_off = <w, t>`, the dark level cancelling as in a pair). Noise-free, such a
//!   session has exactly the values of a split-pair session of `F - 1` pairs, so the planner's
//!   single-frame session is run as that one (`planner 1f`, its zero-filled image `direct` and
//!   `auto` on it).
//! - Haar: a detail's support is a block, whose light is known once every coarser block
//!   containing it has its three details measured, so the unit of choice is a block split (three
//!   frames, three coefficients; [`haar_block_greedy`]). The planner has no such rule today: its
//!   session of `F - 1` pairs (`planner 1f`) takes details whose block light is not known, so for
//!   Haar that column is optimistic; the oracle columns say what the block rule costs (`tree` is
//!   the planner's rule fed the truth, `block` the block-split rule fed the truth).
//!
//! Columns (PSNR in dB against the scene, raw): `best` = the `k'` largest true coefficients,
//! zero-filled (`k' = F / 2` for pairs, `F - 1` for single frames); `tree` / `block` as above;
//! `best auto 1f` = `auto` on the single-frame best `k'`; `planner` = the planner's session,
//! `direct` and `auto`; `block planner` = [`block_planner`], a prototype of a single-frame Haar
//! planner (Haar only), at the pairs' and at the single frames' budget; `fixed` = `auto` on
//! Bernoulli 1/2 and on Russian-doll Hadamard split pairs at the same `F` frames (the better of
//! the two); the last two columns `auto` of `planner 1f` and of `block planner 1f` less `fixed`.
//! Figures and what they say: `docs/benchmark-notes.md`, "One frame per coefficient".
//!
//! Switches: `ONLY_BLOCK=1` runs the block planner alone (the other columns print NaN);
//! `BLOCK_RULE=sq|parent|fit` ranks its blocks by their details' squared scores, by the larger
//! of their predicted energy and `BLOCK_BETA^2` times the measured parent block's, or by a
//! per-scale non-negative least-squares fit of the measured blocks' energies on their features
//! ([`fit_scales`]: the predicted energy `o`, the parent block's measured energy `p`, the mean
//! energy of the measured neighbours at the same scale `n`, and a constant; `FIT_FEATURES`
//! chooses among `opn`, default all) (default: the summed scores); `BLOCK_BETA=b` its persistence (0.5); `FILL_PROBE=1` prints, for the block
//! planner's sessions, `auto`'s fill-in energy `||auto - direct||^2` and `auto`'s squared error,
//! both over the zero-filled image's `E_U`, and the report's `fill_in`.

use std::sync::Arc;

use helmholtz_bench::adaptive::{
    Exact, best_k, haar_block_greedy, probe_session, reconstruct, scene, tree_greedy, zero_filled,
};
use helmholtz_proto::{Family, HadamardOrdering, PatternSpec};
use helmholtz_recon::adaptive::{Basis, Predictor, auto_batch_pairs};
use helmholtz_recon::metrics;
use helmholtz_sim::simulate::{NoiseModel, simulate};

/// A prototype single-frame Haar planner (not the service's): the service's loop (batches of
/// `batch` coefficients, two outstanding), its prediction ([`Predictor`], bicubic from the block
/// averages) and persistence (`beta`), but choosing **block splits**: a block is open once its
/// parent block's three details are all issued (its light is then known when its frames are
/// decoded), scored by the sum of its three details' scores, and split whole (three frames).
/// Noise-free values (the truth's coefficients). Returns the indices in order.
fn block_planner(c: &[f64], width: u32, kp: usize, batch: usize, beta: f64) -> Vec<u32> {
    let k = c.len();
    let w = width;
    let m = w.trailing_zeros();
    let details = |sc: u32, pr: u32, pc: u32| {
        let h = w >> sc;
        [pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc]
    };
    let parent = |n: u32| Basis::Haar.parent(w, n);
    let mut predictor = Predictor::new(Basis::Haar, w);
    let mut values = vec![0.0f64; k];
    let mut pred = vec![0.0f64; k];
    let mut score = vec![0.0f64; k];
    let mut order: Vec<u32> = vec![0];
    // Open blocks (sc, pr, pc) not yet split.
    let mut open: Vec<(u32, u32, u32)> = if m >= 1 { vec![(m, 0, 0)] } else { vec![] };
    let mut outstanding: std::collections::VecDeque<(usize, usize)> = Default::default();
    outstanding.push_back((0, 1));
    let mut observed = 0usize;
    // measured[sc][block]: the block of side 2^sc has its details observed.
    let mut measured: Vec<Vec<bool>> = (0..=m)
        .map(|sc| vec![false; ((w >> sc) as usize).pow(2)])
        .collect();
    let mut seen = vec![false; k];
    let mut fits: Vec<[f64; 4]> = vec![[1.0, 0.0, 0.0, 0.0]; m as usize + 1];
    loop {
        while outstanding.len() < 2 && order.len() < kp && !open.is_empty() {
            let start = order.len();
            let size = batch.min(kp - order.len());
            // Rank the open blocks by their details' summed score (ties: coarser, lower index).
            let rule = std::env::var("BLOCK_RULE").unwrap_or_default();
            let block_score = |&(sc, pr, pc): &(u32, u32, u32)| -> f64 {
                let d = details(sc, pr, pc);
                match rule.as_str() {
                    // Predicted energy, or the measured parent block's energy times beta^2.
                    "parent" => {
                        let own: f64 = d.iter().map(|&n| pred[n as usize].powi(2)).sum();
                        let inherited = if sc < m {
                            details(sc + 1, pr / 2, pc / 2)
                                .iter()
                                .map(|&n| values[n as usize].powi(2))
                                .sum::<f64>()
                                * beta
                                * beta
                        } else {
                            0.0
                        };
                        own.max(inherited)
                    }
                    "sq" => d.iter().map(|&n| score[n as usize].powi(2)).sum(),
                    // The per-scale regression of measured block energies on their features.
                    "fit" => {
                        let f = block_features(&values, &pred, &measured, w, sc, pr, pc);
                        let coef = &fits[sc as usize];
                        coef[0] * f[0] + coef[1] * f[1] + coef[2] * f[2] + coef[3]
                    }
                    _ => d.iter().map(|&n| score[n as usize]).sum(),
                }
            };
            while order.len() - start < size && !open.is_empty() {
                let (best, _) = open
                    .iter()
                    .enumerate()
                    .max_by(|(_, a), (_, b)| {
                        block_score(a)
                            .total_cmp(&block_score(b))
                            .then(a.0.cmp(&b.0))
                            .then(details(b.0, b.1, b.2)[0].cmp(&details(a.0, a.1, a.2)[0]))
                    })
                    .unwrap();
                let (sc, pr, pc) = open.swap_remove(best);
                let mut d = details(sc, pr, pc);
                d.sort_by(|&a, &b| {
                    score[b as usize]
                        .total_cmp(&score[a as usize])
                        .then(a.cmp(&b))
                });
                for n in d {
                    if order.len() < kp {
                        order.push(n);
                    }
                }
                if sc >= 2 {
                    for (dr, dc) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                        open.push((sc - 1, 2 * pr + dr, 2 * pc + dc));
                    }
                }
            }
            outstanding.push_back((start, order.len()));
        }
        let Some((a, b)) = outstanding.pop_front() else {
            break;
        };
        for &n in &order[a..b] {
            values[n as usize] = c[n as usize];
            seen[n as usize] = true;
        }
        observed = b;
        predictor.predict(&values, &mut pred);
        for sc in 1..=m {
            let h = w >> sc;
            for pr in 0..h {
                for pc in 0..h {
                    let d = details(sc, pr, pc);
                    measured[sc as usize][(pr * h + pc) as usize] = seen[d[2] as usize];
                }
            }
        }
        fits = fit_scales(&values, &pred, &measured, w);
        for n in 1..k as u32 {
            let mut size = pred[n as usize].abs();
            if let Some(q) = parent(n).filter(|&q| q != 0) {
                size = size.max(beta * values[q as usize].abs());
            }
            score[n as usize] = size;
        }
    }
    order.truncate(observed);
    order
}

/// Features of block `(sc, pr, pc)` (side `2^sc`): its three details' predicted energy, its
/// parent block's measured detail energy, and the mean detail energy of its measured neighbours
/// at the same scale (8-neighbourhood; 0 if none).
fn block_features(
    values: &[f64],
    pred: &[f64],
    measured: &[Vec<bool>],
    w: u32,
    sc: u32,
    pr: u32,
    pc: u32,
) -> [f64; 3] {
    let m = w.trailing_zeros();
    let details = |sc: u32, pr: u32, pc: u32| {
        let h = w >> sc;
        [pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc]
    };
    let energy = |v: &[f64], d: [u32; 3]| d.iter().map(|&n| v[n as usize].powi(2)).sum::<f64>();
    let own = energy(pred, details(sc, pr, pc));
    let parent = if sc < m {
        energy(values, details(sc + 1, pr / 2, pc / 2))
    } else {
        0.0
    };
    let h = (w >> sc) as i64;
    let (mut sum, mut count) = (0.0, 0usize);
    for dr in -1i64..=1 {
        for dc in -1i64..=1 {
            let (r, c) = (pr as i64 + dr, pc as i64 + dc);
            if (dr, dc) == (0, 0) || r < 0 || c < 0 || r >= h || c >= h {
                continue;
            }
            if measured[sc as usize][(r * h + c) as usize] {
                sum += energy(values, details(sc, r as u32, c as u32));
                count += 1;
            }
        }
    }
    let nbr = if count > 0 { sum / count as f64 } else { 0.0 };
    [own, parent, nbr]
}

/// Per scale, the non-negative least-squares fit `E ~ a own + b parent + c nbr + mu` over the
/// measured blocks (at least 8; else the next coarser scale's fit with `mu / 4`).
#[allow(clippy::needless_range_loop)] // a 4x4 normal-equation solve reads best by index
fn fit_scales(values: &[f64], pred: &[f64], measured: &[Vec<bool>], w: u32) -> Vec<[f64; 4]> {
    let m = w.trailing_zeros();
    let mode = std::env::var("FIT_FEATURES").unwrap_or_else(|_| "opn".into());
    let mut fits = vec![[1.0, 0.0, 0.0, 0.0]; m as usize + 1];
    for sc in (1..=m).rev() {
        let h = w >> sc;
        let mut rows: Vec<([f64; 3], f64)> = Vec::new();
        for pr in 0..h {
            for pc in 0..h {
                if !measured[sc as usize][(pr * h + pc) as usize] {
                    continue;
                }
                let f = block_features(values, pred, measured, w, sc, pr, pc);
                let d = [pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc];
                let e: f64 = d.iter().map(|&n| values[n as usize].powi(2)).sum();
                rows.push((f, e));
            }
        }
        if rows.len() < 8 {
            if (sc as usize) < m as usize {
                let mut f = fits[sc as usize + 1];
                f[3] /= 4.0;
                fits[sc as usize] = f;
            }
            continue;
        }
        // Enumerate the feature subsets (intercept always), keep the best non-negative one.
        let allowed = [mode.contains('o'), mode.contains('p'), mode.contains('n')];
        let mut best = (f64::INFINITY, [0.0; 4]);
        for mask in 0u32..8 {
            if (0..3).any(|j| mask & (1 << j) != 0 && !allowed[j]) {
                continue;
            }
            let cols: Vec<usize> = (0..3).filter(|j| mask & (1 << j) != 0).collect();
            let q = cols.len() + 1;
            let x = |r: &([f64; 3], f64), i: usize| if i < cols.len() { r.0[cols[i]] } else { 1.0 };
            let mut g = vec![vec![0.0; q + 1]; q];
            for r in &rows {
                for i in 0..q {
                    for j in 0..q {
                        g[i][j] += x(r, i) * x(r, j);
                    }
                    g[i][q] += x(r, i) * r.1;
                }
            }
            // Gaussian elimination with a small ridge.
            for i in 0..q {
                g[i][i] += 1e-12 * (1.0 + g[i][i]);
            }
            let mut ok = true;
            for i in 0..q {
                let piv = g[i][i];
                if piv.abs() < 1e-300 {
                    ok = false;
                    break;
                }
                for j in 0..q {
                    if j != i {
                        let f = g[j][i] / piv;
                        for c in i..=q {
                            g[j][c] -= f * g[i][c];
                        }
                    }
                }
            }
            if !ok {
                continue;
            }
            let beta: Vec<f64> = (0..q).map(|i| g[i][q] / g[i][i]).collect();
            if beta.iter().any(|&b| b < 0.0) {
                continue;
            }
            let res: f64 = rows
                .iter()
                .map(|r| {
                    let p: f64 = (0..q).map(|i| beta[i] * x(r, i)).sum();
                    (r.1 - p).powi(2)
                })
                .sum();
            if res < best.0 {
                let mut c = [0.0; 4];
                for (i, &j) in cols.iter().enumerate() {
                    c[j] = beta[i];
                }
                c[3] = beta[q - 1];
                best = (res, c);
            }
        }
        fits[sc as usize] = best.1;
    }
    fits
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        a.len() >= 3,
        "usage: single_frame SIZE SCENE[,SCENE..] [RATIO,..]"
    );
    let size: u32 = a[1].parse()?;
    let scenes: Vec<&str> = a[2].split(',').collect();
    let ratios: Vec<f64> = a
        .get(3)
        .map(|r| r.split(',').map(|v| v.parse()).collect::<Result<_, _>>())
        .transpose()?
        .unwrap_or_else(|| vec![0.01, 0.02, 0.05, 0.10, 0.25]);
    let k = (size * size) as u64;
    // Probe of the block planner's rule alone (BLOCK_RULE, BLOCK_BETA): skip the other sessions.
    let only_block = helmholtz_bench::env_flag("ONLY_BLOCK");
    println!(
        "| scene | basis | frames | % of k | best 2f | best 1f | tree 2f | tree 1f | block 1f | best auto 1f | planner 2f direct | auto | planner 1f direct | auto | block planner 2f direct | auto | block planner 1f direct | auto | fixed auto | 1f auto - fixed | block 1f auto - fixed |"
    );
    println!(
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for name in &scenes {
        let truth32 = scene(name, size)?;
        let truth: Vec<f64> = truth32.iter().map(|&v| v as f64).collect();
        for &ratio in &ratios {
            let frames = ((ratio * k as f64).round() as u64).max(4) & !1;
            let mut fixed = f64::NEG_INFINITY;
            for family in [
                Family::Bernoulli { fill: 0.5 },
                Family::Hadamard {
                    ordering: HadamardOrdering::RussianDoll,
                },
            ] {
                let spec = PatternSpec::new(family, size, size, frames, 1)?;
                let values = simulate(&spec, &[&truth32], &NoiseModel::default(), None).values;
                if !only_block {
                    fixed = fixed.max(reconstruct(&spec, &values, "auto", &truth32).0);
                }
            }
            for haar in [true, false] {
                let exact = Exact::new(&truth, size as usize, haar);
                let c = &exact.coefficients;
                let basis = if haar { Basis::Haar } else { Basis::Hadamard };
                let (k2, k1) = ((frames / 2) as usize, (frames - 1).min(k) as usize);
                let psnr = |sel: &[u32]| {
                    metrics::psnr(&zero_filled(c, sel, size as usize, haar), &truth32)
                };
                let best1 = best_k(c, k1);
                let block = if haar {
                    format!("{:.2}", psnr(&haar_block_greedy(c, size, k1)))
                } else {
                    "-".into()
                };
                // `auto` on the single-frame oracle's coefficients (as the pairs they equal).
                let spec = PatternSpec::new(
                    Family::adaptive(haar, 0, 0.0, None),
                    size,
                    size,
                    2 * k1 as u64,
                    0,
                )?
                .with_indices(Arc::from(best1.clone()))?;
                let values: Vec<f64> = best1
                    .iter()
                    .flat_map(|&n| {
                        let (p, m) = exact.pair(n);
                        [p, m]
                    })
                    .collect();
                let best_auto1 = if only_block {
                    f64::NAN
                } else {
                    reconstruct(&spec, &values, "auto", &truth32).0
                };
                let session = |pairs: u64| -> anyhow::Result<(f64, f64)> {
                    let r = (2 * pairs) as f64 / k as f64;
                    let (spec, values, truth) =
                        probe_session(name, size, r, false, Family::adaptive(haar, 0, 0.0, None))?;
                    Ok((
                        reconstruct(&spec, &values, "direct", &truth).0,
                        reconstruct(&spec, &values, "auto", &truth).0,
                    ))
                };
                let (d2, a2) = if only_block {
                    (f64::NAN, f64::NAN)
                } else {
                    session(k2 as u64)?
                };
                let (d1, a1) = if only_block {
                    (f64::NAN, f64::NAN)
                } else {
                    session(k1 as u64)?
                };
                let block_session = |kp: usize| -> anyhow::Result<(String, f64)> {
                    if !haar {
                        return Ok(("-".into(), f64::NAN));
                    }
                    let batch = auto_batch_pairs(k, 1, kp as u64) as usize;
                    let beta = std::env::var("BLOCK_BETA")
                        .ok()
                        .map(|b| b.parse().expect("BLOCK_BETA"))
                        .unwrap_or(0.5);
                    let sel = block_planner(c, size, kp, batch, beta);
                    let spec = PatternSpec::new(
                        Family::adaptive(true, 0, 0.0, None),
                        size,
                        size,
                        2 * sel.len() as u64,
                        0,
                    )?
                    .with_indices(Arc::from(sel.clone()))?;
                    let values: Vec<f64> = sel
                        .iter()
                        .flat_map(|&n| {
                            let (p, m) = exact.pair(n);
                            [p, m]
                        })
                        .collect();
                    if helmholtz_bench::env_flag("FILL_PROBE") {
                        // auto's fill-in `u = auto - direct` against the energy the zero-filled
                        // image misses, `E_U = ||direct - truth||^2`.
                        let problem = helmholtz_recon::Problem {
                            spec: &spec,
                            channels: 1,
                            rows: values.len() as u64,
                        };
                        let config =
                            helmholtz_recon::MethodConfig::parse("auto", &serde_json::Value::Null)?;
                        let r = helmholtz_recon::reconstruct(
                            &problem,
                            &config,
                            &mut helmholtz_recon::SliceSource::new(&values, 1, 4096),
                            &helmholtz_recon::Control::new(),
                        )?;
                        let auto_img = &r.images[0].data;
                        let direct = zero_filled(c, &sel, size as usize, true);
                        let sq = |a: &[f32], b: &[f32]| -> f64 {
                            a.iter()
                                .zip(b)
                                .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
                                .sum()
                        };
                        let (u2, eu, ea) = (
                            sq(auto_img, &direct),
                            sq(&direct, &truth32),
                            sq(auto_img, &truth32),
                        );
                        eprintln!(
                            "FILL {name} {:.0}% kp {kp}: ||u||^2/E_U {:.3}  auto err/E_U {:.3}  fill_in {}",
                            100.0 * ratio,
                            u2 / eu,
                            ea / eu,
                            r.report
                                .details
                                .get("auto")
                                .and_then(|a| a.as_array())
                                .and_then(|a| a.last())
                                .and_then(|a| a.get("fill_in"))
                                .map(|f| f.to_string())
                                .unwrap_or_default()
                        );
                    }
                    Ok((
                        format!("{:.2}", psnr(&sel)),
                        reconstruct(&spec, &values, "auto", &truth32).0,
                    ))
                };
                let (bd, ba) = block_session(k1)?;
                let (bd2, ba2) = if only_block {
                    ("-".into(), f64::NAN)
                } else {
                    block_session(k2)?
                };
                println!(
                    "| {name} | {} | {frames} | {:.0} % | {:.2} | {:.2} | {:.2} | {:.2} | {block} | {best_auto1:.2} | {d2:.2} | {a2:.2} | {d1:.2} | {a1:.2} | {bd2} | {ba2:.2} | {bd} | {ba:.2} | {fixed:.2} | {:+.2} | {:+.2} |",
                    if haar { "haar" } else { "wh" },
                    100.0 * ratio,
                    psnr(&best_k(c, k2)),
                    psnr(&best1),
                    psnr(&tree_greedy(c, size, basis, k2)),
                    psnr(&tree_greedy(c, size, basis, k1)),
                    a1 - fixed,
                    ba - fixed,
                );
            }
        }
    }
    Ok(())
}
