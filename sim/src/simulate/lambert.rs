//! Simulated rigs on the analytic Lambertian [`Relief`] (`--scene lambert`):
//! bucket detectors in chosen directions (photometric-stereo rigs), colour-filtered buckets, and
//! cameras whose frames are `T p` ([`CameraView::render`]) plus noise.
//!
//! Bucket channels go through the ordinary bucket simulator ([`super::simulate`]) with their
//! dual images `scene.detector_transport(d)` as transports. Camera frames are rendered per
//! pattern and get the bucket simulator's noise model applied per pixel, with figures taken over
//! every pixel of every frame (see [`FrameSimulator`]).

use std::sync::Mutex;

use crate::scene::{Camera, CameraView, Relief};
use helmholtz_proto::{PatternGenerator, PatternSpec};
use serde::Serialize;

use super::random::SplitMix64;
use super::{ChannelNoise, NoiseModel, NoiseReport, drift_factors};
use helmholtz_proto::wire::{SampleBuf, SampleFormat};

/// Noise stream of camera frames (see [`SplitMix64::stream`]).
const STAGE_FRAME: u64 = 3;

/// u16 frames are counts: the brightest noiseless frame pixel (plus the dark offset) maps to
/// this many counts.
pub const U16_FULL_WELL_TARGET: f64 = 60_000.0;

/// The azimuth of a compass-named detector (y is down the image, so north is -y: 270 degrees).
pub fn compass_azimuth(name: &str) -> Option<f64> {
    match name.to_ascii_lowercase().as_str() {
        "n" | "north" => Some(270.0),
        "e" | "east" => Some(0.0),
        "s" | "south" => Some(90.0),
        "w" | "west" => Some(180.0),
        _ => None,
    }
}

/// The bucket channels of a Lambertian rig.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DetectorPlan {
    /// Channel names.
    pub names: Vec<String>,
    /// Unit direction from the scene toward each channel's detector.
    pub directions: Vec<[f64; 3]>,
    /// Per channel: the colour filter (0 red, 1 green, 2 blue), or none (grey albedo).
    pub colours: Vec<Option<usize>>,
}

/// The channels of `--detectors` (names; `None` = one detector at the projector, direction
/// (0, 0, 1)), `--detector-elevation` and `--colour`.
///
/// Named compass detectors (n, e, s, w or north, ...) stand at azimuths 270, 0, 90, 180 degrees;
/// any other name `i` of `n` at `360 i / n` degrees (spread evenly), all at `elevation` degrees
/// above the ground plane. With `colour`, every detector becomes three channels `NAME-r`,
/// `NAME-g`, `NAME-b` (just `r`, `g`, `b` for the single detector at the projector).
pub fn detector_plan(
    detectors: Option<&[String]>,
    elevation_degrees: f64,
    colour: bool,
) -> anyhow::Result<DetectorPlan> {
    let mut plan = DetectorPlan {
        names: Vec::new(),
        directions: Vec::new(),
        colours: Vec::new(),
    };
    let colours: &[(Option<usize>, &str)] = if colour {
        &[(Some(0), "r"), (Some(1), "g"), (Some(2), "b")]
    } else {
        &[(None, "")]
    };
    let detectors: Vec<(String, [f64; 3])> = match detectors {
        None => vec![(String::new(), [0.0, 0.0, 1.0])],
        Some(names) => {
            anyhow::ensure!(!names.is_empty(), "--detectors: name at least one detector");
            anyhow::ensure!(
                elevation_degrees > 0.0 && elevation_degrees <= 90.0,
                "--detector-elevation must be in (0, 90] degrees, got {elevation_degrees}"
            );
            let n = names.len() as f64;
            names
                .iter()
                .enumerate()
                .map(|(i, name)| {
                    let name = name.trim();
                    anyhow::ensure!(!name.is_empty(), "--detectors: empty detector name");
                    let azimuth = compass_azimuth(name).unwrap_or(360.0 * i as f64 / n);
                    // Exact zeros where the trigonometry leaves 1e-17 residues.
                    let d = crate::scene::direction(azimuth, elevation_degrees)
                        .map(|v| if v.abs() < 1e-12 { 0.0 } else { v });
                    Ok((name.to_string(), d))
                })
                .collect::<anyhow::Result<_>>()?
        }
    };
    for (name, dir) in &detectors {
        for (c, suffix) in colours {
            plan.names.push(match (name.is_empty(), suffix.is_empty()) {
                (true, true) => "bucket".to_string(),
                (true, false) => suffix.to_string(),
                (false, true) => name.clone(),
                (false, false) => format!("{name}-{suffix}"),
            });
            plan.directions.push(*dir);
            plan.colours.push(*c);
        }
    }
    let mut seen = std::collections::HashSet::new();
    for n in &plan.names {
        anyhow::ensure!(seen.insert(n), "--detectors: channel {n:?} named twice");
    }
    Ok(plan)
}

/// Each channel's dual image (`k` values, times `gain`): `scene.detector_transport(d)`, or
/// `detector_transport_colour(d, c)` for a colour channel.
pub fn plan_transports(scene: &Relief, plan: &DetectorPlan, gain: f64) -> Vec<Vec<f32>> {
    plan.directions
        .iter()
        .zip(&plan.colours)
        .map(|(&d, colour)| {
            let t = match colour {
                Some(c) => scene.detector_transport_colour(d, *c),
                None => scene.detector_transport(d),
            };
            t.into_iter().map(|v| (v * gain) as f32).collect()
        })
        .collect()
}

/// Parses `WxH` (e.g. `64x48`).
pub fn parse_size(text: &str) -> anyhow::Result<(u32, u32)> {
    let (w, h) = text
        .trim()
        .split_once(['x', 'X'])
        .ok_or_else(|| anyhow::anyhow!("--camera {text:?}: expected WIDTHxHEIGHT, e.g. 64x64"))?;
    let parse = |s: &str| {
        s.trim()
            .parse::<u32>()
            .map_err(|_| anyhow::anyhow!("--camera {text:?}: expected WIDTHxHEIGHT, e.g. 64x64"))
    };
    Ok((parse(w)?, parse(h)?))
}

/// Figures of the noiseless frames over every pixel of every frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FrameStats {
    pub mean: f64,
    pub rms: f64,
    pub max: f64,
}

/// What the noise did to the frames made so far (for the report).
#[derive(Clone, Copy, Debug, Default)]
struct NoiseTally {
    signal_sq: f64,
    error_sq: f64,
    saturated: usize,
}

/// A camera rig imaging the Lambertian scene: renders frames `gain * T p_i`, applies the noise
/// model, and encodes them as f32 or u16.
///
/// Noise (the bucket simulator's stages, per pixel; `c` a noiseless pixel value): drift `x_i`
/// per frame; shot noise `Poisson(alpha c) / alpha` with `alpha = photons / mean` (`--photons`
/// = mean photo-electrons per pixel per frame); read noise `sigma = rms / 10^(snr/20)`; the dark
/// offset. `mean`, `rms`, `max` are over every pixel of every noiseless frame. Then:
///
/// - f32 frames: values in signal units; with `--adc-bits`, clipped to `[0, 1.1 max + dark]`
///   and rounded to `2^bits` levels, as for buckets;
/// - u16 frames: counts, `round(clamp(v * counts_per_unit, 0, 65535))` with
///   `counts_per_unit = 60000 / (max + dark)`, so the brightest noiseless pixel reads about
///   60000 counts.
///
/// Every frame draws from its own random stream: frames are the same however they are batched.
pub struct FrameSimulator<'a> {
    view: CameraView<'a>,
    generator: PatternGenerator,
    spec: PatternSpec,
    gain: f64,
    format: SampleFormat,
    model: NoiseModel,
    stats: FrameStats,
    drift: Vec<f64>,
    alpha: Option<f64>,
    sigma: Option<f64>,
    /// f32 with an ADC: full scale and step.
    adc: Option<(f64, f64)>,
    counts_per_unit: f64,
    tally: Mutex<NoiseTally>,
}

impl<'a> FrameSimulator<'a> {
    /// Prepares the rig; renders every noiseless frame once for the noise figures.
    pub fn new(
        scene: &'a Relief,
        camera: Camera,
        spec: &PatternSpec,
        gain: f64,
        format: SampleFormat,
        model: &NoiseModel,
    ) -> anyhow::Result<Self> {
        anyhow::ensure!(
            scene.width() == spec.width() as usize && scene.height() == spec.height() as usize,
            "the scene is {}x{} but the patterns are {}x{}",
            scene.width(),
            scene.height(),
            spec.width(),
            spec.height()
        );
        anyhow::ensure!(gain > 0.0 && gain.is_finite(), "--gain must be > 0");
        anyhow::ensure!(format != SampleFormat::F64, "camera frames are f32 or u16");
        if format == SampleFormat::U16 {
            anyhow::ensure!(
                model.adc_bits.is_none(),
                "--adc-bits does not apply to u16 frames (they are 16-bit counts already)"
            );
        }
        // An adaptive session's patterns are known batch by batch ([`Self::frames_for`]); its
        // noise figures come from the Walsh-Hadamard split pairs of the same grid, the patterns
        // it chooses among (every pair but the first lights half the projector).
        let stand_in = if spec.is_adaptive() {
            PatternSpec::new(
                helmholtz_proto::Family::Hadamard {
                    ordering: helmholtz_proto::HadamardOrdering::Natural,
                },
                spec.width(),
                spec.height(),
                spec.count().min(2 * spec.pixels() as u64),
                spec.seed(),
            )
            .map_err(|e| anyhow::anyhow!("{}: {}", e.field, e.message))?
        } else {
            spec.clone()
        };
        let mut sim = FrameSimulator {
            view: scene.view(&camera),
            generator: PatternGenerator::new(&stand_in),
            spec: spec.clone(),
            gain,
            format,
            model: model.clone(),
            stats: FrameStats::default(),
            drift: drift_factors(spec.count() as usize, model),
            alpha: None,
            sigma: None,
            adc: None,
            counts_per_unit: 1.0,
            tally: Mutex::new(NoiseTally::default()),
        };
        sim.stats = sim.measure_stats();
        let FrameStats { mean, rms, max } = sim.stats;
        sim.alpha = model.photons.filter(|_| mean > 0.0).map(|n| n / mean);
        sim.sigma = model.snr_db.map(|db| rms / 10f64.powf(db / 20.0));
        sim.adc = model.adc_bits.map(|b| {
            let full_scale = 1.1 * max + model.dark;
            (full_scale, full_scale / ((1u64 << b) - 1) as f64)
        });
        let top = max + model.dark;
        sim.counts_per_unit = if top > 0.0 {
            U16_FULL_WELL_TARGET / top
        } else {
            1.0
        };
        Ok(sim)
    }

    pub fn view(&self) -> &CameraView<'a> {
        &self.view
    }

    pub fn stats(&self) -> FrameStats {
        self.stats
    }

    /// Pixels of one frame.
    pub fn pixels(&self) -> usize {
        self.view.pixels()
    }

    pub fn format(&self) -> SampleFormat {
        self.format
    }

    /// u16 frames: counts per signal unit (1 for f32 frames).
    pub fn counts_per_unit(&self) -> f64 {
        if self.format == SampleFormat::U16 {
            self.counts_per_unit
        } else {
            1.0
        }
    }

    /// The noiseless frames `gain * T p_i` of patterns `start..end`, row-major, in signal
    /// units (parallel over patterns).
    pub fn clean_frames(&self, start: u64, end: u64) -> Vec<f64> {
        self.clean_frames_with(&self.generator, start, end)
    }

    fn clean_frames_with(&self, generator: &PatternGenerator, start: u64, end: u64) -> Vec<f64> {
        let m = self.pixels();
        let k = self.spec.pixels();
        let mut out = vec![0.0f64; (end - start) as usize * m];
        super::par_rows(&mut out, m, |first, chunk| {
            let mut grey = vec![0.0f32; k];
            let mut pattern = vec![0.0f64; k];
            for (r, frame) in chunk.chunks_exact_mut(m).enumerate() {
                generator.fill_values(start + (first + r) as u64, &mut grey);
                for (p, g) in pattern.iter_mut().zip(&grey) {
                    *p = *g as f64;
                }
                for (o, v) in frame.iter_mut().zip(self.view.render(&pattern)) {
                    *o = self.gain * v;
                }
            }
        });
        out
    }

    fn measure_stats(&self) -> FrameStats {
        let (mut sum, mut sum_sq, mut max, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
        let count = self.spec.count();
        let per = (4 << 20) / (8 * self.pixels().max(1)) as u64 + 1;
        let mut start = 0;
        while start < count {
            let end = (start + per).min(count);
            for v in self.clean_frames(start, end) {
                sum += v;
                sum_sq += v * v;
                max = max.max(v);
                n += 1;
            }
            start = end;
        }
        let n = n.max(1) as f64;
        FrameStats {
            mean: sum / n,
            rms: (sum_sq / n).sqrt(),
            max,
        }
    }

    /// The measured frames of patterns `start..end`: rendered, with noise, encoded.
    pub fn frames(&self, start: u64, end: u64) -> SampleBuf {
        self.frames_with(&self.generator, start, end)
    }

    /// [`Self::frames`] of an adaptive session: the patterns of `resolved`, the session's spec
    /// with the indices issued so far (the rows `start..end` must be among them).
    pub fn frames_for(&self, resolved: &PatternSpec, start: u64, end: u64) -> SampleBuf {
        self.frames_with(&PatternGenerator::new(resolved), start, end)
    }

    fn frames_with(&self, generator: &PatternGenerator, start: u64, end: u64) -> SampleBuf {
        let clean = self.clean_frames_with(generator, start, end);
        let m = self.pixels();
        let mut noisy = clean.clone();
        let mut tally = NoiseTally::default();
        for (r, frame) in noisy.chunks_exact_mut(m).enumerate() {
            let i = start + r as u64;
            let mut rng = SplitMix64::stream(self.model.seed, STAGE_FRAME, i);
            let drift = self.drift[i as usize];
            for x in frame.iter_mut() {
                let mut v = *x * drift;
                if let Some(alpha) = self.alpha {
                    v = rng.poisson(alpha * v) / alpha;
                }
                if let Some(sigma) = self.sigma {
                    v += sigma * rng.normal();
                }
                v += self.model.dark;
                *x = v;
            }
        }
        let out = match self.format {
            SampleFormat::U16 => SampleBuf::U16(
                noisy
                    .iter()
                    .map(|&v| {
                        let c = v * self.counts_per_unit;
                        if c >= 65_535.0 {
                            tally.saturated += 1;
                        }
                        c.clamp(0.0, 65_535.0).round() as u16
                    })
                    .collect(),
            ),
            _ => SampleBuf::F32(
                noisy
                    .iter()
                    .map(|&v| match self.adc {
                        Some((fs, step)) => {
                            if v >= fs {
                                tally.saturated += 1;
                            }
                            ((v.clamp(0.0, fs) / step).round() * step).min(fs) as f32
                        }
                        None => v as f32,
                    })
                    .collect(),
            ),
        };
        // Effective SNR in signal units, as the bucket simulator reports it.
        let unit = 1.0 / self.counts_per_unit();
        let widened = out.as_samples();
        for (j, c) in clean.iter().enumerate() {
            let v = widened.get_f64(j) * unit - self.model.dark;
            tally.signal_sq += c * c;
            tally.error_sq += (v - c).powi(2);
        }
        let mut total = self.tally.lock().expect("not poisoned");
        total.signal_sq += tally.signal_sq;
        total.error_sq += tally.error_sq;
        total.saturated += tally.saturated;
        out
    }

    /// The noise figures over the frames made so far (one "channel": the camera).
    pub fn noise_report(&self) -> NoiseReport {
        let t = *self.tally.lock().expect("not poisoned");
        let (drift_min, drift_max) = self
            .drift
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &f| {
                (lo.min(f), hi.max(f))
            });
        NoiseReport {
            channels: vec![ChannelNoise {
                mean_signal: self.stats.mean,
                photons_per_unit: self.alpha,
                read_sigma: self.sigma,
                full_scale: match self.format {
                    SampleFormat::U16 => Some(65_535.0 / self.counts_per_unit),
                    _ => self.adc.map(|(fs, _)| fs),
                },
                saturated: t.saturated,
                effective_snr_db: if t.error_sq > 0.0 {
                    10.0 * (t.signal_sq / t.error_sq).log10()
                } else {
                    f64::INFINITY
                },
            }],
            drift_min: if self.drift.is_empty() {
                1.0
            } else {
                drift_min
            },
            drift_max: if self.drift.is_empty() {
                1.0
            } else {
                drift_max
            },
        }
    }

    /// The ground truth the session can carry: `T` (`m x k` row-major, times `gain`, in the
    /// frames' units: counts for u16) when `m k` is at most `limit` values, else `None`.
    pub fn ground_truth(&self, limit: usize) -> Option<Vec<f32>> {
        let (m, k) = (self.pixels(), self.spec.pixels());
        if m.checked_mul(k)? > limit {
            return None;
        }
        let scale = self.gain * self.counts_per_unit();
        Some(
            self.view
                .dense()
                .into_iter()
                .map(|v| (v as f64 * scale) as f32)
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use helmholtz_proto::patterns::{Family, HadamardOrdering};

    fn spec(w: u32, h: u32, count: u64) -> PatternSpec {
        PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::Sequency,
            },
            w,
            h,
            count,
            0,
        )
        .unwrap()
    }

    #[test]
    fn noiseless_frames_are_the_rendered_patterns() {
        let s = spec(16, 16, 40);
        let scene = Relief::demo(16, 16, 5);
        let camera = Camera::tilted(12, 10, 20.0);
        let view = scene.view(&camera);
        let generator = PatternGenerator::new(&s);
        for format in [SampleFormat::F32, SampleFormat::U16] {
            let sim = FrameSimulator::new(&scene, camera, &s, 1.0, format, &NoiseModel::default())
                .unwrap();
            assert_eq!(sim.pixels(), 120);
            let clean = sim.clean_frames(3, 9);
            let mut grey = vec![0.0f32; 256];
            for (r, frame) in clean.chunks_exact(120).enumerate() {
                generator.fill_values(3 + r as u64, &mut grey);
                let p: Vec<f64> = grey.iter().map(|&g| g as f64).collect();
                assert_eq!(frame, view.render(&p).as_slice(), "frame {}", 3 + r);
            }
            let frames = sim.frames(3, 9);
            match (&frames, format) {
                (SampleBuf::F32(v), SampleFormat::F32) => {
                    // Noiseless f32 frames: the rendered values, rounded to f32.
                    for (a, b) in v.iter().zip(&clean) {
                        assert_eq!(*a, *b as f32);
                    }
                }
                (SampleBuf::U16(v), SampleFormat::U16) => {
                    let cpu = sim.counts_per_unit();
                    assert!((cpu * sim.stats().max - U16_FULL_WELL_TARGET).abs() < 1e-6);
                    for (a, b) in v.iter().zip(&clean) {
                        assert_eq!(*a, (b * cpu).round() as u16);
                    }
                    // The brightest pixel of all frames is near 60000 counts.
                    let all = sim.frames(0, 40);
                    let SampleBuf::U16(all) = all else {
                        unreachable!()
                    };
                    assert_eq!(*all.iter().max().unwrap(), 60_000);
                }
                _ => panic!("wrong buffer for {format:?}"),
            }
        }
    }

    #[test]
    fn frame_noise_has_the_requested_snr_and_is_batch_independent() {
        let s = spec(16, 16, 64);
        let scene = Relief::demo(16, 16, 2);
        let model = NoiseModel {
            snr_db: Some(20.0),
            seed: 9,
            ..NoiseModel::default()
        };
        let sim = FrameSimulator::new(
            &scene,
            Camera::tilted(8, 8, 0.0),
            &s,
            2.0,
            SampleFormat::F32,
            &model,
        )
        .unwrap();
        let whole = sim.frames(0, 64);
        let halves = [sim.frames(0, 30), sim.frames(30, 64)];
        let joined: Vec<f32> = halves
            .iter()
            .flat_map(|h| match h {
                SampleBuf::F32(v) => v.clone(),
                _ => unreachable!(),
            })
            .collect();
        assert_eq!(whole, SampleBuf::F32(joined));
        // Read noise alone at 20 dB: the effective SNR over the run is about 20 dB.
        let sim = FrameSimulator::new(
            &scene,
            Camera::tilted(8, 8, 0.0),
            &s,
            2.0,
            SampleFormat::F32,
            &model,
        )
        .unwrap();
        sim.frames(0, 64);
        let snr = sim.noise_report().channels[0].effective_snr_db;
        assert!((snr - 20.0).abs() < 0.3, "effective SNR {snr}");
        // And it changes the frames.
        let clean = sim.clean_frames(0, 1);
        let SampleBuf::F32(noisy) = sim.frames(0, 1) else {
            unreachable!()
        };
        assert!(
            noisy
                .iter()
                .zip(&clean)
                .any(|(a, b)| (*a as f64 - b).abs() > 1e-3)
        );
    }

    #[test]
    fn detectors_are_placed_as_declared() {
        let names: Vec<String> = ["n", "e", "s", "w"].iter().map(|s| s.to_string()).collect();
        let plan = detector_plan(Some(&names), 45.0, false).unwrap();
        assert_eq!(plan.names, names);
        let h = 0.5f64.sqrt();
        let want = [[0.0, -h, h], [h, 0.0, h], [0.0, h, h], [-h, 0.0, h]];
        for (got, want) in plan.directions.iter().zip(want) {
            for a in 0..3 {
                assert!((got[a] - want[a]).abs() < 1e-12, "{got:?} vs {want:?}");
            }
        }
        // Other names: spread evenly from +x, at the given elevation.
        let names: Vec<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
        let plan = detector_plan(Some(&names), 30.0, false).unwrap();
        for (i, d) in plan.directions.iter().enumerate() {
            let want = crate::scene::direction(120.0 * i as f64, 30.0);
            for a in 0..3 {
                assert!((d[a] - want[a]).abs() < 1e-12, "{d:?} vs {want:?}");
            }
            assert!((d[2] - 0.5).abs() < 1e-12);
        }
        // One detector at the projector by default.
        let plan = detector_plan(None, 45.0, false).unwrap();
        assert_eq!(
            (plan.names.as_slice(), plan.directions.as_slice()),
            (&["bucket".to_string()][..], &[[0.0, 0.0, 1.0]][..])
        );
        assert!(detector_plan(Some(&names), 0.0, false).is_err());
        assert!(detector_plan(Some(&["n".into(), "n".into()]), 45.0, false).is_err());
    }

    #[test]
    fn colour_channels_use_the_colour_filtered_transports() {
        let plan = detector_plan(None, 45.0, true).unwrap();
        assert_eq!(plan.names, ["r", "g", "b"]);
        assert!(plan.directions.iter().all(|d| *d == [0.0, 0.0, 1.0]));
        let scene = Relief::demo(16, 16, 4);
        let t = plan_transports(&scene, &plan, 1.0);
        for (c, got) in t.iter().enumerate() {
            let want: Vec<f32> = scene
                .detector_transport_colour([0.0, 0.0, 1.0], c)
                .into_iter()
                .map(|v| v as f32)
                .collect();
            assert_eq!(*got, want);
        }
        assert_ne!(t[0], t[2], "the filters see different albedos");
        let two = detector_plan(Some(&["n".into(), "e".into()]), 45.0, true).unwrap();
        assert_eq!(two.names, ["n-r", "n-g", "n-b", "e-r", "e-g", "e-b"]);
        assert_eq!(
            two.colours,
            [Some(0), Some(1), Some(2), Some(0), Some(1), Some(2)]
        );
        // Grey detectors: the grey transport, times the gain.
        let grey = plan_transports(&scene, &detector_plan(None, 45.0, false).unwrap(), 2.0);
        let want: Vec<f32> = scene
            .detector_transport([0.0, 0.0, 1.0])
            .into_iter()
            .map(|v| (v * 2.0) as f32)
            .collect();
        assert_eq!(grey[0], want);
    }

    #[test]
    fn camera_ground_truth_is_dense_t_within_the_limit() {
        let s = spec(8, 8, 16);
        let scene = Relief::demo(8, 8, 1);
        let camera = Camera::tilted(4, 4, 10.0);
        let sim = FrameSimulator::new(
            &scene,
            camera,
            &s,
            1.0,
            SampleFormat::F32,
            &NoiseModel::default(),
        )
        .unwrap();
        assert_eq!(sim.ground_truth(16 * 64), Some(scene.view(&camera).dense()));
        assert_eq!(sim.ground_truth(16 * 64 - 1), None);
        assert_eq!(parse_size("64x48").unwrap(), (64, 48));
        assert!(parse_size("64").is_err() && parse_size("ax4").is_err());
    }
}
