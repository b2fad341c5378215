//! The benchmark grid and its presets.

use std::str::FromStr;

use helmholtz_proto::{Family, HadamardOrdering, PatternSpec};
use helmholtz_sim::simulate::NoiseModel;
use serde::Serialize;

use super::frames_for;

/// Detector noise of a case.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Noise {
    None,
    /// Gaussian read noise at 30 dB SNR (rms signal / sigma).
    Snr30,
    /// Poisson shot noise, 1e4 photons per pattern on average.
    Poisson,
}

impl Noise {
    pub fn model(self) -> NoiseModel {
        match self {
            Noise::None => NoiseModel::default(),
            Noise::Snr30 => NoiseModel {
                snr_db: Some(30.0),
                seed: 17,
                ..NoiseModel::default()
            },
            Noise::Poisson => NoiseModel {
                photons: Some(1e4),
                seed: 17,
                ..NoiseModel::default()
            },
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Noise::None => "none",
            Noise::Snr30 => "30 dB",
            Noise::Poisson => "Poisson 1e4",
        }
    }
}

/// One reconstruction to measure.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Case {
    pub scene: String,
    pub size: (u32, u32),
    /// Measurements / pixels (Hadamard: pairs / pixels).
    pub ratio: f64,
    /// "bernoulli" or "hadamard" (Russian-doll ordering).
    pub family: String,
    pub noise: Noise,
    pub method: String,
}

impl Case {
    pub fn family(&self) -> Family {
        match self.family.as_str() {
            "hadamard" => Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            _ => Family::Bernoulli { fill: 0.5 },
        }
    }

    pub fn spec(&self) -> PatternSpec {
        let family = self.family();
        let k = (self.size.0 * self.size.1) as usize;
        let count = frames_for(&family, k, self.ratio);
        PatternSpec::new(family, self.size.0, self.size.1, count, 1).expect("grid specs are valid")
    }

    /// Cases with the same key share one simulated acquisition.
    pub fn acquisition_key(&self) -> String {
        format!(
            "{}|{}x{}|{}|{}|{:?}",
            self.scene, self.size.0, self.size.1, self.ratio, self.family, self.noise
        )
    }

    pub fn label(&self) -> String {
        format!(
            "{} {}x{} {} {:.1}% {} {}",
            self.scene,
            self.size.0,
            self.size.1,
            self.family,
            self.ratio * 100.0,
            self.noise.name(),
            self.method
        )
    }
}

/// Methods that estimate t only up to scale and offset (scored after an affine fit).
pub fn scale_free(method: &str) -> bool {
    matches!(method, "gi" | "dgi" | "ngi")
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Preset {
    Smoke,
    Targets,
    Full,
}

impl FromStr for Preset {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "smoke" => Ok(Preset::Smoke),
            "targets" => Ok(Preset::Targets),
            "full" => Ok(Preset::Full),
            other => Err(format!("unknown preset {other:?}")),
        }
    }
}

/// Every method the service offers, cheapest first.
pub const METHODS: &[&str] = &[
    "gi",
    "dgi",
    "ngi",
    "direct",
    "zero_filled",
    "levels",
    "lsq",
    "cs",
    "tv",
    "auto",
];

/// Iterative methods on Bernoulli patterns cost about `rows x pixels x 1.5e-10 s` per iteration
/// here (a few hundred iterations per case, several paths for `auto`); above this product
/// (128 x 128 at 100 %, 256 x 256 from 5 %) one case takes minutes, so the full grid leaves them
/// out. The correlators and every Hadamard method run at every size.
pub const MAX_ITERATIVE_BERNOULLI_WORK: f64 = 1.1e8;

fn applicable(family: &str, size: u32, ratio: f64, method: &str) -> bool {
    let k = (size as f64) * (size as f64);
    match method {
        // The exact inverse needs the complete set.
        "direct" => family == "hadamard" && ratio >= 1.0,
        "zero_filled" | "levels" => family == "hadamard",
        "lsq" | "cs" | "tv" | "auto" if family == "bernoulli" => {
            ratio * k * k <= MAX_ITERATIVE_BERNOULLI_WORK
        }
        _ => true,
    }
}

/// Simulating a Bernoulli acquisition costs `rows x pixels` pattern-pixel products (seconds at
/// 256 x 256 and 25 % or more, per scene and noise); above this product the full grid leaves the
/// acquisition out altogether (the 256 x 256 Bernoulli cases keep 1 %, the source paper's regime).
pub const MAX_BERNOULLI_SIMULATION: f64 = 1e9;

fn grid(
    scenes: &[&str],
    sizes: &[u32],
    ratios: &[f64],
    families: &[&str],
    noises: &[Noise],
) -> Vec<Case> {
    let mut out = Vec::new();
    for &scene in scenes {
        for &n in sizes {
            for &family in families {
                for &ratio in ratios {
                    let k = n as f64 * n as f64;
                    if family == "bernoulli" && ratio * k * k > MAX_BERNOULLI_SIMULATION {
                        continue;
                    }
                    for &noise in noises {
                        for &method in METHODS {
                            if applicable(family, n, ratio, method) {
                                out.push(Case {
                                    scene: scene.into(),
                                    size: (n, n),
                                    ratio,
                                    family: family.into(),
                                    noise,
                                    method: method.into(),
                                });
                            }
                        }
                    }
                }
            }
        }
    }
    out
}

impl Preset {
    pub fn cases(self) -> Vec<Case> {
        match self {
            Preset::Smoke => grid(
                &["shapes"],
                &[32],
                &[0.1, 1.0],
                &["bernoulli", "hadamard"],
                &[Noise::None],
            ),
            Preset::Targets => {
                let mut cases = grid(
                    &["camera"],
                    &[128],
                    &[0.1],
                    &["bernoulli", "hadamard"],
                    &[Noise::None],
                );
                cases.extend(grid(
                    &["camera"],
                    &[256],
                    &[0.1],
                    &["hadamard"],
                    &[Noise::None],
                ));
                cases.extend(grid(
                    &["shapes"],
                    &[256],
                    &[1000.0 / 65536.0],
                    &["bernoulli"],
                    &[Noise::None],
                ));
                cases
            }
            Preset::Full => grid(
                &["camera", "shapes", "usaf"],
                &[32, 64, 128, 256],
                &[0.01, 0.05, 0.1, 0.25, 1.0],
                &["bernoulli", "hadamard"],
                &[Noise::None, Noise::Snr30, Noise::Poisson],
            ),
        }
    }
}
