use super::geometry::uniform;
use super::*;

fn random(len: usize, seed: u64) -> Vec<f64> {
    (0..len)
        .map(|i| 2.0 * uniform(seed, i as u64) - 1.0)
        .collect()
}

fn inner(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn scenes() -> Vec<(&'static str, RenderedTransport)> {
    vec![
        ("cornell", RenderedTransport::cornell((12, 10), (14, 12), 3)),
        ("glossy", RenderedTransport::glossy((12, 10), (14, 12), 3)),
        ("slide", RenderedTransport::slide((12, 10), (14, 12), 3)),
    ]
}

#[test]
fn relight_is_the_adjoint_of_render() {
    for (name, t) in scenes() {
        assert_eq!((t.pixels(), t.projector_pixels()), (14 * 12, 12 * 10));
        for s in 0..3 {
            let (p, c) = (
                random(t.projector_pixels(), 10 + s),
                random(t.pixels(), 20 + s),
            );
            let (lhs, rhs) = (inner(&t.render(&p), &c), inner(&p, &t.relight(&c)));
            let size = t.render(&p).iter().map(|v| v.abs()).sum::<f64>()
                * c.iter().map(|v| v.abs()).fold(0.0, f64::max);
            assert!((lhs - rhs).abs() <= 1e-10 * size, "{name}: {lhs} vs {rhs}");
        }
        // Rows, the dense copy and render agree.
        let p = random(t.projector_pixels(), 5);
        let frame = t.render(&p);
        let dense = t.dense();
        let k = t.projector_pixels();
        for j in [0, t.pixels() / 2, t.pixels() - 1] {
            assert_eq!(inner(t.row(j), &p), frame[j]);
            assert!(
                dense[j * k..(j + 1) * k]
                    .iter()
                    .zip(t.row(j))
                    .all(|(a, b)| *a == *b as f32)
            );
        }
    }
}

#[test]
fn transports_are_nonnegative_and_direct_is_a_part_of_them() {
    for (name, t) in scenes() {
        let d = t.direct_only();
        assert!(
            t.matrix().iter().all(|v| v.is_finite() && *v >= 0.0),
            "{name}"
        );
        assert!(
            t.matrix()
                .iter()
                .zip(d.matrix())
                .all(|(a, b)| *b >= 0.0 && *b <= *a),
            "{name}"
        );
        assert_eq!(d.indirect_share(), 0.0);
        assert!(t.total() > 0.0 && t.lit_rows() > 0, "{name}");
    }
}

#[test]
fn scenes_are_deterministic_by_seed() {
    for f in [
        RenderedTransport::cornell,
        RenderedTransport::glossy,
        RenderedTransport::slide,
    ] {
        let a = f((10, 8), (12, 12), 7);
        assert_eq!(a, f((10, 8), (12, 12), 7));
        assert_ne!(a.matrix(), f((10, 8), (12, 12), 8).matrix());
    }
}

#[test]
fn cornell_radiosity_meets_its_equation() {
    let r = cornell::render((12, 12), (12, 12), 1);
    let (n, k) = (r.room.len(), 144);
    let f = &r.room.form;
    // F: nonnegative, rows summing below 1 (the box is open at the front), reciprocity exact.
    for p in 0..n {
        let row: f64 = f[p * n..(p + 1) * n].iter().sum();
        assert!(row < 1.0 && f[p * n + p] == 0.0, "row sum {row}");
        for q in 0..n {
            let (ap, aq) = (r.room.patches[p].1, r.room.patches[q].1);
            assert!(f[p * n + q] >= 0.0);
            assert!((ap * f[p * n + q] - aq * f[q * n + p]).abs() <= 1e-14);
        }
    }
    let big = r.b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut worst = 0.0f64;
    for p in 0..n {
        let rho = r.room.patches[p].2;
        for i in 0..k {
            let gathered: f64 = (0..n).map(|q| f[p * n + q] * r.b[q * k + i]).sum();
            worst = worst.max((r.b[p * k + i] - r.e[p * k + i] - rho * gathered).abs());
        }
    }
    assert!(worst <= 1e-10 * big, "residual {worst} of {big}");
    assert!(r.sweeps > 5, "{} sweeps: several bounces", r.sweeps);
}

#[test]
fn cornell_conserves_energy() {
    let r = cornell::render((10, 10), (8, 8), 2);
    let (n, k) = (r.room.len(), 100);
    let rho_max = r.room.patches.iter().map(|p| p.2).fold(0.0, f64::max);
    for i in 0..k {
        // Every projector ray lands in the box.
        assert!((r.power[i] - 1.0).abs() < 1e-12);
        // Power in = absorbed + escaped through the opening; light leaving the walls is bounded
        // by the geometric series of the largest albedo.
        let (mut absorbed, mut escaped, mut leaving) = (0.0, 0.0, 0.0);
        for p in 0..n {
            let (_, area, rho) = r.room.patches[p];
            let b = r.b[p * k + i];
            let kept: f64 = r.room.form[p * n..(p + 1) * n].iter().sum();
            absorbed += area * b * (1.0 - rho) / rho;
            escaped += area * b * (1.0 - kept);
            leaving += area * b;
        }
        assert!(
            (absorbed + escaped - r.power[i]).abs() < 1e-9,
            "{absorbed} + {escaped}"
        );
        assert!(leaving <= rho_max / (1.0 - rho_max) * r.power[i]);
        assert!(escaped > 0.0 && escaped < leaving);
    }
}

#[test]
fn the_box_has_a_dense_indirect_share_of_10_to_40_percent() {
    for (projector, camera) in [((32, 32), (48, 48)), ((16, 16), (20, 20))] {
        let t = RenderedTransport::cornell(projector, camera, 5);
        let share = t.indirect_share();
        assert!(
            (0.10..=0.40).contains(&share),
            "{projector:?} {camera:?}: indirect share {share}"
        );
        // The indirect light reaches nearly every entry; the direct light few.
        let entries = (t.pixels() * t.projector_pixels()) as f64;
        assert!(t.nonzeros() as f64 > 0.8 * entries);
        assert!((t.direct_only().nonzeros() as f64) < 0.05 * entries);
    }
}

#[test]
fn the_glossy_spheres_add_a_sparse_bright_specular_part() {
    let r = glossy::render((32, 32), (48, 48), 1);
    let (m, k) = (48 * 48, 32 * 32);
    let specular: Vec<f64> = r.glint.iter().zip(&r.caustic).map(|(a, b)| a + b).collect();
    let nonzero = |v: &[f64]| v.iter().filter(|&&x| x != 0.0).count() as f64 / (m * k) as f64;
    // Sparse: few entries, and each sphere pixel's light goes to a small set of camera pixels.
    assert!(
        nonzero(&specular) < 0.02,
        "specular fill {}",
        nonzero(&specular)
    );
    for pixels in &r.on_sphere {
        assert!(pixels.len() > 10, "the sphere catches light");
        for &i in pixels {
            let col = (0..m).filter(|&j| specular[j * k + i] != 0.0).count();
            assert!(
                col < m / 20,
                "projector pixel {i} spreads over {col} camera pixels"
            );
        }
    }
    // Bright: the brightest specular entry outshines every diffuse one, and the caustic (the
    // glass ball's light, all projector pixels on) concentrates on a few camera pixels brighter
    // than the diffusely lit floor.
    let max = |v: &[f64]| v.iter().cloned().fold(0.0, f64::max);
    assert!(max(&specular) > max(&r.diffuse));
    let ones = vec![1.0; k];
    let row_sums =
        |t: &[f64]| -> Vec<f64> { t.chunks_exact(k).map(|row| inner(row, &ones)).collect() };
    let (caustic, diffuse) = (row_sums(&r.caustic), row_sums(&r.diffuse));
    assert!(
        max(&caustic) > 2.0 * max(&diffuse),
        "{} vs {}",
        max(&caustic),
        max(&diffuse)
    );
    let bright = caustic.iter().filter(|&&v| v > 0.5 * max(&caustic)).count();
    assert!(
        bright < m / 100,
        "{bright} camera pixels in the caustic's core"
    );
    let share = r.transport.indirect_share();
    assert!(share > 0.02 && share < 0.5, "indirect share {share}");
}

#[test]
fn the_slide_lights_a_third_of_the_camera_with_a_few_projector_pixels_each() {
    for (projector, camera) in [((32, 32), (48, 48)), ((32, 32), (64, 64))] {
        let t = RenderedTransport::slide(projector, camera, 1);
        let k = t.projector_pixels();
        let lit = t.lit_rows() as f64 / t.pixels() as f64;
        assert!(
            (0.30..=0.40).contains(&lit),
            "{camera:?}: lit fraction {lit}"
        );
        let mut per_row = Vec::new();
        for j in 0..t.pixels() {
            let nnz = t.row(j).iter().filter(|&&v| v != 0.0).count();
            if nnz > 0 {
                per_row.push(nnz);
            }
        }
        assert_eq!(per_row.len(), t.lit_rows());
        let mean = per_row.iter().sum::<usize>() as f64 / per_row.len() as f64;
        assert!(
            (3.0..=6.0).contains(&mean),
            "{camera:?}: {mean} nonzeros per lit row"
        );
        assert!(per_row.iter().all(|&n| n <= 8));
        assert_eq!(t.indirect_share(), 0.0);
        assert!(k == 1024);
    }
}
