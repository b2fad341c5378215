//! Virtual lights on a camera's pixels for relighting `p' = T^T c'`: the presets a user names
//! (the whole camera, a disc, a band of columns), drawn on the `width x height` camera grid.
//! Pixel `j` sits at `(j % width + 1/2, j / width + 1/2)`.

/// A preset light on the camera pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Light {
    /// Every camera pixel at weight 1 (the dual image seen by the whole camera).
    Full,
    /// Pixels whose centre lies within `radius` of `(x, y)` (camera pixel units).
    Disc { x: f64, y: f64, radius: f64 },
    /// Columns `x0 <= column < x1`.
    Stripe { x0: f64, x1: f64 },
}

/// Why a light cannot be drawn; `field` names the offending input (`light.radius`, ...).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct LightError {
    pub field: &'static str,
    pub message: String,
}

impl Light {
    /// The light's weights on a `width x height` camera (row-major), 0 or 1. Refuses a light that
    /// lights no pixel or whose parameters are degenerate.
    pub fn weights(&self, width: usize, height: usize) -> Result<Vec<f32>, LightError> {
        let m = width * height;
        let pixel = |j: usize| {
            (
                (j % width.max(1)) as f64 + 0.5,
                (j / width.max(1)) as f64 + 0.5,
            )
        };
        let out: Vec<f32> = match *self {
            Light::Full => vec![1.0; m],
            Light::Disc { x, y, radius } => {
                if radius.is_nan() || radius <= 0.0 {
                    return Err(LightError {
                        field: "light.radius",
                        message: format!("must be positive, got {radius}"),
                    });
                }
                (0..m)
                    .map(|j| {
                        let (px, py) = pixel(j);
                        f32::from((px - x).powi(2) + (py - y).powi(2) <= radius * radius)
                    })
                    .collect()
            }
            Light::Stripe { x0, x1 } => {
                if x0.is_nan() || x1.is_nan() || x1 <= x0 {
                    return Err(LightError {
                        field: "light.x1",
                        message: format!("must exceed x0 ({x0}), got {x1}"),
                    });
                }
                (0..m)
                    .map(|j| {
                        let c = (j % width.max(1)) as f64;
                        f32::from(c >= x0 && c < x1)
                    })
                    .collect()
            }
        };
        if out.iter().all(|&v| v == 0.0) {
            let message = match *self {
                Light::Disc { x, y, radius } => format!(
                    "the disc at ({x}, {y}) of radius {radius} covers no pixel of the {width}x{height} camera"
                ),
                Light::Stripe { x0, x1 } => {
                    format!("columns {x0} <= x < {x1} miss the {width}-column camera")
                }
                Light::Full => "the camera has no pixels".to_string(),
            };
            return Err(LightError {
                field: "light",
                message,
            });
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_light_the_pixels_they_name() {
        // 4 x 3 camera.
        assert_eq!(Light::Full.weights(4, 3).unwrap(), vec![1.0; 12]);
        // A disc of radius 0.6 around pixel (1, 1)'s centre lights it alone.
        let disc = Light::Disc {
            x: 1.5,
            y: 1.5,
            radius: 0.6,
        };
        let w = disc.weights(4, 3).unwrap();
        assert_eq!(w.iter().sum::<f32>(), 1.0);
        assert_eq!(w[4 + 1], 1.0);
        // Columns 1 and 2 of every row.
        let w = Light::Stripe { x0: 1.0, x1: 3.0 }.weights(4, 3).unwrap();
        assert_eq!(
            w,
            [0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0]
        );
    }

    #[test]
    fn degenerate_or_empty_lights_name_their_field() {
        let e = Light::Disc {
            x: 1.0,
            y: 1.0,
            radius: 0.0,
        }
        .weights(4, 3)
        .unwrap_err();
        assert_eq!(e.field, "light.radius");
        let e = Light::Stripe { x0: 2.0, x1: 2.0 }
            .weights(4, 3)
            .unwrap_err();
        assert_eq!(e.field, "light.x1");
        let e = Light::Disc {
            x: 100.0,
            y: 100.0,
            radius: 1.0,
        }
        .weights(4, 3)
        .unwrap_err();
        assert_eq!(e.field, "light");
        assert!(e.message.contains("covers no pixel"), "{e}");
        let e = Light::Stripe { x0: 10.0, x1: 20.0 }
            .weights(4, 3)
            .unwrap_err();
        assert!(e.message.contains("miss the 4-column camera"), "{e}");
    }
}
