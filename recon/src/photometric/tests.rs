//! Analytic scenes with known normals and albedo, rendered with the Lambertian model.

use super::*;
use crate::testutil::Rng;

const SIDE: u32 = 64;

/// Unit directions at `elevation` degrees above the image plane, at `azimuths` degrees from +x
/// (east) toward +y (down the image).
fn ring(elevation: f64, azimuths: &[f64]) -> Vec<[f64; 3]> {
    let e = elevation.to_radians();
    azimuths
        .iter()
        .map(|a| a.to_radians())
        .map(|a| [e.cos() * a.cos(), e.cos() * a.sin(), e.sin()])
        .collect()
}

/// Four detectors east, south, west, north at 45 degrees elevation.
fn four() -> Vec<[f64; 3]> {
    ring(45.0, &[0.0, 90.0, 180.0, 270.0])
}

struct Scene {
    normals: Vec<[f64; 3]>,
    albedo: Vec<f64>,
}

/// Smoothly varying albedo in [0.3, 0.8], with a black 2-pixel border (albedo 0: too dark to fit).
fn albedo_at(x: usize, y: usize) -> f64 {
    let s = SIDE as usize;
    if x < 2 || y < 2 || x >= s - 2 || y >= s - 2 {
        return 0.0;
    }
    0.55 + 0.25 * (x as f64 / 7.0).sin() * (y as f64 / 5.0).cos()
}

/// A hemisphere of radius 22 pixels on a plane facing the projector.
fn hemisphere_on_plane() -> Scene {
    let s = SIDE as usize;
    let (c, r) = (s as f64 / 2.0, 22.0);
    let mut scene = Scene {
        normals: Vec::new(),
        albedo: Vec::new(),
    };
    for y in 0..s {
        for x in 0..s {
            let (dx, dy) = (x as f64 + 0.5 - c, y as f64 + 0.5 - c);
            let d2 = dx * dx + dy * dy;
            let n = if d2 < r * r {
                [dx / r, dy / r, (r * r - d2).sqrt() / r]
            } else {
                [0.0, 0.0, 1.0]
            };
            scene.normals.push(n);
            scene.albedo.push(albedo_at(x, y));
        }
    }
    scene
}

fn tilted_plane(n: [f64; 3]) -> Scene {
    let s = SIDE as usize;
    let l = norm(&n);
    let n = [n[0] / l, n[1] / l, n[2] / l];
    Scene {
        normals: vec![n; s * s],
        albedo: (0..s * s).map(|p| albedo_at(p % s, p / s)).collect(),
    }
}

fn render(scene: &Scene, dirs: &[[f64; 3]], gains: &[f64]) -> Vec<Vec<f32>> {
    dirs.iter()
        .zip(gains)
        .map(|(l, g)| {
            scene
                .normals
                .iter()
                .zip(&scene.albedo)
                .map(|(n, a)| (g * a * dot(n, l).max(0.0)) as f32)
                .collect()
        })
        .collect()
}

/// Adds Gaussian noise of standard deviation `fraction` of the brightest value over all channels.
fn add_noise(images: &mut [Vec<f32>], fraction: f64, seed: u64) {
    let peak = images.iter().flatten().fold(0f32, |m, &v| m.max(v)) as f64;
    let mut rng = Rng::new(seed);
    for v in images.iter_mut().flatten() {
        *v += (fraction * peak * rng.normal()) as f32;
    }
}

fn run(
    images: &[Vec<f32>],
    dirs: &[[f64; 3]],
    options: &PhotometricOptions,
) -> Result<(NormalMap, Value), PhotometricError> {
    let refs: Vec<&[f32]> = images.iter().map(|v| v.as_slice()).collect();
    photometric_stereo(&refs, dirs, SIDE, SIDE, options)
}

fn equal() -> PhotometricOptions {
    PhotometricOptions {
        gains: Gains::Equal,
        ..PhotometricOptions::default()
    }
}

fn angle_deg(a: [f32; 3], b: [f64; 3]) -> f64 {
    let a = [a[0] as f64, a[1] as f64, a[2] as f64];
    (dot(&a, &b) / norm(&a) / norm(&b))
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

#[derive(Debug)]
struct Errors {
    determined: usize,
    mean_deg: f64,
    p95_deg: f64,
    albedo_median: f64,
    albedo_p95: f64,
}

/// Angular errors of the determined normals and relative albedo errors (after dividing the
/// albedo by `albedo_scale`).
fn errors(map: &NormalMap, scene: &Scene, albedo_scale: f64) -> Errors {
    let (mut angles, mut albedo) = (Vec::new(), Vec::new());
    for p in (0..map.normals.len()).filter(|&p| map.is_determined(p)) {
        angles.push(angle_deg(map.normals[p], scene.normals[p]));
        albedo
            .push((map.albedo[p] as f64 / albedo_scale - scene.albedo[p]).abs() / scene.albedo[p]);
    }
    Errors {
        determined: angles.len(),
        mean_deg: angles.iter().sum::<f64>() / angles.len() as f64,
        p95_deg: percentile(angles, 0.95),
        albedo_median: percentile(albedo.clone(), 0.5),
        albedo_p95: percentile(albedo, 0.95),
    }
}

#[test]
fn symmetric_eigen_decomposes() {
    let mut rng = Rng::new(3);
    let n = 6;
    let b: Vec<f64> = (0..n * n).map(|_| rng.normal()).collect();
    let a: Vec<f64> = (0..n * n)
        .map(|i| (0..n).map(|k| b[i / n * n + k] * b[i % n * n + k]).sum())
        .collect();
    let (values, vectors) = symmetric_eigen(a.clone(), n);
    assert!(values.windows(2).all(|w| w[0] <= w[1]), "{values:?}");
    for e in 0..n {
        for r in 0..n {
            let av: f64 = (0..n).map(|k| a[r * n + k] * vectors[k * n + e]).sum();
            assert!(
                (av - values[e] * vectors[r * n + e]).abs() < 1e-10,
                "A v != lambda v"
            );
        }
        let length: f64 = (0..n).map(|r| vectors[r * n + e].powi(2)).sum();
        assert!((length - 1.0).abs() < 1e-12);
    }
}

#[test]
fn hemisphere_noise_free_is_exact_and_flags_only_the_rim_and_the_dark_border() {
    let scene = hemisphere_on_plane();
    let dirs = four();
    let images = render(&scene, &dirs, &[1.0; 4]);
    let (map, report) = run(&images, &dirs, &equal()).unwrap();
    let e = errors(&map, &scene, 1.0);
    eprintln!("noise-free hemisphere: {e:?}");
    assert!(e.mean_deg < 0.01 && e.p95_deg < 0.01, "{e:?}");
    assert!(e.albedo_p95 < 1e-4, "{e:?}");
    let border = (SIDE * SIDE) as usize - 60 * 60;
    assert_eq!(report["undetermined"]["dark"], border);
    for p in 0..map.normals.len() {
        let n = scene.normals[p];
        if scene.albedo[p] == 0.0 {
            assert!(!map.is_determined(p));
        } else if n[2] > 0.7 {
            // Every detector lights a normal within 45 degrees of the viewer.
            assert!(
                map.is_determined(p),
                "pixel {p} with n_z {} undetermined",
                n[2]
            );
        } else if !map.is_determined(p) {
            // Two of four detectors are behind a normal only beyond 54.7 degrees (cot < cos 45).
            assert!(n[2] < 0.6, "pixel {p} with n_z {} undetermined", n[2]);
            assert!(map.lit[p] < 3 && map.albedo[p].is_nan() && map.residual[p].is_nan());
        }
    }
    assert_eq!(report["determined"], e.determined);
    assert!(
        report["residual"]["p95"].as_f64().unwrap() < 1e-5,
        "{report}"
    );
}

#[test]
fn tilted_plane_with_three_detectors_is_exact() {
    let scene = tilted_plane([0.3, -0.2, 0.9]);
    let dirs = ring(50.0, &[0.0, 120.0, 240.0]);
    let images = render(&scene, &dirs, &[1.0; 3]);
    let (map, report) = run(&images, &dirs, &PhotometricOptions::default()).unwrap();
    let e = errors(&map, &scene, 1.0);
    assert_eq!(e.determined, 60 * 60, "{report}");
    assert!(
        e.mean_deg < 0.01 && e.p95_deg < 0.01 && e.albedo_p95 < 1e-4,
        "{e:?}"
    );
    // Auto with three detectors cannot estimate gains: it says it assumed them equal.
    assert_eq!(report["gains"]["mode"], "equal");
    assert!(
        report["gains"]["reason"]
            .as_str()
            .unwrap()
            .contains("linear map"),
        "{report}"
    );
}

#[test]
fn noisy_hemisphere_stays_within_stated_errors() {
    let scene = hemisphere_on_plane();
    let dirs = four();
    for (fraction, max_mean, max_p95, max_albedo_median, max_albedo_p95) in
        [(0.005, 0.6, 1.5, 0.01, 0.03), (0.01, 1.2, 3.0, 0.02, 0.06)]
    {
        let mut images = render(&scene, &dirs, &[1.0; 4]);
        add_noise(&mut images, fraction, 11);
        let (map, _) = run(&images, &dirs, &equal()).unwrap();
        let e = errors(&map, &scene, 1.0);
        eprintln!("noise {fraction} of peak, equal gains: {e:?}");
        assert!(e.determined > 3000, "{e:?}");
        // The black border is noise around 0: too dark to fit, not a random normal.
        assert!(
            (0..map.normals.len())
                .filter(|&p| scene.albedo[p] == 0.0)
                .all(|p| !map.is_determined(p))
        );
        assert!(e.mean_deg < max_mean && e.p95_deg < max_p95, "{e:?}");
        assert!(
            e.albedo_median < max_albedo_median && e.albedo_p95 < max_albedo_p95,
            "{e:?}"
        );
    }
}

#[test]
fn noise_on_the_plane_matches_the_least_squares_prediction() {
    // Facing the viewer with four detectors at 45 degrees, L^T L = diag(1, 1, 2): noise of
    // deviation sigma moves b_x, b_y by sigma each and b_z by sigma / sqrt(2). So the angular error
    // over sigma / albedo is Rayleigh (mean sqrt(pi / 2), mean square 2) and the albedo error over
    // sigma / sqrt(2) is standard normal (mean square 1).
    let scene = hemisphere_on_plane();
    let dirs = four();
    let mut images = render(&scene, &dirs, &[1.0; 4]);
    let fraction = 0.01;
    let peak = images.iter().flatten().fold(0f32, |m, &v| m.max(v)) as f64;
    add_noise(&mut images, fraction, 23);
    let sigma = fraction * peak;
    let (map, _) = run(&images, &dirs, &equal()).unwrap();
    let plane: Vec<usize> = (0..map.normals.len())
        .filter(|&p| scene.normals[p][2] == 1.0 && scene.albedo[p] > 0.0)
        .collect();
    assert!(plane.iter().all(|&p| map.lit[p] == 4));
    let n = plane.len() as f64;
    let angle: Vec<f64> = plane
        .iter()
        .map(|&p| {
            angle_deg(map.normals[p], scene.normals[p]).to_radians() / (sigma / scene.albedo[p])
        })
        .collect();
    let mean = angle.iter().sum::<f64>() / n;
    let square = angle.iter().map(|a| a * a).sum::<f64>() / n;
    let albedo = plane
        .iter()
        .map(|&p| ((map.albedo[p] as f64 - scene.albedo[p]) / (sigma / 2f64.sqrt())).powi(2))
        .sum::<f64>()
        / n;
    eprintln!(
        "{n} plane pixels: angle/(sigma/albedo) mean {mean:.4} (sqrt(pi/2) = 1.2533), mean square {square:.4} (2); albedo error mean square {albedo:.4} (1)"
    );
    // Standard errors for ~2000 pixels: 0.014, 0.044, 0.032; the bounds are about 3.5 of them.
    assert!(
        (mean - (std::f64::consts::PI / 2.0).sqrt()).abs() < 0.05,
        "{mean}"
    );
    assert!((square - 2.0).abs() < 0.15, "{square}");
    assert!((albedo - 1.0).abs() < 0.11, "{albedo}");
}

#[test]
fn attached_shadow_drops_the_channel_and_keeps_the_normal() {
    let scene = hemisphere_on_plane();
    let dirs = four();
    let images = render(&scene, &dirs, &[1.0; 4]);
    let (map, _) = run(&images, &dirs, &equal()).unwrap();
    // Pixels behind exactly one detector (n . l <= 0) and well lit by the other three.
    let shadowed: Vec<usize> = (0..map.normals.len())
        .filter(|&p| {
            let s: Vec<f64> = dirs.iter().map(|l| dot(&scene.normals[p], l)).collect();
            s.iter().filter(|&&v| v <= 0.0).count() == 1
                && s.iter().filter(|&&v| v > 0.2).count() == 3
        })
        .collect();
    assert!(shadowed.len() > 50, "{}", shadowed.len());
    for p in shadowed {
        assert_eq!(map.lit[p], 3, "pixel {p}");
        let error = angle_deg(map.normals[p], scene.normals[p]);
        assert!(error < 0.01, "pixel {p}: {error} degrees");
        // An attached shadow is what the model predicts: no misfit.
        assert!(
            map.residual[p] < 1e-5,
            "pixel {p}: residual {}",
            map.residual[p]
        );
    }
}

#[test]
fn cast_shadow_keeps_the_normal_and_shows_in_the_residual() {
    let scene = hemisphere_on_plane();
    let dirs = four();
    let mut images = render(&scene, &dirs, &[1.0; 4]);
    // Something blocks the west detector's view of a patch of the plane.
    let in_patch = |p: usize| (3..13).contains(&(p % 64)) && (3..13).contains(&(p / 64));
    for p in (0..images[2].len()).filter(|&p| in_patch(p)) {
        images[2][p] = 0.0;
    }
    let (map, report) = run(&images, &dirs, &equal()).unwrap();
    for p in 0..map.normals.len() {
        if in_patch(p) {
            assert_eq!(map.lit[p], 3);
            assert!(angle_deg(map.normals[p], scene.normals[p]) < 0.01);
            // Four equal channels (flat normal) with one dark: misfit 1/sqrt(3).
            assert!(
                (map.residual[p] - 1.0 / 3f32.sqrt()).abs() < 1e-4,
                "{}",
                map.residual[p]
            );
        } else if map.is_determined(p) {
            assert!(map.residual[p] < 1e-5);
        }
    }
    assert!(
        report["shadowed_pixels_per_channel"][2].as_u64().unwrap() >= 100,
        "{report}"
    );
    assert!(report["residual"]["fraction_above_0.1"].as_f64().unwrap() > 0.0);
}

#[test]
fn specular_highlight_shows_in_the_residual() {
    let scene = hemisphere_on_plane();
    let dirs = four();
    let mut images = render(&scene, &dirs, &[1.0; 4]);
    // A highlight: the east channel twice as bright as the cosine law on a small disc.
    let in_disc =
        |p: usize| ((p % 64) as f64 - 40.0).powi(2) + ((p / 64) as f64 - 30.0).powi(2) < 9.0;
    for p in (0..images[0].len()).filter(|&p| in_disc(p)) {
        images[0][p] *= 2.0;
    }
    let (map, _) = run(&images, &dirs, &equal()).unwrap();
    for p in (0..map.normals.len()).filter(|&p| map.is_determined(p)) {
        if in_disc(p) {
            assert!(map.residual[p] > 0.1, "pixel {p}: {}", map.residual[p]);
            // The normal tilts toward the east detector.
            assert!(map.normals[p][0] as f64 > scene.normals[p][0] + 0.05);
        } else {
            assert!(map.residual[p] < 1e-5);
        }
    }
}

#[test]
fn unknown_gains_are_estimated_with_four_detectors() {
    let scene = hemisphere_on_plane();
    let dirs = four();
    let truth = [0.8, 1.3, 0.9, 1.0]; // mean 1, the normalisation of the estimate
    let images = render(&scene, &dirs, &truth);
    let (map, report) = run(
        &images,
        &dirs,
        &PhotometricOptions {
            gains: Gains::Estimate,
            ..Default::default()
        },
    )
    .unwrap();
    let gains: Vec<f64> = serde_json::from_value(report["gains"]["values"].clone()).unwrap();
    eprintln!("noise-free estimated gains {gains:?}, {}", report["gains"]);
    for (g, t) in gains.iter().zip(truth) {
        assert!((g - t).abs() / t < 1e-4, "{gains:?}");
    }
    let e = errors(&map, &scene, 1.0);
    assert!(
        e.mean_deg < 0.01 && e.p95_deg < 0.01 && e.albedo_p95 < 1e-4,
        "{e:?}"
    );

    // Assuming equal gains instead bends every normal (the linear ambiguity) and the residual
    // shows it.
    let (wrong, wrong_report) = run(&images, &dirs, &equal()).unwrap();
    let w = errors(&wrong, &scene, 1.0);
    eprintln!(
        "same data, equal gains assumed: {w:?}, residual {}",
        wrong_report["residual"]
    );
    assert!(w.mean_deg > 5.0, "{w:?}");
    assert!(wrong_report["residual"]["median"].as_f64().unwrap() > 0.05);

    // With 1 % noise.
    let mut noisy = images.clone();
    add_noise(&mut noisy, 0.01, 5);
    let (map, report) = run(&noisy, &dirs, &PhotometricOptions::default()).unwrap();
    assert_eq!(report["gains"]["mode"], "estimated");
    let gains: Vec<f64> = serde_json::from_value(report["gains"]["values"].clone()).unwrap();
    let worst = gains
        .iter()
        .zip(truth)
        .map(|(g, t)| (g - t).abs() / t)
        .fold(0.0, f64::max);
    let e = errors(&map, &scene, 1.0);
    eprintln!("noise 0.01, estimated gains {gains:?} (worst relative error {worst:.4}): {e:?}");
    assert!(worst < 0.01, "{gains:?}");
    // Estimating the gains costs little against knowing them.
    let (known, _) = run(
        &noisy,
        &dirs,
        &PhotometricOptions {
            gains: Gains::Given(truth.to_vec()),
            ..Default::default()
        },
    )
    .unwrap();
    let k = errors(&known, &scene, 1.0);
    eprintln!("noise 0.01, true gains given: {k:?}");
    assert!(
        e.mean_deg < 1.1 * k.mean_deg && e.p95_deg < 1.1 * k.p95_deg,
        "{e:?} vs {k:?}"
    );
    assert!(
        e.mean_deg < 2.0 && e.p95_deg < 4.0 && e.albedo_median < 0.015,
        "{e:?}"
    );
}

#[test]
fn given_gains_are_divided_out() {
    let scene = tilted_plane([-0.1, 0.25, 1.0]);
    let dirs = ring(35.0, &[10.0, 130.0, 250.0]);
    let truth = [2.0, 0.5, 1.25];
    let images = render(&scene, &dirs, &truth);
    let (map, report) = run(
        &images,
        &dirs,
        &PhotometricOptions {
            gains: Gains::Given(truth.to_vec()),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(report["gains"]["mode"], "given");
    let e = errors(&map, &scene, 1.0);
    assert!(
        e.determined == 3600 && e.mean_deg < 0.01 && e.albedo_p95 < 1e-4,
        "{e:?}"
    );
}

#[test]
fn a_flat_scene_cannot_fix_the_gains() {
    let scene = tilted_plane([0.2, 0.1, 1.0]);
    let dirs = four();
    let images = render(&scene, &dirs, &[0.8, 1.3, 0.9, 1.0]);
    let err = run(
        &images,
        &dirs,
        &PhotometricOptions {
            gains: Gains::Estimate,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(
        matches!(err, PhotometricError::GainsUndetermined(_)),
        "{err}"
    );
    assert_eq!(err.field(), "gains");
    let (_, report) = run(&images, &dirs, &PhotometricOptions::default()).unwrap();
    assert_eq!(report["gains"]["mode"], "equal");
    assert!(
        report["gains"]["reason"]
            .as_str()
            .unwrap()
            .contains("does not fix"),
        "{report}"
    );
}

#[test]
fn normals_facing_away_are_clamped_to_the_image_plane() {
    // Eight detectors near the horizon see a surface tilted 5.7 degrees past edge-on: the fit
    // says n_z < 0, which no visible surface has, so the normal is projected onto z = 0.
    let scene = tilted_plane([0.995, 0.0, -0.1]);
    let dirs = ring(10.0, &[0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0]);
    let images = render(&scene, &dirs, &[1.0; 8]);
    let (map, report) = run(&images, &dirs, &equal()).unwrap();
    assert_eq!(report["normals_clamped_to_z_0"], 3600, "{report}");
    for p in (0..map.normals.len()).filter(|&p| scene.albedo[p] > 0.0) {
        assert_eq!(map.lit[p], 3);
        let n = map.normals[p];
        assert!(n[2] == 0.0 && n[0] == 1.0 && n[1].abs() < 1e-6, "{n:?}");
    }
}

#[test]
fn bad_inputs_are_refused_naming_the_field() {
    let scene = tilted_plane([0.0, 0.0, 1.0]);
    let dirs = four();
    let images = render(&scene, &dirs, &[1.0; 4]);
    let field = |r: Result<(NormalMap, Value), PhotometricError>| r.unwrap_err().field();

    assert_eq!(field(run(&images[..2], &dirs[..2], &equal())), "images");
    // Coplanar: all in the image plane, or three directions of which two coincide.
    let flat = ring(0.0, &[0.0, 90.0, 180.0, 270.0]);
    let err = run(&images, &flat, &equal()).unwrap_err();
    assert!(
        matches!(err, PhotometricError::CoplanarDirections { .. }) && err.field() == "directions",
        "{err}"
    );
    let twice = [dirs[0], dirs[1], dirs[1]];
    assert!(matches!(
        run(&images[..3], &twice, &equal()).unwrap_err(),
        PhotometricError::CoplanarDirections { .. }
    ));
    // Same azimuth plane through z: (x, 0, z) directions are coplanar.
    let meridian = [[1.0, 0.0, 0.0], [0.6, 0.0, 0.8], [-0.6, 0.0, 0.8]];
    assert!(matches!(
        run(&images[..3], &meridian, &equal()).unwrap_err(),
        PhotometricError::CoplanarDirections { .. }
    ));
    let mut long = dirs.clone();
    long[1] = [0.0, 1.1, 0.0];
    assert_eq!(field(run(&images, &long, &equal())), "directions[1]");
    long[1] = [f64::NAN, 0.0, 1.0];
    assert_eq!(field(run(&images, &long, &equal())), "directions[1]");
    assert_eq!(field(run(&images, &dirs[..3], &equal())), "directions");
    let mut short = images.clone();
    short[2].pop();
    assert_eq!(field(run(&short, &dirs, &equal())), "images[2]");
    let refs: Vec<&[f32]> = images.iter().map(|v| v.as_slice()).collect();
    assert_eq!(
        photometric_stereo(&refs, &dirs, 0, 64, &equal())
            .unwrap_err()
            .field(),
        "width"
    );
    assert_eq!(
        field(run(
            &images,
            &dirs,
            &PhotometricOptions {
                gains: Gains::Given(vec![1.0; 3]),
                ..equal()
            }
        )),
        "gains"
    );
    assert_eq!(
        field(run(
            &images,
            &dirs,
            &PhotometricOptions {
                gains: Gains::Given(vec![1.0, -1.0, 1.0, 1.0]),
                ..equal()
            }
        )),
        "gains"
    );
    assert_eq!(
        field(run(
            &images[..3],
            &dirs[..3],
            &PhotometricOptions {
                gains: Gains::Estimate,
                ..equal()
            }
        )),
        "gains"
    );
    assert_eq!(
        field(run(
            &images,
            &dirs,
            &PhotometricOptions {
                shadow_threshold: 1.0,
                ..equal()
            }
        )),
        "shadow_threshold"
    );
    assert_eq!(
        field(run(
            &images,
            &dirs,
            &PhotometricOptions {
                dark_threshold: f64::NAN,
                ..equal()
            }
        )),
        "dark_threshold"
    );
}

#[test]
fn report_names_the_failure_modes() {
    let scene = tilted_plane([0.0, 0.0, 1.0]);
    let dirs = four();
    let images = render(&scene, &dirs, &[1.0; 4]);
    let (_, report) = run(&images, &dirs, &equal()).unwrap();
    let text = report["lambertian_fails_where"].to_string();
    for needle in [
        "specular",
        "interreflections",
        "near the scene",
        "cast shadows",
        "gains",
    ] {
        assert!(text.contains(needle), "{needle} missing from {text}");
    }
}

#[test]
fn options_from_params_name_bad_keys() {
    assert_eq!(
        PhotometricOptions::from_params(&Value::Null).unwrap(),
        PhotometricOptions::default()
    );
    let o = PhotometricOptions::from_params(
        &json!({"shadow_threshold": 0.1, "dark_threshold": 0.0, "gains": [1, 0.5, 2]}),
    )
    .unwrap();
    assert_eq!(
        o,
        PhotometricOptions {
            shadow_threshold: 0.1,
            dark_threshold: 0.0,
            gains: Gains::Given(vec![1.0, 0.5, 2.0])
        }
    );
    for (name, gains) in [
        ("auto", Gains::Auto),
        ("equal", Gains::Equal),
        ("estimate", Gains::Estimate),
    ] {
        assert_eq!(
            PhotometricOptions::from_params(&json!({"gains": name}))
                .unwrap()
                .gains,
            gains
        );
    }
    let field = |v: Value| PhotometricOptions::from_params(&v).unwrap_err().field();
    assert_eq!(
        field(json!({"shadow_threshold": "high"})),
        "shadow_threshold"
    );
    assert_eq!(field(json!({"dark_threshold": null})), "dark_threshold");
    assert_eq!(field(json!({"gains": "guess"})), "gains");
    assert_eq!(field(json!({"gains": [1, "x"]})), "gains");
    assert_eq!(field(json!({"shadow": 0.1})), "params");
    assert_eq!(field(json!([1])), "params");
    // Ranges are checked with the images (shadow_threshold 1 is refused there).
    let o = PhotometricOptions::from_params(&json!({"shadow_threshold": 1.0})).unwrap();
    let scene = tilted_plane([0.0, 0.0, 1.0]);
    let images = render(&scene, &four(), &[1.0; 4]);
    assert_eq!(
        run(&images, &four(), &o).unwrap_err().field(),
        "shadow_threshold"
    );
}
