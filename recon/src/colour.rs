//! Colour composites from bucket channels behind red, green and blue filters.
//!
//! Each filtered detector's dual image is the scene in that band, so the three together are a
//! colour image seen from the projector. The composite uses one scale for all three channels and
//! black at 0, so the ratios between channels (the colour) survive. Correlation methods (`gi`,
//! `dgi`, `ngi`) estimate the transport only up to a gain and an offset per channel; their
//! composites are colour-true only as far as those are equal across channels.

/// The quantile of the pixels' brightest channel that maps to white.
pub const WHITE_QUANTILE: f64 = 0.995;

/// Indices of the r, g, b channels if the names say they are colours (case-insensitive `r`/`g`/`b`
/// or `red`/`green`/`blue`, surrounding spaces ignored), else None. Other channels may be present
/// (e.g. `ir`); a colour named twice (`r` and `red`) is ambiguous: None.
pub fn colour_channels(names: &[String]) -> Option<[usize; 3]> {
    let mut found = [None; 3];
    for (i, name) in names.iter().enumerate() {
        let slot = match name.trim().to_ascii_lowercase().as_str() {
            "r" | "red" => 0,
            "g" | "green" => 1,
            "b" | "blue" => 2,
            _ => continue,
        };
        if found[slot].replace(i).is_some() {
            return None;
        }
    }
    Some([found[0]?, found[1]?, found[2]?])
}

/// Interleaved RGB composite in [0, 1] with one common scale for all three channels (keeps the
/// colour balance), robust to outliers: the [`WHITE_QUANTILE`] of the pixels' brightest channel
/// maps to 1, and a brighter pixel is scaled down as a whole (its hue kept) instead of clipped per
/// channel. Negative values (noise around black) and non-finite ones count as 0; an all-dark
/// input gives black. Panics if the three lengths differ.
pub fn composite(r: &[f32], g: &[f32], b: &[f32]) -> Vec<f32> {
    assert!(
        r.len() == g.len() && r.len() == b.len(),
        "r, g, b differ in length: {} {} {}",
        r.len(),
        g.len(),
        b.len()
    );
    let clean = |v: f32| if v.is_finite() { v.max(0.0) } else { 0.0 };
    let mut brightest: Vec<f32> = (0..r.len())
        .map(|i| clean(r[i]).max(clean(g[i])).max(clean(b[i])))
        .collect();
    let white = if brightest.is_empty() {
        0.0
    } else {
        let at = ((brightest.len() - 1) as f64 * WHITE_QUANTILE).round() as usize;
        *brightest
            .select_nth_unstable_by(at, |a, b| a.total_cmp(b))
            .1
    };
    if white.is_nan() || white <= 0.0 {
        return vec![0.0; 3 * r.len()];
    }
    let mut out = Vec::with_capacity(3 * r.len());
    for i in 0..r.len() {
        let pixel = [
            clean(r[i]) / white,
            clean(g[i]) / white,
            clean(b[i]) / white,
        ];
        let top = pixel[0].max(pixel[1]).max(pixel[2]);
        let divisor = top.max(1.0);
        out.extend(pixel.map(|v| v / divisor));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn colour_names_are_recognised_in_any_order_and_case() {
        assert_eq!(colour_channels(&names(&["r", "g", "b"])), Some([0, 1, 2]));
        assert_eq!(
            colour_channels(&names(&["Blue", "GREEN", " red "])),
            Some([2, 1, 0])
        );
        assert_eq!(
            colour_channels(&names(&["ir", "B", "R", "G"])),
            Some([2, 3, 1])
        );
        assert_eq!(colour_channels(&names(&["n", "e", "s", "w"])), None);
        assert_eq!(colour_channels(&names(&["r", "g"])), None);
        assert_eq!(colour_channels(&names(&["r", "red", "g", "b"])), None);
        assert_eq!(colour_channels(&names(&["bucket"])), None);
        assert_eq!(colour_channels(&[]), None);
    }

    #[test]
    fn composite_keeps_channel_ratios_under_one_scale() {
        // A ramp of a fixed colour r:g:b = 4:2:1 plus a hot pixel of another colour.
        let n = 1000;
        let mut r: Vec<f32> = (0..n).map(|i| 4.0 * i as f32 / n as f32).collect();
        let mut g: Vec<f32> = r.iter().map(|v| v / 2.0).collect();
        let mut b: Vec<f32> = r.iter().map(|v| v / 4.0).collect();
        (r[7], g[7], b[7]) = (50.0, 100.0, 25.0);
        let rgb = composite(&r, &g, &b);
        assert_eq!(rgb.len(), 3 * n);
        assert!(rgb.iter().all(|v| (0.0..=1.0).contains(v)));
        for px in rgb
            .chunks_exact(3)
            .enumerate()
            .filter(|(i, _)| *i != 7 && *i > 0)
            .map(|(_, p)| p)
        {
            // Ratios kept exactly (one scale; pixels above white shrink as a whole).
            assert!(
                (px[0] / px[1] - 2.0).abs() < 1e-4 && (px[0] / px[2] - 4.0).abs() < 1e-4,
                "{px:?}"
            );
        }
        // The 99.5th percentile of the brightest channel (red here) maps to 1, not the hot pixel.
        // Ranks skip the hot pixel (index 7): rank round(999 * 0.995) = 994 is ramp index 995, so
        // white = 3.98 and ramp indices 995..=999 reach 1.
        let reds: Vec<f32> = rgb.chunks_exact(3).map(|p| p[0]).collect();
        let full: Vec<usize> = (0..n).filter(|&i| reds[i] >= 1.0 - 1e-6).collect();
        assert_eq!(full, vec![995, 996, 997, 998, 999]);
        assert!(
            reds[n / 2] > 0.49 && reds[n / 2] < 0.52,
            "mid-ramp {}",
            reds[n / 2]
        );
        // The hot pixel keeps its hue: g is the brightest, r:g = 1:2, b:g = 1:4.
        let hot = &rgb[21..24];
        assert_eq!(hot[1], 1.0);
        assert!(
            (hot[0] - 0.5).abs() < 1e-6 && (hot[2] - 0.25).abs() < 1e-6,
            "{hot:?}"
        );
    }

    #[test]
    fn composite_of_dark_or_invalid_input_is_black() {
        assert_eq!(
            composite(&[0.0, -1.0], &[f32::NAN, 0.0], &[0.0, 0.0]),
            vec![0.0; 6]
        );
        assert!(composite(&[], &[], &[]).is_empty());
        let rgb = composite(&[1.0, -0.5], &[1.0, f32::INFINITY], &[1.0, 0.0]);
        assert_eq!(&rgb[3..], &[0.0, 0.0, 0.0]);
    }
}
