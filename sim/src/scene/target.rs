//! Flat test targets (the [`Flat`](super::Scene::Flat) kind of [`Scene`](super::Scene)): the
//! transport `t` one bucket detector measures of a flat target is its grey image on the pattern
//! grid (values in [0, 1]), so the image is the dual image to recover.
//!
//! Sources: any PNG file, the embedded photos `camera` and
//! `shapes` (see `sim/images/README.md`), and two procedural targets drawn analytically at any
//! size with exact area coverage (no aliasing): `usaf` (a USAF-1951 resolution chart),
//! `double-slit` (the classic ghost-imaging target) and `text` (a page of dark 5x7 capitals on a
//! bright ground); and `smooth`, a smooth low-contrast field (values 0.55 to 1: no edges, little
//! contrast over a large common level, the hardest kind of scene for 0/1 patterns under noise).

use std::path::Path;

use anyhow::{Context, bail};

use helmholtz_proto::png as pngio;

const CAMERA_PNG: &[u8] = include_bytes!("../../images/camera-256.png");
const SHAPES_PNG: &[u8] = include_bytes!("../../images/shapes-256.png");

/// Names accepted by [`Target::builtin`].
pub const BUILTIN_TARGETS: [&str; 6] =
    ["camera", "shapes", "usaf", "double-slit", "smooth", "text"];

/// A grey image, row-major, values in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct Target {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<f32>,
}

impl Target {
    /// A built-in scene at `width x height`: photos are resampled, procedural targets are drawn
    /// at that size directly.
    pub fn builtin(name: &str, width: u32, height: u32) -> anyhow::Result<Target> {
        anyhow::ensure!(width > 0 && height > 0, "scene size must be positive");
        match name {
            "camera" => Ok(Target::from_png_bytes(CAMERA_PNG)?.resample(width, height)),
            "shapes" => Ok(Target::from_png_bytes(SHAPES_PNG)?.resample(width, height)),
            "usaf" => Ok(usaf(width, height)),
            "double-slit" | "double_slit" => Ok(double_slit(width, height)),
            "smooth" => Ok(smooth(width, height)),
            "text" => Ok(text(width, height)),
            other => bail!(
                "unknown built-in scene {other:?}: expected one of {} or a path to a .png file",
                BUILTIN_TARGETS.join(", ")
            ),
        }
    }

    /// A built-in name, or else a path to a PNG file; resampled to `width x height`.
    pub fn load(name_or_path: &str, width: u32, height: u32) -> anyhow::Result<Target> {
        if BUILTIN_TARGETS.contains(&name_or_path) || name_or_path == "double_slit" {
            return Target::builtin(name_or_path, width, height);
        }
        let path = Path::new(name_or_path);
        if !path.exists() {
            bail!(
                "scene {name_or_path:?} is neither a built-in ({}) nor an existing file",
                BUILTIN_TARGETS.join(", ")
            );
        }
        Ok(Target::from_png_file(path)?.resample(width, height))
    }

    /// Reads a PNG file (grey or colour, 8 or 16 bit) as luminance.
    pub fn from_png_file(path: &Path) -> anyhow::Result<Target> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        Target::from_png_bytes(&bytes).with_context(|| format!("decoding {}", path.display()))
    }

    /// Decodes PNG bytes as luminance.
    pub fn from_png_bytes(bytes: &[u8]) -> anyhow::Result<Target> {
        let img = pngio::decode_luminance(bytes)?;
        Ok(Target {
            width: img.width,
            height: img.height,
            pixels: img.pixels,
        })
    }

    /// Resampled to `width x height`: area average along an axis that shrinks (every source pixel
    /// contributes by its overlap), bilinear (pixel centres aligned) along an axis that grows.
    pub fn resample(&self, width: u32, height: u32) -> Target {
        Target {
            width,
            height,
            pixels: resample(&self.pixels, self.width, self.height, width, height),
        }
    }

    /// The transport a simulated rig sees: the scene scaled so its maximum is `peak`
    /// (an all-black scene stays zero). Values are >= 0.
    pub fn transport(&self, peak: f32) -> Vec<f32> {
        let max = self.pixels.iter().copied().fold(0.0f32, f32::max);
        if max <= 0.0 {
            return vec![0.0; self.pixels.len()];
        }
        let s = peak / max;
        self.pixels.iter().map(|&v| (v * s).max(0.0)).collect()
    }

    /// As an 8-bit grey PNG.
    pub fn to_png(&self) -> anyhow::Result<Vec<u8>> {
        pngio::encode_grey8(self.width, self.height, &pngio::to_grey8(&self.pixels))
    }
}

/// Resamples a row-major image `sw x sh` to `dw x dh` (separable; see [`Target::resample`]).
pub fn resample(src: &[f32], sw: u32, sh: u32, dw: u32, dh: u32) -> Vec<f32> {
    assert_eq!(src.len(), sw as usize * sh as usize);
    let (sw, sh, dw, dh) = (sw as usize, sh as usize, dw as usize, dh as usize);
    let wx = axis_weights(sw, dw);
    let wy = axis_weights(sh, dh);
    // Horizontal pass: sh x dw.
    let mut tmp = vec![0.0f32; sh * dw];
    for y in 0..sh {
        let row = &src[y * sw..(y + 1) * sw];
        for (x, taps) in wx.iter().enumerate() {
            tmp[y * dw + x] = taps.iter().map(|&(i, w)| row[i] * w).sum();
        }
    }
    // Vertical pass: dh x dw.
    let mut out = vec![0.0f32; dh * dw];
    for (y, taps) in wy.iter().enumerate() {
        let dst = &mut out[y * dw..(y + 1) * dw];
        for &(i, w) in taps {
            for (d, s) in dst.iter_mut().zip(&tmp[i * dw..(i + 1) * dw]) {
                *d += s * w;
            }
        }
    }
    out
}

/// Per output index, the (source index, weight) taps along one axis; weights sum to 1.
fn axis_weights(src: usize, dst: usize) -> Vec<Vec<(usize, f32)>> {
    let scale = src as f64 / dst as f64;
    (0..dst)
        .map(|o| {
            if scale >= 1.0 {
                // Box filter: output pixel o covers source interval [o*scale, (o+1)*scale).
                let (lo, hi) = (o as f64 * scale, (o + 1) as f64 * scale);
                let first = lo.floor() as usize;
                let last = (hi.ceil() as usize).min(src);
                (first..last)
                    .filter_map(|i| {
                        let overlap = hi.min(i as f64 + 1.0) - lo.max(i as f64);
                        (overlap > 1e-12).then_some((i, (overlap / scale) as f32))
                    })
                    .collect()
            } else {
                let x = ((o as f64 + 0.5) * scale - 0.5).clamp(0.0, (src - 1) as f64);
                let i0 = x.floor() as usize;
                let i1 = (i0 + 1).min(src - 1);
                let f = (x - i0 as f64) as f32;
                if i1 == i0 || f == 0.0 {
                    vec![(i0, 1.0)]
                } else {
                    vec![(i0, 1.0 - f), (i1, f)]
                }
            }
        })
        .collect()
}

/// An axis-aligned rectangle in pixel units `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rect {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

/// Adds `value` times the exact area of `rect` falling in each pixel.
fn paint_rect(pixels: &mut [f32], width: u32, height: u32, rect: Rect, value: f32) {
    let (w, h) = (width as f64, height as f64);
    let (x0, x1) = (rect.x0.clamp(0.0, w), rect.x1.clamp(0.0, w));
    let (y0, y1) = (rect.y0.clamp(0.0, h), rect.y1.clamp(0.0, h));
    if x1 <= x0 || y1 <= y0 {
        return;
    }
    for py in y0.floor() as usize..(y1.ceil() as usize).min(height as usize) {
        let cy = (y1.min(py as f64 + 1.0) - y0.max(py as f64)).max(0.0);
        for px in x0.floor() as usize..(x1.ceil() as usize).min(width as usize) {
            let cx = (x1.min(px as f64 + 1.0) - x0.max(px as f64)).max(0.0);
            pixels[py * width as usize + px] += (cx * cy) as f32 * value;
        }
    }
}

fn render(width: u32, height: u32, rects: &[Rect]) -> Target {
    let mut pixels = vec![0.0f32; width as usize * height as usize];
    for &r in rects {
        paint_rect(&mut pixels, width, height, r, 1.0);
    }
    for p in &mut pixels {
        *p = p.clamp(0.0, 1.0);
    }
    Target {
        width,
        height,
        pixels,
    }
}

/// One USAF-1951 element: three vertical bars (left square) and three horizontal bars (right
/// square), each bar `bar` wide and `5 * bar` long, separated by `bar`; pixel units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UsafElement {
    /// Top-left corner of the element's vertical-bar square.
    pub x: f64,
    pub y: f64,
    /// Bar width (= gap width); element `e` has `bar = bar_0 * 2^(-e/6)`.
    pub bar: f64,
}

impl UsafElement {
    /// The three vertical bars (they resolve horizontal detail).
    pub fn vertical_bars(&self) -> [Rect; 3] {
        let b = self.bar;
        std::array::from_fn(|j| {
            let x0 = self.x + 2.0 * j as f64 * b;
            Rect {
                x0,
                y0: self.y,
                x1: x0 + b,
                y1: self.y + 5.0 * b,
            }
        })
    }

    /// The three horizontal bars, in the square `2 * bar` to the right of the vertical ones.
    pub fn horizontal_bars(&self) -> [Rect; 3] {
        let b = self.bar;
        let x0 = self.x + 7.0 * b;
        std::array::from_fn(|j| {
            let y0 = self.y + 2.0 * j as f64 * b;
            Rect {
                x0,
                y0,
                x1: x0 + 5.0 * b,
                y1: y0 + b,
            }
        })
    }
}

/// Layout of the USAF target on a `width x height` grid: elements shrink by 2^(1/6) (six per
/// group, one octave per group), stacked in columns from the top-left of the centred square of
/// side `min(width, height)`; the largest bar is 1/32 of that side. Elements whose bars would be
/// thinner than half a pixel are left out (they cannot be drawn on this grid).
pub fn usaf_layout(width: u32, height: u32) -> Vec<UsafElement> {
    let side = width.min(height) as f64;
    let (ox, oy) = ((width as f64 - side) / 2.0, (height as f64 - side) / 2.0);
    let bar0 = side / 32.0;
    let margin = bar0;
    let ratio = 2f64.powf(-1.0 / 6.0);
    let mut elements = Vec::new();
    let (mut x, mut y) = (margin, margin);
    let mut column_bar = bar0;
    for e in 0..36 {
        let bar = bar0 * ratio.powi(e);
        if bar < 0.5 {
            break;
        }
        if y + 5.0 * bar > side - margin {
            // Next column: right of the widest (first) element of this one.
            x += 12.0 * column_bar + 2.0 * bar;
            y = margin;
            column_bar = bar;
        }
        if x + 12.0 * bar > side - margin {
            break;
        }
        elements.push(UsafElement {
            x: ox + x,
            y: oy + y,
            bar,
        });
        y += 7.0 * bar;
    }
    elements
}

/// A USAF-1951 resolution target: bright bars on a dark ground (see [`usaf_layout`]).
pub fn usaf(width: u32, height: u32) -> Target {
    let rects: Vec<Rect> = usaf_layout(width, height)
        .iter()
        .flat_map(|e| e.vertical_bars().into_iter().chain(e.horizontal_bars()))
        .collect();
    render(width, height, &rects)
}

/// The two slits of [`double_slit`], pixel units: each `width / 20` wide, centres `width / 5`
/// apart, `0.6 * height` tall, centred.
pub fn double_slit_rects(width: u32, height: u32) -> [Rect; 2] {
    let (w, h) = (width as f64, height as f64);
    let slit = w / 20.0;
    let (y0, y1) = (0.2 * h, 0.8 * h);
    let centres = [w / 2.0 - w / 10.0, w / 2.0 + w / 10.0];
    centres.map(|c| Rect {
        x0: c - slit / 2.0,
        y0,
        x1: c + slit / 2.0,
        y1,
    })
}

/// Two bright vertical slits on black (Pittman et al. 1995's ghost-imaging target).
pub fn double_slit(width: u32, height: u32) -> Target {
    render(width, height, &double_slit_rects(width, height))
}

/// A smooth low-contrast field: two gentle waves and a soft blob over a level of 0.55, values
/// in [0.55, 1] (the maximum is exactly 1), evaluated at pixel centres (band-limited enough not
/// to alias at any size).
pub fn smooth(width: u32, height: u32) -> Target {
    use std::f64::consts::PI;
    let (w, h) = (width as f64, height as f64);
    let raw: Vec<f64> = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (u, v) = ((x as f64 + 0.5) / w, (y as f64 + 0.5) / h);
            let waves = (2.0 * PI * (1.3 * u + 0.4 * v)).sin() * (2.0 * PI * 0.8 * v).cos();
            let blob = (-((u - 0.62).powi(2) + (v - 0.35).powi(2)) / (2.0 * 0.12f64.powi(2))).exp();
            waves + 1.5 * blob
        })
        .collect();
    let (lo, hi) = raw
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let span = if hi > lo { hi - lo } else { 1.0 };
    Target {
        width,
        height,
        pixels: raw
            .iter()
            .map(|&v| (0.55 + 0.45 * (v - lo) / span) as f32)
            .collect(),
    }
}

/// 5x7 capitals of [`text`], one string of five `#`/space cells per row.
const GLYPHS: [(char, [&str; 7]); 26] = [
    (
        'A',
        [
            " ### ", "#   #", "#   #", "#####", "#   #", "#   #", "#   #",
        ],
    ),
    (
        'B',
        [
            "#### ", "#   #", "#   #", "#### ", "#   #", "#   #", "#### ",
        ],
    ),
    (
        'C',
        [
            " ### ", "#   #", "#    ", "#    ", "#    ", "#   #", " ### ",
        ],
    ),
    (
        'D',
        [
            "#### ", "#   #", "#   #", "#   #", "#   #", "#   #", "#### ",
        ],
    ),
    (
        'E',
        [
            "#####", "#    ", "#    ", "#### ", "#    ", "#    ", "#####",
        ],
    ),
    (
        'F',
        [
            "#####", "#    ", "#    ", "#### ", "#    ", "#    ", "#    ",
        ],
    ),
    (
        'G',
        [
            " ### ", "#   #", "#    ", "# ###", "#   #", "#   #", " ####",
        ],
    ),
    (
        'H',
        [
            "#   #", "#   #", "#   #", "#####", "#   #", "#   #", "#   #",
        ],
    ),
    (
        'I',
        [
            " ### ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", " ### ",
        ],
    ),
    (
        'J',
        [
            "  ###", "   # ", "   # ", "   # ", "   # ", "#  # ", " ##  ",
        ],
    ),
    (
        'K',
        [
            "#   #", "#  # ", "# #  ", "##   ", "# #  ", "#  # ", "#   #",
        ],
    ),
    (
        'L',
        [
            "#    ", "#    ", "#    ", "#    ", "#    ", "#    ", "#####",
        ],
    ),
    (
        'M',
        [
            "#   #", "## ##", "# # #", "# # #", "#   #", "#   #", "#   #",
        ],
    ),
    (
        'N',
        [
            "#   #", "##  #", "# # #", "#  ##", "#   #", "#   #", "#   #",
        ],
    ),
    (
        'O',
        [
            " ### ", "#   #", "#   #", "#   #", "#   #", "#   #", " ### ",
        ],
    ),
    (
        'P',
        [
            "#### ", "#   #", "#   #", "#### ", "#    ", "#    ", "#    ",
        ],
    ),
    (
        'Q',
        [
            " ### ", "#   #", "#   #", "#   #", "# # #", "#  # ", " ## #",
        ],
    ),
    (
        'R',
        [
            "#### ", "#   #", "#   #", "#### ", "# #  ", "#  # ", "#   #",
        ],
    ),
    (
        'S',
        [
            " ####", "#    ", "#    ", " ### ", "    #", "    #", "#### ",
        ],
    ),
    (
        'T',
        [
            "#####", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ",
        ],
    ),
    (
        'U',
        [
            "#   #", "#   #", "#   #", "#   #", "#   #", "#   #", " ### ",
        ],
    ),
    (
        'V',
        [
            "#   #", "#   #", "#   #", "#   #", "#   #", " # # ", "  #  ",
        ],
    ),
    (
        'W',
        [
            "#   #", "#   #", "#   #", "# # #", "# # #", "# # #", " # # ",
        ],
    ),
    (
        'X',
        [
            "#   #", "#   #", " # # ", "  #  ", " # # ", "#   #", "#   #",
        ],
    ),
    (
        'Y',
        [
            "#   #", "#   #", " # # ", "  #  ", "  #  ", "  #  ", "  #  ",
        ],
    ),
    (
        'Z',
        [
            "#####", "    #", "   # ", "  #  ", " #   ", "#    ", "#####",
        ],
    ),
];

/// The rectangles of the ink of [`text`], pixel units: lines of the pangram set in 5x7 capitals,
/// a cell of 6x10 units per character, `unit = side / 128` (1 px at 128x128), a margin of 4
/// units; lines wrap at the right margin and stop at the bottom one.
pub fn text_ink(width: u32, height: u32) -> Vec<Rect> {
    const WORDS: &str = "THE QUICK BROWN FOX JUMPS OVER THE LAZY DOG HELMHOLTZ RECIPROCITY SWAPS LIGHTS AND CAMERAS SO A PROJECTOR SEES THE SCENE PACK MY BOX WITH FIVE DOZEN LIQUOR JUGS";
    let unit = width.min(height) as f64 / 128.0;
    let margin = 4.0 * unit;
    let (cw, lh) = (6.0 * unit, 10.0 * unit);
    let per_line = (((width as f64 - 2.0 * margin) / cw).floor() as usize).max(1);
    let lines = ((height as f64 - 2.0 * margin) / lh).floor() as usize;
    let chars: Vec<char> = WORDS.chars().collect();
    let mut rects = Vec::new();
    for line in 0..lines {
        for col in 0..per_line {
            let c = chars[(line * per_line + col) % chars.len()];
            let Some((_, rows)) = GLYPHS.iter().find(|(g, _)| *g == c) else {
                continue; // a space
            };
            for (r, row) in rows.iter().enumerate() {
                for (q, cell) in row.chars().enumerate() {
                    if cell == '#' {
                        let x0 = margin + col as f64 * cw + q as f64 * unit;
                        let y0 = margin + line as f64 * lh + r as f64 * unit;
                        rects.push(Rect {
                            x0,
                            y0,
                            x1: x0 + unit,
                            y1: y0 + unit,
                        });
                    }
                }
            }
        }
    }
    rects
}

/// A page of text: ink at 0.1 on paper at 1 ([`text_ink`]; exact area coverage).
pub fn text(width: u32, height: u32) -> Target {
    let ink = render(width, height, &text_ink(width, height));
    Target {
        width,
        height,
        pixels: ink.pixels.iter().map(|&v| 1.0 - 0.9 * v).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smooth_and_text_are_what_they_say() {
        let s = smooth(64, 48);
        let (lo, hi) = s
            .pixels
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        assert!(
            (lo - 0.55).abs() < 1e-6 && (hi - 1.0).abs() < 1e-6,
            "{lo} {hi}"
        );
        // Smooth: neighbouring pixels differ by little.
        let steps = s
            .pixels
            .chunks_exact(64)
            .flat_map(|row| row.windows(2).map(|p| (p[0] - p[1]).abs()))
            .fold(0.0, f32::max);
        assert!(steps < 0.05, "largest step {steps}");
        // Text: mostly paper, the ink a minority with full-contrast edges; ink covers exactly
        // the glyph cells (area coverage is exact, so the total is an integer count of units).
        let t = text(128, 128);
        let ink: f64 = t.pixels.iter().map(|&v| (1.0 - v as f64) / 0.9).sum();
        let cells = text_ink(128, 128).len() as f64;
        assert!((ink - cells).abs() < 1e-2 * cells, "{ink} vs {cells}");
        assert!(
            cells > 0.1 * 128.0 * 128.0 * 0.2 && cells < 0.4 * 128.0 * 128.0,
            "{cells}"
        );
        assert!(t.pixels.iter().any(|&v| v < 0.2));
        // Every letter of the text has a glyph.
        assert_eq!(GLYPHS.len(), 26);
        assert!(
            GLYPHS
                .iter()
                .all(|(_, rows)| rows.iter().all(|r| r.len() == 5))
        );
    }

    /// Runs of values above `threshold` along a sequence.
    fn bright_runs(values: impl IntoIterator<Item = f32>, threshold: f32) -> usize {
        let mut runs = 0;
        let mut inside = false;
        for v in values {
            if v > threshold && !inside {
                runs += 1;
            }
            inside = v > threshold;
        }
        runs
    }

    #[test]
    fn double_slit_has_two_slits_at_any_size() {
        for (w, h) in [(32, 32), (64, 48), (256, 256), (100, 37)] {
            let s = double_slit(w, h);
            let mid = &s.pixels[(h / 2) as usize * w as usize..(h / 2 + 1) as usize * w as usize];
            assert_eq!(bright_runs(mid.iter().copied(), 0.2), 2, "{w}x{h}");
            // Above and below the slits: dark.
            assert!(s.pixels[..w as usize].iter().all(|&v| v == 0.0));
            // Total brightness = exact slit area (area coverage is exact).
            let area: f64 = s.pixels.iter().map(|&v| v as f64).sum();
            let expect = 2.0 * (w as f64 / 20.0) * (0.6 * h as f64);
            assert!(
                (area - expect).abs() < 1e-3 * expect.max(1.0),
                "{area} vs {expect}"
            );
        }
    }

    #[test]
    fn usaf_bars_have_full_contrast_where_resolvable() {
        let (w, h) = (256, 256);
        let s = usaf(w, h);
        let layout = usaf_layout(w, h);
        assert!(
            layout.len() >= 12,
            "at 256 px at least two groups fit, got {}",
            layout.len()
        );
        // Successive elements shrink by 2^(1/6).
        for pair in layout.windows(2) {
            let r = pair[0].bar / pair[1].bar;
            assert!((r - 2f64.powf(1.0 / 6.0)).abs() < 1e-9);
        }
        let at = |x: f64, y: f64| s.pixels[y as usize * w as usize + x as usize];
        for e in layout.iter().filter(|e| e.bar >= 3.0) {
            // Across the vertical bars, through their middle: three bright runs, dark gaps.
            let y = e.y + 2.5 * e.bar;
            let xs = (0..(5.0 * e.bar) as usize).map(|d| at(e.x + d as f64, y));
            assert_eq!(bright_runs(xs, 0.5), 3, "vertical bars of {e:?}");
            // Down the horizontal bars.
            let x = e.x + 9.5 * e.bar;
            let ys = (0..(5.0 * e.bar) as usize).map(|d| at(x, e.y + d as f64));
            assert_eq!(bright_runs(ys, 0.5), 3, "horizontal bars of {e:?}");
            // Michelson contrast between bar centre and gap centre is 1 for bars >= 3 px.
            let bar = at(e.x + 0.5 * e.bar, y);
            let gap = at(e.x + 1.5 * e.bar, y);
            assert!((bar - gap) / (bar + gap) > 0.99, "contrast {bar} {gap}");
        }
        // Bright bars on dark: most of the chart is background.
        let mean: f32 = s.pixels.iter().sum::<f32>() / s.pixels.len() as f32;
        assert!(mean > 0.02 && mean < 0.5, "mean {mean}");
    }

    #[test]
    fn usaf_fits_and_scales() {
        for (w, h) in [(32, 32), (64, 64), (128, 64), (1024, 1024)] {
            let layout = usaf_layout(w, h);
            assert!(!layout.is_empty());
            for e in &layout {
                for r in e.vertical_bars().iter().chain(&e.horizontal_bars()) {
                    assert!(r.x0 >= 0.0 && r.y0 >= 0.0 && r.x1 <= w as f64 && r.y1 <= h as f64);
                }
                assert!(e.bar >= 0.5);
            }
            let s = usaf(w, h);
            assert!(s.pixels.iter().all(|v| (0.0..=1.0).contains(v)));
            assert!(s.pixels.contains(&1.0));
        }
        // Larger grids resolve more elements.
        assert!(usaf_layout(1024, 1024).len() > usaf_layout(64, 64).len());
    }

    #[test]
    fn resample_area_average_is_exact_on_blocks() {
        // 4x4 -> 2x2 averages 2x2 blocks.
        let src: Vec<f32> = (0..16).map(|v| v as f32).collect();
        let out = resample(&src, 4, 4, 2, 2);
        assert_eq!(out, vec![2.5, 4.5, 10.5, 12.5]);
        // Non-integer factor keeps the mean (every source pixel counted once in total).
        let src: Vec<f32> = (0..7 * 5).map(|v| ((v * 37) % 11) as f32).collect();
        let out = resample(&src, 7, 5, 3, 2);
        let mean_in = src.iter().sum::<f32>() / src.len() as f32;
        let mean_out = out.iter().sum::<f32>() / out.len() as f32;
        assert!((mean_in - mean_out).abs() < 1e-4, "{mean_in} {mean_out}");
    }

    #[test]
    fn resample_preserves_constants_and_ramps() {
        let c = vec![0.25f32; 9 * 4];
        for (dw, dh) in [(3, 2), (18, 8), (5, 11), (9, 4)] {
            let out = resample(&c, 9, 4, dw, dh);
            assert_eq!(out.len(), dw as usize * dh as usize);
            assert!(out.iter().all(|&v| (v - 0.25).abs() < 1e-6));
        }
        // Upsampling a linear ramp 0..3 by 4 is linear between the (aligned) pixel centres.
        let ramp = vec![0.0f32, 1.0, 2.0, 3.0];
        let out = resample(&ramp, 4, 1, 16, 1);
        for (x, &v) in out.iter().enumerate().take(14).skip(2) {
            let expect = (x as f32 + 0.5) / 4.0 - 0.5;
            assert!((v - expect).abs() < 1e-5, "{x}: {v}");
        }
        // Identity.
        let src: Vec<f32> = (0..12).map(|v| v as f32 * 0.1).collect();
        assert_eq!(resample(&src, 4, 3, 4, 3), src);
    }

    #[test]
    fn builtins_load_at_any_size() {
        for name in BUILTIN_TARGETS {
            let s = Target::builtin(name, 48, 40).unwrap();
            assert_eq!(s.pixels.len(), 48 * 40);
            assert!(s.pixels.iter().all(|v| (0.0..=1.0).contains(v)), "{name}");
            let t = s.transport(2.0);
            let max = t.iter().copied().fold(0.0, f32::max);
            assert!((max - 2.0).abs() < 1e-6, "{name}: {max}");
        }
        assert!(Target::builtin("nope", 8, 8).is_err());
        let err = Target::load("/no/such/scene.png", 8, 8)
            .unwrap_err()
            .to_string();
        assert!(err.contains("neither a built-in"), "{err}");
    }

    #[test]
    fn png_round_trip_through_a_file() {
        let dir = tempfile::tempdir().unwrap();
        let s = double_slit(40, 20);
        let path = dir.path().join("slits.png");
        std::fs::write(&path, s.to_png().unwrap()).unwrap();
        let back = Target::load(path.to_str().unwrap(), 40, 20).unwrap();
        for (a, b) in back.pixels.iter().zip(&s.pixels) {
            assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6);
        }
    }
}
