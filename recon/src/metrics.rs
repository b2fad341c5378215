//! Image quality figures: PSNR, SSIM, affine fit, relative error, Pearson correlation.
//!
//! All take row-major images as `f32` slices (the [`super::DualImage`] data) and compute in
//! `f64`. `truth` is the reference; the data range `L` used by PSNR and SSIM is taken from it.
//! Correlation methods (GI, DGI, NGI) estimate `t` only up to a gain and an offset: compare them
//! after [`fit_affine`] (or with [`pearson`]), not raw.
//!
//! [`dual_quality`] and [`transport_quality`] score a finished reconstruction against a simulated
//! session's ground truth: the `quality` of its report.

/// The data range of `truth`: `max - min`, or `max |truth|` when the image is constant, or 1 when
/// it is all zero (so the figures stay finite).
fn data_range(truth: &[f32]) -> f64 {
    let (lo, hi) = truth
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v as f64), hi.max(v as f64))
        });
    let range = hi - lo;
    if range > 0.0 {
        return range;
    }
    let peak = truth.iter().fold(0.0f64, |m, &v| m.max((v as f64).abs()));
    if peak > 0.0 { peak } else { 1.0 }
}

fn check_lengths(estimate: &[f32], truth: &[f32]) {
    assert_eq!(
        estimate.len(),
        truth.len(),
        "estimate and truth differ in length"
    );
    assert!(!truth.is_empty(), "empty image");
}

/// Peak signal-to-noise ratio in dB: `10 log10(L^2 / MSE)`, `L` = max(truth) - min(truth) (or
/// max |truth| for a constant truth, 1 for an all-zero one).
///
/// Identical images (MSE = 0) give `f64::INFINITY`. Panics if the lengths differ or are zero.
pub fn psnr(estimate: &[f32], truth: &[f32]) -> f64 {
    check_lengths(estimate, truth);
    let mse = estimate
        .iter()
        .zip(truth)
        .map(|(&e, &t)| {
            let d = e as f64 - t as f64;
            d * d
        })
        .sum::<f64>()
        / truth.len() as f64;
    if mse == 0.0 {
        return f64::INFINITY;
    }
    let peak = data_range(truth);
    10.0 * (peak * peak / mse).log10()
}

/// Side of the SSIM window (Wang et al. 2004).
const SSIM_WINDOW: usize = 11;
const SSIM_SIGMA: f64 = 1.5;
const SSIM_K1: f64 = 0.01;
const SSIM_K2: f64 = 0.03;

/// Normalised 1D Gaussian of odd length `len`, standard deviation `SSIM_SIGMA`.
fn gaussian(len: usize) -> Vec<f64> {
    let c = (len / 2) as f64;
    let g: Vec<f64> = (0..len)
        .map(|i| (-(i as f64 - c).powi(2) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp())
        .collect();
    let s: f64 = g.iter().sum();
    g.into_iter().map(|v| v / s).collect()
}

/// Window side per axis: 11, or the largest odd length that fits a smaller image.
fn window_side(dim: usize) -> usize {
    let w = dim.min(SSIM_WINDOW);
    if w.is_multiple_of(2) { w - 1 } else { w }
}

/// 'valid' separable filtering: `out[(y, x)] = sum g[i] g[j] img[(y + i, x + j)]` for every
/// window position fully inside the image.
fn filter_valid(img: &[f64], width: usize, height: usize, gx: &[f64], gy: &[f64]) -> Vec<f64> {
    let (ow, oh) = (width + 1 - gx.len(), height + 1 - gy.len());
    let mut rows = vec![0.0; ow * height];
    for y in 0..height {
        let src = &img[y * width..(y + 1) * width];
        for x in 0..ow {
            rows[y * ow + x] = gx.iter().zip(&src[x..]).map(|(g, v)| g * v).sum();
        }
    }
    let mut out = vec![0.0; ow * oh];
    for y in 0..oh {
        for (i, g) in gy.iter().enumerate() {
            let src = &rows[(y + i) * ow..(y + i + 1) * ow];
            for (o, v) in out[y * ow..(y + 1) * ow].iter_mut().zip(src) {
                *o += g * v;
            }
        }
    }
    out
}

/// Mean structural similarity (Wang, Bovik, Sheikh, Simoncelli 2004): 11 x 11 Gaussian window
/// (sigma 1.5, weights normalised), `K1 = 0.01`, `K2 = 0.03`, `L` = data range of `truth` (as for
/// [`psnr`]); the local statistics are Gaussian-weighted (no Bessel correction) and the SSIM map is
/// averaged over every window position that lies wholly inside the image.
///
/// An image narrower or shorter than 11 uses, along that axis, the largest odd window that fits
/// (renormalised Gaussian). Identical images give 1. Panics if the lengths differ from
/// `width * height` or the image is empty.
pub fn ssim(estimate: &[f32], truth: &[f32], width: usize, height: usize) -> f64 {
    check_lengths(estimate, truth);
    let (w, h) = (width, height);
    assert_eq!(truth.len(), w * h, "image is not width x height");
    let gx = gaussian(window_side(w));
    let gy = gaussian(window_side(h));
    let l = data_range(truth);
    let (c1, c2) = ((SSIM_K1 * l).powi(2), (SSIM_K2 * l).powi(2));
    let x: Vec<f64> = estimate.iter().map(|&v| v as f64).collect();
    let y: Vec<f64> = truth.iter().map(|&v| v as f64).collect();
    let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
    let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
    let xy: Vec<f64> = x.iter().zip(&y).map(|(a, b)| a * b).collect();
    let [mx, my, mxx, myy, mxy] =
        [&x, &y, &xx, &yy, &xy].map(|img| filter_valid(img, w, h, &gx, &gy));
    let mut total = 0.0;
    for i in 0..mx.len() {
        let (ux, uy) = (mx[i], my[i]);
        let vx = mxx[i] - ux * ux;
        let vy = myy[i] - uy * uy;
        let cxy = mxy[i] - ux * uy;
        total +=
            ((2.0 * ux * uy + c1) * (2.0 * cxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
    }
    total / mx.len() as f64
}

/// Least squares `(a, b)` minimising `sum (a * estimate + b - truth)^2`: the gain and offset that
/// map a correlation estimate onto the truth. A constant estimate gives `a = 0`, `b = mean(truth)`.
pub fn fit_affine(estimate: &[f32], truth: &[f32]) -> (f64, f64) {
    check_lengths(estimate, truth);
    let n = truth.len() as f64;
    let me = estimate.iter().map(|&v| v as f64).sum::<f64>() / n;
    let mt = truth.iter().map(|&v| v as f64).sum::<f64>() / n;
    let (mut set, mut see) = (0.0, 0.0);
    for (&e, &t) in estimate.iter().zip(truth) {
        let (de, dt) = (e as f64 - me, t as f64 - mt);
        set += de * dt;
        see += de * de;
    }
    let a = if see > 0.0 { set / see } else { 0.0 };
    (a, mt - a * me)
}

/// `||estimate - truth|| / ||truth||` (Euclidean). A zero truth gives 0 for a zero estimate and
/// `f64::INFINITY` otherwise.
pub fn relative_error(estimate: &[f32], truth: &[f32]) -> f64 {
    check_lengths(estimate, truth);
    let (mut num, mut den) = (0.0, 0.0);
    for (&e, &t) in estimate.iter().zip(truth) {
        let d = e as f64 - t as f64;
        num += d * d;
        den += t as f64 * t as f64;
    }
    if den == 0.0 {
        return if num == 0.0 { 0.0 } else { f64::INFINITY };
    }
    (num / den).sqrt()
}

/// Pearson correlation coefficient; 0 when either image is constant.
pub fn pearson(estimate: &[f32], truth: &[f32]) -> f64 {
    check_lengths(estimate, truth);
    let n = truth.len() as f64;
    let me = estimate.iter().map(|&v| v as f64).sum::<f64>() / n;
    let mt = truth.iter().map(|&v| v as f64).sum::<f64>() / n;
    let (mut set, mut see, mut stt) = (0.0, 0.0, 0.0);
    for (&e, &t) in estimate.iter().zip(truth) {
        let (de, dt) = (e as f64 - me, t as f64 - mt);
        set += de * dt;
        see += de * de;
        stt += dt * dt;
    }
    if see == 0.0 || stt == 0.0 {
        0.0
    } else {
        set / (see * stt).sqrt()
    }
}

// ---------------------------------------------------------------------------------------------
// Scores of a finished reconstruction against a simulated session's ground truth (the report's
// `quality`).

// The report's figures are the contract's types (`helmholtz_proto::rest`).
pub use helmholtz_proto::rest::{AffineFit, ChannelQuality, Figure, TransportQuality};

/// Every channel whose image is `w x h` against `truth`: one image shared by every channel, or
/// one per channel (row-major, concatenated).
pub fn dual_quality(
    images: &[super::DualImage],
    channels: &[String],
    w: u32,
    h: u32,
    truth: &[f32],
) -> Vec<ChannelQuality> {
    let k = w as usize * h as usize;
    images
        .iter()
        .zip(channels)
        .enumerate()
        .filter(|(_, (img, _))| img.width == w && img.height == h)
        .map(|(c, (img, name))| {
            let truth = if truth.len() >= (c + 1) * k && truth.len() > k {
                &truth[c * k..(c + 1) * k]
            } else {
                &truth[..k]
            };
            let (a, b) = fit_affine(&img.data, truth);
            let fitted: Vec<f32> = img
                .data
                .iter()
                .map(|&v| (a * v as f64 + b) as f32)
                .collect();
            let (w, h) = (w as usize, h as usize);
            ChannelQuality {
                channel: name.clone(),
                psnr_db: Figure(psnr(&img.data, truth)),
                ssim: Figure(ssim(&img.data, truth, w, h)),
                relative_error: Figure(relative_error(&img.data, truth)),
                psnr_fitted_db: Figure(psnr(&fitted, truth)),
                ssim_fitted: Figure(ssim(&fitted, truth, w, h)),
                fit: AffineFit {
                    scale: a,
                    offset: b,
                },
            }
        })
        .collect()
}

/// `t` against `truth` (`w x h` projector pixels, `truth.len() / (w h)` camera pixels);
/// `summed` is `T^T 1`. A `t` on a coarser projector grid (`projector_binning`) is judged
/// against the truth's `b x b` blocks summed.
pub fn transport_quality(
    t: &super::transport::TransportMatrix,
    summed: &[f32],
    w: u32,
    h: u32,
    truth: &[f32],
) -> TransportQuality {
    let (tw, th) = t.projector();
    if (tw, th) != (w, h) {
        let fine = w as usize * h as usize;
        if tw == 0
            || th == 0
            || !w.is_multiple_of(tw)
            || !h.is_multiple_of(th)
            || w / tw != h / th
            || fine == 0
        {
            return TransportQuality::Unavailable {
                unavailable: "the ground truth does not match the projector grid".into(),
            };
        }
        let b = (w / tw) as usize;
        let (wu, cw) = (w as usize, tw as usize);
        let binned: Vec<f32> = truth
            .chunks_exact(fine)
            .flat_map(|row| {
                let mut out = vec![0f64; cw * th as usize];
                for (i, v) in row.iter().enumerate() {
                    out[(i / wu / b) * cw + (i % wu) / b] += *v as f64;
                }
                out.into_iter().map(|v| v as f32)
            })
            .collect();
        if binned.len() * b * b != truth.len() {
            return TransportQuality::Unavailable {
                unavailable: "the ground truth does not match the camera and pattern sizes".into(),
            };
        }
        return transport_quality(t, summed, tw, th, &binned);
    }
    let k = w as usize * h as usize;
    let m = truth.len() / k.max(1);
    if k == 0 || truth.len() != m * k || t.camera().0 as usize * t.camera().1 as usize != m {
        return TransportQuality::Unavailable {
            unavailable: "the ground truth does not match the camera and pattern sizes".into(),
        };
    }
    let (mut err2, mut norm2, mut worst) = (0.0f64, 0.0f64, 0.0f64);
    let mut column_sums = vec![0f32; k];
    for j in 0..m {
        let row = t.row(j);
        let want = &truth[j * k..(j + 1) * k];
        let (mut e, mut n) = (0.0f64, 0.0f64);
        for ((a, b), s) in row.iter().zip(want).zip(column_sums.iter_mut()) {
            e += (*a as f64 - *b as f64).powi(2);
            n += (*b as f64).powi(2);
            *s += b;
        }
        err2 += e;
        norm2 += n;
        if n > 0.0 {
            worst = worst.max((e / n).sqrt());
        }
    }
    TransportQuality::Scored {
        transport_relative_error: Figure((err2 / norm2).sqrt()),
        worst_row_relative_error: Figure(worst),
        camera_dual_psnr_db: Figure(psnr(summed, &column_sums)),
        camera_dual_ssim: Figure(ssim(summed, &column_sums, w as usize, h as usize)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::Rng;

    fn ramp(w: usize, h: usize) -> Vec<f32> {
        // t(x, y) = x / (w - 1): linear in x, constant in y.
        (0..h)
            .flat_map(|_| (0..w).map(move |x| x as f32 / (w - 1) as f32))
            .collect()
    }

    #[test]
    fn psnr_known_answers() {
        let t = [0.0f32, 1.0, 2.0, 3.0];
        assert_eq!(psnr(&t, &t), f64::INFINITY);
        // Every pixel off by 0.5: MSE 0.25, peak 3 -> 10 log10(9 / 0.25) = 10 log10(36).
        let e = [0.5f32, 1.5, 2.5, 3.5];
        assert!((psnr(&e, &t) - 10.0 * 36f64.log10()).abs() < 1e-12);
        // One pixel off by 2 of four: MSE 1, peak 3 -> 20 log10(3).
        let e = [0.0f32, 1.0, 4.0, 3.0];
        assert!((psnr(&e, &t) - 20.0 * 3f64.log10()).abs() < 1e-12);
        // Constant truth 2: peak falls back to max = 2; MSE 1 -> 20 log10(2).
        let c = [2.0f32; 4];
        let e = [3.0f32, 1.0, 3.0, 1.0];
        assert!((psnr(&e, &c) - 20.0 * 2f64.log10()).abs() < 1e-12);
    }

    #[test]
    fn ssim_identical_is_one() {
        let mut rng = Rng::new(3);
        let t: Vec<f32> = (0..40 * 30).map(|_| rng.uniform() as f32).collect();
        assert!((ssim(&t, &t, 40, 30) - 1.0).abs() < 1e-12);
        // Small images (window shrinks to fit) too.
        let s: Vec<f32> = t[..6 * 5].to_vec();
        assert!((ssim(&s, &s, 6, 5) - 1.0).abs() < 1e-12);
    }

    /// On a linear ramp every 11 x 11 window has mean = its centre value `mu` and the same
    /// variance `s2 = sum_i g_i (i - 5)^2 / (w - 1)^2` (g the normalised 1D Gaussian), so
    /// SSIM has a closed form per window.
    #[test]
    fn ssim_closed_forms_on_a_ramp() {
        let (w, h) = (32usize, 16usize);
        let t = ramp(w, h);
        let g = gaussian(11);
        let s2: f64 = g
            .iter()
            .enumerate()
            .map(|(i, gi)| gi * (i as f64 - 5.0).powi(2))
            .sum::<f64>()
            / ((w - 1) as f64).powi(2);
        let (c1, c2) = (1e-4, 9e-4); // L = 1
        let centres: Vec<f64> = (5..w - 5).map(|x| x as f64 / (w - 1) as f64).collect();
        let rows = (h - 10) as f64;
        let mean_over = |f: &dyn Fn(f64) -> f64| {
            centres.iter().map(|&mu| f(mu)).sum::<f64>() * rows / (centres.len() as f64 * rows)
        };

        // Offset by delta: structure term is exactly 1, luminance term differs.
        let delta = 0.1;
        let e: Vec<f32> = t.iter().map(|v| v + delta as f32).collect();
        let want =
            mean_over(&|mu| (2.0 * mu * (mu + delta) + c1) / (mu * mu + (mu + delta).powi(2) + c1));
        assert!((ssim(&e, &t, w, h) - want).abs() < 1e-5, "offset");

        // Doubled: sigma_e = 2 s, cov = 2 s^2, mean 2 mu.
        let e: Vec<f32> = t.iter().map(|v| 2.0 * v).collect();
        let want = mean_over(&|mu| {
            ((4.0 * mu * mu + c1) * (4.0 * s2 + c2)) / ((5.0 * mu * mu + c1) * (5.0 * s2 + c2))
        });
        assert!((ssim(&e, &t, w, h) - want).abs() < 1e-5, "scaled");
    }

    #[test]
    fn noise_lowers_ssim_monotonically() {
        let (w, h) = (48usize, 40usize);
        let t: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                0.5 + 0.4 * (x / 5.0).sin() * (y / 7.0).cos()
            })
            .collect();
        let mut last = 1.0;
        for sigma in [0.01, 0.05, 0.2] {
            let mut rng = Rng::new(11);
            let e: Vec<f32> = t
                .iter()
                .map(|v| v + (sigma * rng.normal()) as f32)
                .collect();
            let s = ssim(&e, &t, w, h);
            assert!(s < last - 1e-3, "sigma {sigma}: ssim {s} not below {last}");
            last = s;
        }
        assert!(last < 0.5, "heavy noise should wreck SSIM, got {last}");
    }

    #[test]
    fn affine_fit_and_relative_error() {
        let t = [0.0f32, 1.0, 5.0, 2.0, 7.0];
        let e: Vec<f32> = t.iter().map(|v| 2.0 * v + 3.0).collect();
        let (a, b) = fit_affine(&e, &t);
        assert!(
            (a - 0.5).abs() < 1e-12 && (b + 1.5).abs() < 1e-12,
            "({a}, {b})"
        );
        let (a, b) = fit_affine(&[4.0; 5], &t);
        assert_eq!(a, 0.0);
        assert!((b - 3.0).abs() < 1e-12);

        assert_eq!(relative_error(&[3.0, 4.0], &[3.0, 4.0]), 0.0);
        assert!((relative_error(&[3.0, 9.0], &[3.0, 4.0]) - 1.0).abs() < 1e-12);
        assert!((relative_error(&[0.0, 0.0], &[3.0, 4.0]) - 1.0).abs() < 1e-12);
        assert_eq!(relative_error(&[1.0], &[0.0]), f64::INFINITY);

        assert!((pearson(&e, &t) - 1.0).abs() < 1e-12);
        let neg: Vec<f32> = t.iter().map(|v| -v).collect();
        assert!((pearson(&neg, &t) + 1.0).abs() < 1e-12);
    }

    #[test]
    fn figures_serialise_as_reports_show_them() {
        let v = serde_json::to_value([Figure(1.5), Figure(f64::INFINITY), Figure(f64::NAN)]);
        assert_eq!(v.unwrap(), serde_json::json!([1.5, "inf", null]));
    }

    #[test]
    fn dual_quality_scores_each_channel_against_its_own_truth() {
        let truth = [0.0f32, 1.0, 2.0, 3.0, 10.0, 20.0, 30.0, 40.0];
        let image = |data: &[f32]| crate::DualImage {
            width: 2,
            height: 2,
            data: data.to_vec(),
        };
        // Channel a is exact; channel b is its truth at half scale plus 1.
        let images = [image(&truth[..4]), image(&[6.0, 11.0, 16.0, 21.0])];
        let names = ["a".to_string(), "b".to_string()];
        let q = dual_quality(&images, &names, 2, 2, &truth);
        assert_eq!(q[0].psnr_db, Figure(f64::INFINITY));
        assert!(q[1].relative_error.0 > 0.1);
        assert!((q[1].fit.scale - 2.0).abs() < 1e-9 && (q[1].fit.offset + 2.0).abs() < 1e-9);
        assert_eq!(q[1].psnr_fitted_db, Figure(f64::INFINITY));
    }
}
