//! One camera session reconstructed into `T`, for probing: time, T error, relit-image errors
//! (full, left-half and checkerboard lights), total light, against the scene's exact `T`.
//!
//! `transport_one FAMILY PROJ CAM RATIO NOISE [PARAMS_JSON]`: FAMILY `hadamard` (Russian doll)
//! or `bernoulli`; PROJ and CAM square sizes (`32`, `64`); RATIO frames over projector pixels
//! (Hadamard: pairs, so 1 is the complete set); NOISE Gaussian frame noise relative to the frames'
//! RMS (`0.01`). `TRANSPORT_REPORT=1` prints the report's details. A Hadamard subset also
//! prints where the full-light relit image's error lies (measured or unmeasured coefficients)
//! and `q`, the share of the truth's energy the fit misses in the pairs a set twice as large
//! would add (`BAND_TO=r`: as large as `r` pairs per projector pixel), and in all unmeasured
//! ones (what an error estimate must predict). `EXTRA=1` counts the stored coefficients where
//! the exact `T` is zero (with their light and their size against their row's largest, by
//! decade) and the exact `T`'s nonzeros not stored (identity transform: pixels of `T`).
//! Where the error lies and what could estimate it: `ORDERS=1` (Hadamard) splits the full relit
//! image's error and the truth's energy by scale order, measured and unmeasured coefficients;
//! `ROWERR=1` lists the rows carrying most of T's error; `POLYTOPE=n` measures every row's
//! distance to the nearest nonnegative row the measured pairs cannot tell from it (n Dykstra
//! iterations) and the full relight of those distances; `SECOND=params` reconstructs the session
//! again with other params and compares the two T (both without `projector_binning`; POLYTOPE on
//! Hadamard sessions).

use std::time::Instant;

use helmholtz_proto::{Family, HadamardOrdering, PatternGenerator, PatternSpec};
use helmholtz_recon::Control;
use helmholtz_recon::metrics::relative_error;
use helmholtz_recon::transport::{
    CameraGrid, SliceFrames, TransportConfig, assemble_transport, plan_transport,
    solve_transport_blocks,
};
use helmholtz_sim::{Camera, CameraView, Relief, RenderedTransport};

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        a.len() >= 6,
        "usage: transport_one FAMILY PROJ CAM RATIO NOISE [PARAMS_JSON]"
    );
    let (p, c): (u32, u32) = (a[2].parse()?, a[3].parse()?);
    let ratio: f64 = a[4].parse()?;
    let noise: f64 = a[5].parse()?;
    let params: serde_json::Value = a
        .get(6)
        .map(|s| serde_json::from_str(s))
        .transpose()?
        .unwrap_or(serde_json::json!({}));
    let k = (p * p) as u64;
    let (family, count) = match a[1].as_str() {
        "hadamard" => (
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            2 * ((k as f64 * ratio).round() as u64),
        ),
        "bernoulli" => (
            Family::Bernoulli { fill: 0.5 },
            (k as f64 * ratio).round() as u64,
        ),
        f => anyhow::bail!("family {f}"),
    };
    let hadamard = matches!(family, Family::Hadamard { .. });
    let spec = PatternSpec::new(family, p, p, count, 3)?;
    // SCENE=cornell|glossy|slide: a rendered scene; else the demo relief.
    let scene = Relief::demo(p, p, 7);
    let relief = scene.view(&Camera::tilted(c, c, 25.0));
    let rendered = match std::env::var("SCENE").as_deref() {
        Ok("cornell") => Some(RenderedTransport::cornell(
            (p as usize, p as usize),
            (c as usize, c as usize),
            1,
        )),
        Ok("glossy") => Some(RenderedTransport::glossy(
            (p as usize, p as usize),
            (c as usize, c as usize),
            1,
        )),
        Ok("slide") => Some(RenderedTransport::slide(
            (p as usize, p as usize),
            (c as usize, c as usize),
            1,
        )),
        _ => None,
    };
    let view = View {
        relief: &relief,
        rendered: rendered.as_ref(),
    };
    let config = TransportConfig::parse(&params)?;
    // `projector_binning` b: the truth is the b x b blocks' summed light.
    let b = config.projector_binning as usize;
    let bin = |v: &[f64]| -> Vec<f64> {
        let (pu, cw) = (p as usize, p as usize / b);
        let mut out = vec![0.0; cw * cw];
        for (i, x) in v.iter().enumerate() {
            out[(i / pu / b) * cw + (i % pu) / b] += x;
        }
        out
    };
    let fine_truth = view.dense();
    let m = view.pixels();
    let truth: Vec<f32> = if b > 1 {
        fine_truth
            .chunks_exact(k as usize)
            .flat_map(|row| bin(&row.iter().map(|&v| v as f64).collect::<Vec<_>>()))
            .map(|v| v as f32)
            .collect()
    } else {
        fine_truth
    };
    let g = PatternGenerator::new(&spec);
    let mut pat = vec![0f32; k as usize];
    let mut frames = Vec::with_capacity(count as usize * m);
    for i in 0..count {
        g.fill_values(i, &mut pat);
        let p64: Vec<f64> = pat.iter().map(|&v| v as f64).collect();
        frames.extend(view.render(&p64));
    }
    let rms = (frames.iter().map(|v| v * v).sum::<f64>() / frames.len() as f64).sqrt();
    let mut rng = 0x9E3779B97F4A7C15u64;
    let mut normal = || {
        let mut u = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            ((rng >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let (u1, u2) = (u(), u());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    };
    let frames: Vec<f32> = frames
        .iter()
        .map(|v| (v + noise * rms * normal()) as f32)
        .collect();
    let mut source = SliceFrames::new(&frames, m);
    let start = Instant::now();
    let grid = CameraGrid {
        width: c,
        height: c,
    };
    let control = Control::new();
    let model = plan_transport(&spec, grid, count, &config, &mut source, &control)?;
    let planned = start.elapsed().as_secs_f64();
    let part = solve_transport_blocks(&spec, &model, 0..model.blocks.len(), &mut source, &control)?;
    let (t, report) = assemble_transport(&model, std::slice::from_ref(&part))?;
    println!(
        "plan {planned:.2} s, solve {:.2} s",
        start.elapsed().as_secs_f64() - planned
    );
    let seconds = start.elapsed().as_secs_f64();
    let est: Vec<f32> = (0..m).flat_map(|j| t.row(j)).collect();
    // SECOND=params: the session reconstructed again with other params; the full relight of
    // the difference between the two T, against the first's true relight error.
    // (Both compare against the scene's own relight: the session's grid, not a binned one.)
    if let Ok(second) = std::env::var("SECOND")
        && b == 1
    {
        let config2 = TransportConfig::parse(&serde_json::from_str(&second)?)?;
        let model2 = plan_transport(&spec, grid, count, &config2, &mut source, &control)?;
        let part2 = solve_transport_blocks(
            &spec,
            &model2,
            0..model2.blocks.len(),
            &mut source,
            &control,
        )?;
        let (t2, _) = assemble_transport(&model2, std::slice::from_ref(&part2))?;
        let est2: Vec<f32> = (0..m).flat_map(|j| t2.row(j)).collect();
        let ones = vec![1.0f32; m];
        let (r1, r2) = (t.relight(&ones), t2.relight(&ones));
        let want: Vec<f32> = view
            .relight(&vec![1.0; m])
            .into_iter()
            .map(|v| v as f32)
            .collect();
        println!(
            "second {second}: relight difference {:.4} (first's error {:.4}, second's {:.4}); rows difference {:.4}",
            relative_error(&r2, &r1),
            relative_error(&r1, &want),
            relative_error(&r2, &want),
            relative_error(&est2, &est),
        );
    }
    let identity = t.transform() == helmholtz_recon::transforms::TransformKind::Identity;
    if helmholtz_bench::env_flag("EXTRA") && !identity {
        println!(
            "EXTRA: T is stored in {:?}; the counts need the identity transform",
            t.transform()
        );
    }
    if helmholtz_bench::env_flag("EXTRA") && identity {
        let kk = k as usize;
        let mut hist = [0usize; 8];
        let (mut extra, mut missing, mut extra_light, mut total_light) =
            (0usize, 0usize, 0f64, 0f64);
        for j in 0..m {
            let (idx, val) = t.row_coefficients(j);
            let tr = &truth[j * kk..(j + 1) * kk];
            let mx = tr.iter().fold(0f32, |a, b| a.max(b.abs())).max(1e-30);
            total_light += tr.iter().map(|v| *v as f64).sum::<f64>();
            for (&i, &v) in idx.iter().zip(val) {
                if tr[i as usize] == 0.0 {
                    extra += 1;
                    extra_light += v as f64;
                    let r = (v.abs() / mx).log10().floor() as i32;
                    hist[(-r).clamp(0, 7) as usize] += 1;
                }
            }
            missing += tr
                .iter()
                .enumerate()
                .filter(|(i, v)| **v != 0.0 && !idx.contains(&(*i as u32)))
                .count();
        }
        println!(
            "stored: extra {extra} (light {extra_light:.2e} of {total_light:.3e}), missing {missing}, extra by -log10(|v|/rowmax) {hist:?}"
        );
    }
    let total = |v: &[f32]| v.iter().map(|x| *x as f64).sum::<f64>();
    let lights: [(&str, Vec<f64>); 3] = [
        ("full", vec![1.0; m]),
        (
            "half",
            (0..m)
                .map(|j| f64::from(2 * (j % c as usize) < c as usize))
                .collect(),
        ),
        (
            "checker",
            (0..m)
                .map(|j| f64::from(((j % c as usize) / 4 + (j / c as usize) / 4).is_multiple_of(2)))
                .collect(),
        ),
    ];
    // The plain least-squares baseline of Hadamard sets: the adjoint of the split pairs (the
    // exact inverse of a complete set, the zero-filled one of a subset).
    let plain: Option<Vec<f32>> = (hadamard && b == 1).then(|| {
        use helmholtz_recon::linop::LinearOperator;
        let op = helmholtz_recon::ops::HadamardOperator::from_spec(&spec, count).unwrap();
        let scale = 1.0 / (k as f64).sqrt();
        let mut out = Vec::with_capacity(m * k as usize);
        let mut row = vec![0.0; k as usize];
        for j in 0..m {
            let d: Vec<f64> = (0..op.rows())
                .map(|r| {
                    (frames[2 * r * m + j] as f64 - frames[(2 * r + 1) * m + j] as f64) * scale
                })
                .collect();
            op.adjoint(&d, &mut row);
            out.extend(row.iter().map(|&v| v as f32));
        }
        out
    });
    let relit_of = |t: &[f32], l: &[f64]| -> Vec<f32> {
        let mut out = vec![0.0f64; k as usize];
        for (row, &c) in t.chunks_exact(k as usize).zip(l) {
            out.iter_mut()
                .zip(row)
                .for_each(|(o, v)| *o += *v as f64 * c);
        }
        out.into_iter().map(|v| v as f32).collect()
    };
    let mut relit = String::new();
    for (name, l) in &lights {
        let l32: Vec<f32> = l.iter().map(|&v| v as f32).collect();
        let fine = view.relight(l);
        let want: Vec<f32> = if b > 1 { bin(&fine) } else { fine }
            .into_iter()
            .map(|v| v as f32)
            .collect();
        relit += &format!(" {name} {:.4}", relative_error(&t.relight(&l32), &want));
        if let Some(p) = &plain {
            relit += &format!(" (plain {:.4})", relative_error(&relit_of(p, l), &want));
        }
    }
    if let Some(p) = &plain {
        println!(
            "plain adjoint: T err {:.4}, total light {:.4}",
            relative_error(p, &truth),
            total(p) / total(&truth)
        );
    }
    println!(
        "{} {p}->{c} ratio {ratio} noise {noise}: {seconds:.2} s, transform {} lambda {} refit {}, nnz/row {:.1}, T err {:.4}, relit{relit}, total light {:.4}, held-out {:?}",
        a[1],
        report.details["transform"],
        report.details["lambda"],
        report.details["refit"],
        t.nonzeros() as f64 / m as f64,
        relative_error(&est, &truth),
        total(&est) / total(&truth),
        report.held_out.as_ref().and_then(|h| h.relative_residual),
    );
    for key in ["relight_error_estimate", "error_estimate"] {
        if let Some(e) = report.details.get(key) {
            let mut e = e.clone();
            if let Some(o) = e.as_object_mut() {
                o.remove("basis");
            }
            println!("{key}: {e}");
        }
    }
    // A Hadamard subset: the share of the full-light relit image's energy in the coefficients
    // no pair measured, of the truth and of the estimate (what a relight error estimate must
    // extrapolate).
    if hadamard && b == 1 {
        use helmholtz_recon::linop::LinearOperator;
        let op = helmholtz_recon::ops::HadamardOperator::from_spec(&spec, count)?;
        let full =
            helmholtz_recon::ops::HadamardOperator::with_natural(p, p, (0..k as usize).collect());
        let mut measured = vec![false; k as usize];
        op.natural_indices()
            .iter()
            .for_each(|&n| measured[n] = true);
        let unmeasured_share = |r: &[f64]| {
            let mut co = vec![0.0; k as usize];
            full.apply(r, &mut co);
            let all: f64 = co.iter().map(|v| v * v).sum();
            let un: f64 = co
                .iter()
                .zip(&measured)
                .filter(|(_, m)| !**m)
                .map(|(v, _)| v * v)
                .sum();
            un / all
        };
        let truth_relit = view.relight(&vec![1.0; m]);
        let est_relit: Vec<f64> = t
            .relight(&vec![1.0f32; m])
            .into_iter()
            .map(f64::from)
            .collect();
        let diff: Vec<f64> = truth_relit
            .iter()
            .zip(&est_relit)
            .map(|(a, b)| a - b)
            .collect();
        let n2: f64 = truth_relit.iter().map(|v| v * v).sum();
        let mut co = vec![0.0; k as usize];
        full.apply(&diff, &mut co);
        // ORDERS=1: per scale order, the full relit image's error and the truth's energy in
        // its unmeasured and measured coefficients, relative to the truth's squared norm.
        if helmholtz_bench::env_flag("ORDERS") {
            let mut tco = vec![0.0; k as usize];
            full.apply(&truth_relit, &mut tco);
            let pp = p as usize;
            let top = helmholtz_recon::auto::hadamard_level(k as usize - 1, (pp, pp)) as usize;
            for o in 0..=top {
                let (mut eu, mut tu, mut em, mut tm, mut nu, mut nm) = (0.0, 0.0, 0.0, 0.0, 0, 0);
                for n in 0..k as usize {
                    if helmholtz_recon::auto::hadamard_level(n, (pp, pp)) as usize != o {
                        continue;
                    }
                    if measured[n] {
                        em += co[n] * co[n];
                        tm += tco[n] * tco[n];
                        nm += 1;
                    } else {
                        eu += co[n] * co[n];
                        tu += tco[n] * tco[n];
                        nu += 1;
                    }
                }
                println!(
                    "order {o}: measured {nm} (error {:.2e}, truth {:.2e}), unmeasured {nu} (error {:.2e}, truth {:.2e})",
                    em / n2,
                    tm / n2,
                    eu / n2,
                    tu / n2
                );
            }
        }
        let err_un: f64 = co
            .iter()
            .zip(&measured)
            .filter(|(_, m)| !**m)
            .map(|(v, _)| v * v)
            .sum();
        let err_me: f64 = co
            .iter()
            .zip(&measured)
            .filter(|(_, m)| **m)
            .map(|(v, _)| v * v)
            .sum();
        println!(
            "full relit: share of energy in unmeasured coefficients: truth {:.4e}, estimate {:.4e}; error^2 / norm^2 in unmeasured {:.3e}, in measured {:.3e}",
            unmeasured_share(&truth_relit),
            unmeasured_share(&est_relit),
            err_un / n2,
            err_me / n2,
        );
        // The next band: the pairs a set of twice as many would add. The share of the truth's
        // energy there the fit misses (q^2), for the full-light relit image and for the rows
        // pooled, and the same for every unmeasured coefficient.
        // BAND_TO=r: the band ends at r pairs per projector pixel instead.
        let next_count = match std::env::var("BAND_TO") {
            Ok(r) => 2 * ((k as f64 * r.parse::<f64>()?).round() as u64),
            Err(_) => count * 2,
        };
        if next_count <= 2 * k && next_count > count {
            let next = helmholtz_recon::ops::HadamardOperator::from_spec(
                &PatternSpec::new(spec.family().clone(), p, p, next_count, 3)?,
                next_count,
            )?;
            let mut band = vec![false; k as usize];
            next.natural_indices()
                .iter()
                .filter(|&&n| !measured[n])
                .for_each(|&n| band[n] = true);
            let split = |d: &[f64], sel: &[bool]| {
                let mut co = vec![0.0; k as usize];
                full.apply(d, &mut co);
                co.iter()
                    .zip(sel)
                    .filter(|(_, s)| **s)
                    .map(|(v, _)| v * v)
                    .sum::<f64>()
            };
            let unmeasured: Vec<bool> = measured.iter().map(|m| !m).collect();
            let relit_band = split(&diff, &band) / split(&truth_relit, &band);
            let relit_un = split(&diff, &unmeasured) / split(&truth_relit, &unmeasured);
            let (mut rb, mut tb, mut ru, mut tu) = (0.0, 0.0, 0.0, 0.0);
            let kk = k as usize;
            for j in 0..m {
                let tr: Vec<f64> = truth[j * kk..(j + 1) * kk]
                    .iter()
                    .map(|&v| v as f64)
                    .collect();
                let d: Vec<f64> = est[j * kk..(j + 1) * kk]
                    .iter()
                    .zip(&tr)
                    .map(|(&e, t)| e as f64 - t)
                    .collect();
                rb += split(&d, &band);
                tb += split(&tr, &band);
                ru += split(&d, &unmeasured);
                tu += split(&tr, &unmeasured);
            }
            println!(
                "q (missed share of the truth's energy, sqrt): next band relit {:.4} rows {:.4}; all unmeasured relit {:.4} rows {:.4}; truth's band share relit {:.4e} rows {:.4e}",
                relit_band.sqrt(),
                (rb / tb).sqrt(),
                relit_un.sqrt(),
                (ru / tu).sqrt(),
                split(&truth_relit, &band) / n2,
                tb / truth.iter().map(|&v| (v as f64).powi(2)).sum::<f64>(),
            );
        }
    }
    // POLYTOPE=n: every row's nearest nonnegative row that the measured pairs cannot tell from
    // it (Dykstra, n iterations, from the zero-filled part), and the full relight of the
    // difference against the true relight error.
    if let Ok(iters) = std::env::var("POLYTOPE")
        && hadamard
        && b == 1
    {
        use helmholtz_recon::linop::LinearOperator;
        let iters: usize = iters.parse()?;
        let op = helmholtz_recon::ops::HadamardOperator::from_spec(&spec, count)?;
        let kk = k as usize;
        let mr = op.rows();
        let mut diff = vec![0.0f64; kk];
        let mut diff_truth = vec![0.0f64; kk];
        let (mut e2rows, mut t2rows, mut c2rows) = (0.0, 0.0, 0.0);
        let tp = Instant::now();
        let (mut d, mut r, mut back) = (vec![0.0; mr], vec![0.0; mr], vec![0.0; kk]);
        for j in 0..m {
            let row: Vec<f64> = est[j * kk..(j + 1) * kk]
                .iter()
                .map(|&v| v as f64)
                .collect();
            op.apply(&row, &mut d);
            let mut x = vec![0.0; kk];
            op.adjoint(&d, &mut x);
            let (mut pp, mut q, mut y) = (vec![0.0; kk], vec![0.0; kk], vec![0.0; kk]);
            let mut yq = vec![0.0; kk];
            for _ in 0..iters {
                for i in 0..kk {
                    let z = x[i] + pp[i];
                    y[i] = z.max(0.0);
                    pp[i] = z - y[i];
                    yq[i] = y[i] + q[i];
                }
                op.apply(&yq, &mut r);
                r.iter_mut().zip(&d).for_each(|(a, b)| *a = b - *a);
                op.adjoint(&r, &mut back);
                for i in 0..kk {
                    let nx = yq[i] + back[i];
                    q[i] = yq[i] - nx;
                    x[i] = nx;
                }
            }
            for i in 0..kk {
                diff[i] += row[i] - y[i];
                diff_truth[i] += truth[j * kk + i] as f64 - y[i];
                e2rows += (row[i] - y[i]).powi(2);
                c2rows += (truth[j * kk + i] as f64 - y[i]).powi(2);
                t2rows += (truth[j * kk + i] as f64).powi(2);
            }
        }
        let relit_truth = view.relight(&vec![1.0; m]);
        let n2: f64 = relit_truth.iter().map(|v| v * v).sum();
        println!(
            "polytope ({iters} iterations, {:.2} s): relight of fit - nearest nonneg {:.4}, of truth - it {:.4}; rows: fit - it {:.4}, truth - it {:.4}",
            tp.elapsed().as_secs_f64(),
            (diff.iter().map(|v| v * v).sum::<f64>() / n2).sqrt(),
            (diff_truth.iter().map(|v| v * v).sum::<f64>() / n2).sqrt(),
            (e2rows / t2rows).sqrt(),
            (c2rows / t2rows).sqrt(),
        );
    }
    // ROWERR=1: where T's error lies: the rows by their share of the squared error, with the
    // truth's nonzeros and energy in them.
    if helmholtz_bench::env_flag("ROWERR") {
        let kk = k as usize;
        let mut rows: Vec<(f64, f64, usize, usize)> = (0..m)
            .map(|j| {
                let tr = &truth[j * kk..(j + 1) * kk];
                let es = &est[j * kk..(j + 1) * kk];
                let e2: f64 = tr
                    .iter()
                    .zip(es)
                    .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
                    .sum();
                let n2: f64 = tr.iter().map(|a| (*a as f64).powi(2)).sum();
                (e2, n2, tr.iter().filter(|v| **v != 0.0).count(), j)
            })
            .collect();
        let total_e2: f64 = rows.iter().map(|r| r.0).sum();
        let total_n2: f64 = rows.iter().map(|r| r.1).sum();
        rows.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mut acc = 0.0;
        for r in rows.iter().take(12) {
            acc += r.0;
            println!(
                "row {} (x {} y {}): error share {:.3} (cum {:.3}), rel err {:.3}, energy share {:.2e}, truth nnz {}",
                r.3,
                r.3 % c as usize,
                r.3 / c as usize,
                r.0 / total_e2,
                acc / total_e2,
                (r.0 / r.1.max(1e-300)).sqrt(),
                r.1 / total_n2,
                r.2
            );
        }
    }
    // PRUNE=e1,e2,...: each row's smallest stored coefficients dropped while their energy stays
    // within e^2 of the row's (the first coefficient of a wavelet/DCT row kept), and the result
    // judged as above (what a compaction of the stored T would cost).
    if let Ok(list) = std::env::var("PRUNE") {
        let kind = t.transform();
        let free = usize::from(kind.name() != "identity");
        let psi = kind.build(p as usize, p as usize);
        for eps in list.split(',').map(|s| s.parse::<f64>()) {
            let eps = eps?;
            let mut dense = Vec::with_capacity(m * k as usize);
            let mut kept = 0usize;
            let mut s = vec![0.0f64; k as usize];
            let mut row = vec![0.0f64; k as usize];
            for j in 0..m {
                let (idx, val) = t.row_coefficients(j);
                s.iter_mut().for_each(|v| *v = 0.0);
                let energy: f64 = val.iter().map(|v| (*v as f64).powi(2)).sum();
                let mut order: Vec<usize> = (0..idx.len())
                    .filter(|&q| (idx[q] as usize) >= free)
                    .collect();
                order.sort_by(|&a, &b| val[a].abs().total_cmp(&val[b].abs()));
                let mut dropped = 0.0;
                let mut drop = vec![false; idx.len()];
                for q in order {
                    let e = (val[q] as f64).powi(2);
                    if dropped + e > eps * eps * energy {
                        break;
                    }
                    dropped += e;
                    drop[q] = true;
                }
                for (q, (&i, &v)) in idx.iter().zip(val).enumerate() {
                    if !drop[q] {
                        s[i as usize] = v as f64;
                        kept += 1;
                    }
                }
                psi.adjoint(&s, &mut row);
                dense.extend(row.iter().map(|&v| v as f32));
            }
            let mut line = format!(
                "prune {eps:e}: nnz/row {:.1}, T err {:.4}, relit",
                kept as f64 / m as f64,
                relative_error(&dense, &truth)
            );
            for (name, l) in &lights {
                let want: Vec<f32> = view.relight(l).into_iter().map(|v| v as f32).collect();
                line += &format!(" {name} {:.4}", relative_error(&relit_of(&dense, l), &want));
            }
            line += &format!(", total light {:.4}", total(&dense) / total(&truth));
            println!("{line}");
        }
    }
    if helmholtz_bench::env_flag("TRANSPORT_REPORT") {
        println!("{}", serde_json::to_string_pretty(&report.details)?);
    }
    Ok(())
}

/// The scene's exact transport, rendered or the relief's.
struct View<'a> {
    relief: &'a CameraView<'a>,
    rendered: Option<&'a RenderedTransport>,
}

impl View<'_> {
    fn dense(&self) -> Vec<f32> {
        self.rendered
            .map_or_else(|| self.relief.dense(), |r| r.dense())
    }
    fn pixels(&self) -> usize {
        self.rendered
            .map_or_else(|| self.relief.pixels(), |r| r.pixels())
    }
    fn render(&self, p: &[f64]) -> Vec<f64> {
        self.rendered
            .map_or_else(|| self.relief.render(p), |r| r.render(p))
    }
    fn relight(&self, c: &[f64]) -> Vec<f64> {
        self.rendered
            .map_or_else(|| self.relief.relight(c), |r| r.relight(c))
    }
}
