//! Minimal SVG line plots: time (log scale) against quality, one curve per method.

use std::fmt::Write;

/// One curve: a label and its (seconds, dB) points.
pub struct Curve {
    pub label: String,
    pub points: Vec<(f64, f64)>,
}

const COLORS: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
];

/// An SVG of `curves` with x = log10(seconds), y = PSNR in dB.
pub fn time_vs_psnr(title: &str, curves: &[Curve]) -> String {
    let (w, h, ml, mr, mt, mb) = (560.0, 340.0, 56.0, 150.0, 30.0, 44.0);
    let pts: Vec<(f64, f64)> = curves
        .iter()
        .flat_map(|c| c.points.iter().copied())
        .filter(|(t, q)| t.is_finite() && *t > 0.0 && q.is_finite())
        .collect();
    let mut svg = String::new();
    let _ = write!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="11">"#
    );
    let _ = write!(
        svg,
        r#"<rect width="{w}" height="{h}" fill="white"/><text x="{}" y="18" font-size="13">{}</text>"#,
        ml,
        escape(title)
    );
    if pts.is_empty() {
        svg.push_str("<text x=\"60\" y=\"100\">no finite points</text></svg>");
        return svg;
    }
    let lx: Vec<f64> = pts.iter().map(|p| p.0.log10()).collect();
    let (mut x0, mut x1) = (
        lx.iter().cloned().fold(f64::INFINITY, f64::min).floor(),
        lx.iter().cloned().fold(f64::NEG_INFINITY, f64::max).ceil(),
    );
    if x1 <= x0 {
        x0 -= 1.0;
        x1 += 1.0;
    }
    let ys: Vec<f64> = pts.iter().map(|p| p.1).collect();
    let (mut y0, mut y1) = (
        ys.iter().cloned().fold(f64::INFINITY, f64::min),
        ys.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    );
    y0 = (y0 / 5.0).floor() * 5.0;
    y1 = (y1 / 5.0).ceil() * 5.0;
    if y1 <= y0 {
        y1 = y0 + 5.0;
    }
    let (pw, ph) = (w - ml - mr, h - mt - mb);
    let sx = |t: f64| ml + (t.log10() - x0) / (x1 - x0) * pw;
    let sy = |q: f64| mt + (1.0 - (q - y0) / (y1 - y0)) * ph;
    let _ = write!(
        svg,
        r##"<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" fill="none" stroke="#888"/>"##
    );
    let mut e = x0 as i32;
    while e as f64 <= x1 {
        let x = ml + (e as f64 - x0) / (x1 - x0) * pw;
        let _ = write!(
            svg,
            r##"<line x1="{x}" y1="{mt}" x2="{x}" y2="{}" stroke="#eee"/><text x="{x}" y="{}" text-anchor="middle">1e{e} s</text>"##,
            mt + ph,
            mt + ph + 16.0
        );
        e += 1;
    }
    let mut q = y0;
    while q <= y1 + 1e-9 {
        let y = sy(q);
        let _ = write!(
            svg,
            r##"<line x1="{ml}" y1="{y}" x2="{}" y2="{y}" stroke="#eee"/><text x="{}" y="{}" text-anchor="end">{q:.0}</text>"##,
            ml + pw,
            ml - 6.0,
            y + 4.0
        );
        q += 5.0;
    }
    let _ = write!(
        svg,
        r#"<text x="{}" y="{}" text-anchor="middle">reconstruction time (log scale)</text>"#,
        ml + pw / 2.0,
        h - 6.0
    );
    let _ = write!(
        svg,
        r#"<text x="14" y="{}" transform="rotate(-90 14 {})" text-anchor="middle">PSNR (dB)</text>"#,
        mt + ph / 2.0,
        mt + ph / 2.0
    );
    for (i, c) in curves.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        let mut p: Vec<(f64, f64)> = c
            .points
            .iter()
            .copied()
            .filter(|(t, q)| t.is_finite() && *t > 0.0 && q.is_finite())
            .collect();
        p.sort_by(|a, b| a.0.total_cmp(&b.0));
        if p.len() > 1 {
            let path: Vec<String> = p
                .iter()
                .map(|&(t, q)| format!("{:.1},{:.1}", sx(t), sy(q)))
                .collect();
            let _ = write!(
                svg,
                r#"<polyline points="{}" fill="none" stroke="{color}" stroke-width="1.5"/>"#,
                path.join(" ")
            );
        }
        for &(t, q) in &p {
            let _ = write!(
                svg,
                r#"<circle cx="{:.1}" cy="{:.1}" r="3" fill="{color}"/>"#,
                sx(t),
                sy(q)
            );
        }
        let ly = mt + 14.0 + 16.0 * i as f64;
        let _ = write!(
            svg,
            r#"<rect x="{}" y="{}" width="10" height="10" fill="{color}"/><text x="{}" y="{}">{}</text>"#,
            ml + pw + 12.0,
            ly - 9.0,
            ml + pw + 26.0,
            ly,
            escape(&c.label)
        );
    }
    svg.push_str("</svg>");
    svg
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
