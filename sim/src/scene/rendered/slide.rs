//! A printed slide seen at a grazing angle: very sparse rows, most of them exactly zero.
//!
//! The slide is a black card (`z = 0`, 1 wide, 3 deep) printed with text-like glyphs (random
//! 3 x 5 bitmaps in a grid of cells, grey ink 0.55-1, from the seed). The projector lights it
//! head-on (orthographic, its pixel grid stretched over the card); its image on the card is the
//! pattern interpolated bilinearly between pixel centres. The camera (pinhole, nothing behind the
//! card) looks along the card from about 16 degrees above it. Each camera pixel averages two
//! points (a quarter pixel left and right of its centre): its row of `T` is
//! `sum_s ink(x_s) w_i(x_s) / 2`, `w_i` the bilinear weights of projector pixel `i` at `x_s`.
//!
//! So a camera pixel that sees ink has a row with 2-6 nonzeros (4 mostly); a pixel that sees
//! black card or beyond the card has a row of exact zeros. At 32 x 32 x 48 x 48 about a third of
//! the camera pixels see ink. Units: a pixel's value is the ink's reflectance times the
//! projector's interpolated value there (radiance relative to white paper under a full pixel).
//! The light is all first bounce.

use super::RenderedTransport;
use super::geometry::{Pinhole, Rect, bilinear, uniform};

/// Card depth (along y); its width (along x) is 1.
const DEPTH: f64 = 3.0;
/// Glyph cells across and along the card.
const CELLS: (usize, usize) = (6, 12);
/// Probability that a glyph's bitmap cell is inked.
const INK: f64 = 0.6;
const CAMERA_AT: [f64; 3] = [0.5, -2.0, 0.9];
const CAMERA_TARGET: [f64; 3] = [0.5, 1.2, 0.0];
const CAMERA_TAN: f64 = 0.14;

/// The ink's reflectance at card point `(x, y)` (0 off the print).
fn ink(seed: u64, x: f64, y: f64) -> f64 {
    if !(0.0..1.0).contains(&x) || !(0.0..DEPTH).contains(&y) {
        return 0.0;
    }
    let (gx, gy) = (x * CELLS.0 as f64, y / DEPTH * CELLS.1 as f64);
    let (cx, cy) = (gx.floor() as usize, gy.floor() as usize);
    let cell = (cy * CELLS.0 + cx) as u64;
    // Within a cell: a 3 x 5 bitmap in a 4 x 6 grid (one column and one row of margin).
    let (bx, by) = ((gx.fract() * 4.0) as i64, (gy.fract() * 6.0) as i64);
    if !(0..3).contains(&bx) || !(0..5).contains(&by) {
        return 0.0;
    }
    let bit = cell * 16 + (by * 3 + bx) as u64;
    if uniform(seed, bit) < INK {
        0.55 + 0.45 * uniform(seed ^ 0xC01, cell)
    } else {
        0.0
    }
}

pub(super) fn render(
    projector: (usize, usize),
    camera: (usize, usize),
    seed: u64,
) -> RenderedTransport {
    assert!(
        projector.0 > 0 && projector.1 > 0 && camera.0 > 0 && camera.1 > 0,
        "a rig needs pixels"
    );
    let (k, m) = (projector.0 * projector.1, camera.0 * camera.1);
    let card = Rect::new([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, DEPTH, 0.0]);
    let cam = Pinhole::looking_at(
        CAMERA_AT,
        CAMERA_TARGET,
        [0.0, 0.0, 1.0],
        CAMERA_TAN,
        camera.0,
        camera.1,
    );
    let mut t = vec![0.0; m * k];
    for j in 0..m {
        let (col, row) = ((j % camera.0) as f64, (j / camera.0) as f64);
        for du in [-0.25, 0.25] {
            let d = cam.ray(col + du, row);
            let Some((_, a, b)) = card.hit(cam.position, d) else {
                continue;
            };
            let (x, y) = (a, b * DEPTH);
            let rho = ink(seed, x, y);
            if rho == 0.0 {
                continue;
            }
            // Projector pixel centres at ((c + 1/2) / W, (r + 1/2) DEPTH / H), row 0 at y = 0.
            let (u, v) = (
                x * projector.0 as f64 - 0.5,
                y / DEPTH * projector.1 as f64 - 0.5,
            );
            for (i, w) in bilinear(u, v, projector.0, projector.1) {
                t[j * k + i] += 0.5 * rho * w;
            }
        }
    }
    RenderedTransport::new(projector, camera, t.clone(), t)
}
