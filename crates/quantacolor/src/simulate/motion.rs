//! Camera and object motion of a simulated burst (paper §6.1 handheld bursts, Fig. 10 circular
//! motion).
//!
//! Every model is stored as per-frame parameters of one rigid map per frame: a reference-frame
//! position `p = (y, x)` (sensor pixels) lands in frame `t` at
//!
//! ```text
//! forward(t, p) = R(θ_t) · (p − c) + c + (dy_t, dx_t)
//! ```
//!
//! with `c` the sensor centre. The parameters are exactly zero at the reference frame, so the map
//! is the identity there. The optional object layer (a textured disc) moves over the static
//! background by its own translation `o_t` on top of the camera map. [`Motion`] is `serde`
//! serialisable and is written into a capture as `motion.toml`.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Which motion to simulate, with its parameters. `FromStr` accepts the command-line names
/// (`static`, `pan`, `handheld`, `fast-handheld`, `circular`, `object`) with default parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "model", rename_all = "kebab-case")]
pub enum MotionConfig {
    /// No motion.
    #[default]
    Static,
    /// Constant velocity `(dy, dx)` in pixels per frame.
    Pan {
        #[serde(default = "default_pan_velocity")]
        velocity: [f64; 2],
    },
    /// Smooth random translation plus a small rotation: each of dy, dx, θ is a sum of three
    /// low-frequency sinusoids with random phases, scaled so that its largest deviation from the
    /// reference frame equals the given peak.
    Handheld {
        /// Peak translation from the reference frame, pixels.
        #[serde(default = "default_handheld_amplitude")]
        amplitude_px: f64,
        /// Peak rotation from the reference frame, degrees.
        #[serde(default = "default_handheld_rotation")]
        rotation_deg: f64,
        /// Cycles of the slowest sinusoid over the whole burst.
        #[serde(default = "default_handheld_cycles")]
        cycles: f64,
    },
    /// As `Handheld` with larger amplitude and frequency (shaky hands, fast bursts).
    FastHandheld {
        #[serde(default = "default_fast_amplitude")]
        amplitude_px: f64,
        #[serde(default = "default_fast_rotation")]
        rotation_deg: f64,
        #[serde(default = "default_fast_cycles")]
        cycles: f64,
    },
    /// Translation along a circle of `radius_px` passing through the reference position, with
    /// `revolutions` turns over the burst (paper Fig. 10).
    Circular {
        #[serde(default = "default_circle_radius")]
        radius_px: f64,
        #[serde(default = "default_revolutions")]
        revolutions: f64,
    },
    /// Static camera; a textured disc of radius `radius_frac · min(H, W)`, centred on the sensor at
    /// the reference frame, moves at `velocity` (pixels per frame) over the background.
    Object {
        #[serde(default = "default_object_radius")]
        radius_frac: f64,
        #[serde(default = "default_object_velocity")]
        velocity: [f64; 2],
    },
}

fn default_pan_velocity() -> [f64; 2] {
    [0.0, 0.02]
}
fn default_handheld_amplitude() -> f64 {
    4.0
}
fn default_handheld_rotation() -> f64 {
    0.5
}
fn default_handheld_cycles() -> f64 {
    0.75
}
fn default_fast_amplitude() -> f64 {
    16.0
}
fn default_fast_rotation() -> f64 {
    1.5
}
fn default_fast_cycles() -> f64 {
    3.0
}
fn default_circle_radius() -> f64 {
    8.0
}
fn default_revolutions() -> f64 {
    1.0
}
fn default_object_radius() -> f64 {
    0.2
}
fn default_object_velocity() -> [f64; 2] {
    [0.0, 0.05]
}

impl std::str::FromStr for MotionConfig {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "static" => MotionConfig::Static,
            "pan" => MotionConfig::Pan {
                velocity: default_pan_velocity(),
            },
            "handheld" => MotionConfig::Handheld {
                amplitude_px: default_handheld_amplitude(),
                rotation_deg: default_handheld_rotation(),
                cycles: default_handheld_cycles(),
            },
            "fast-handheld" => MotionConfig::FastHandheld {
                amplitude_px: default_fast_amplitude(),
                rotation_deg: default_fast_rotation(),
                cycles: default_fast_cycles(),
            },
            "circular" => MotionConfig::Circular {
                radius_px: default_circle_radius(),
                revolutions: default_revolutions(),
            },
            "object" => MotionConfig::Object {
                radius_frac: default_object_radius(),
                velocity: default_object_velocity(),
            },
            other => {
                return Err(Error::invalid(format!(
                    "unknown motion '{other}' (expected static, pan, handheld, fast-handheld, \
                     circular or object)"
                )))
            }
        })
    }
}

/// A moving object: a disc of `radius` pixels centred at `center` (y, x) in the reference frame,
/// translated by `(dy[t], dx[t])` in frame `t` (before the camera map).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectTrack {
    pub center: [f64; 2],
    pub radius: f64,
    pub dy: Vec<f64>,
    pub dx: Vec<f64>,
}

/// Per-frame motion of a burst; see the module documentation for the map it describes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Motion {
    /// The model that generated it (`static`, `pan`, ...).
    pub model: String,
    pub frames: usize,
    pub reference_frame: usize,
    /// Rotation centre (y, x), sensor pixels.
    pub center: [f64; 2],
    /// Camera translation per frame, pixels.
    pub dy: Vec<f64>,
    pub dx: Vec<f64>,
    /// Camera rotation per frame, radians (positive turns +x towards +y).
    pub theta_rad: Vec<f64>,
    /// The moving object, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object: Option<ObjectTrack>,
}

/// Errors unless the burst has a frame and `reference_frame` is one of them.
fn check_frames(frames: usize, reference_frame: usize) -> Result<()> {
    if frames == 0 {
        return Err(Error::invalid("motion needs at least one frame"));
    }
    if reference_frame >= frames {
        return Err(Error::invalid(format!(
            "reference frame {reference_frame} is outside the burst of {frames} frames"
        )));
    }
    Ok(())
}

/// The handheld models' `(dy, dx, θ)` per frame: three [`smooth_random`] signals drawn in that
/// order from the seeded generator, each zero at `reference_frame` and scaled to its peak
/// (`amplitude_px` pixels for dy and dx, `rotation_deg` degrees for θ, in radians).
fn handheld_signals(
    frames: usize,
    reference_frame: usize,
    amplitude_px: f64,
    rotation_deg: f64,
    cycles: f64,
    seed: u64,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6d6f_7469_6f6e_0001);
    let mut dy = smooth_random(frames, cycles, &mut rng);
    let mut dx = smooth_random(frames, cycles, &mut rng);
    let mut th = smooth_random(frames, cycles, &mut rng);
    normalise_to_peak(&mut dy, reference_frame, amplitude_px.abs());
    normalise_to_peak(&mut dx, reference_frame, amplitude_px.abs());
    normalise_to_peak(&mut th, reference_frame, rotation_deg.abs().to_radians());
    (dy, dx, th)
}

/// Scales `signal − signal[reference]` so that its largest magnitude is `peak`.
fn normalise_to_peak(signal: &mut [f64], reference: usize, peak: f64) {
    let r = signal[reference];
    signal.iter_mut().for_each(|v| *v -= r);
    let max = signal.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let gain = if max > 0.0 { peak / max } else { 0.0 };
    signal.iter_mut().for_each(|v| *v *= gain);
    signal[reference] = 0.0;
}

/// Sum of three sinusoids with random phases; the k-th has frequency `cycles · (k + 1) · u`
/// (u in [0.7, 1.3]) cycles per burst and amplitude 1/(k + 1).
fn smooth_random(frames: usize, cycles: f64, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let terms: Vec<(f64, f64, f64)> = (0..3)
        .map(|k| {
            let f = cycles * (k as f64 + 1.0) * rng.gen_range(0.7..1.3);
            let phase = rng.gen_range(0.0..2.0 * PI);
            (f, phase, 1.0 / (k as f64 + 1.0))
        })
        .collect();
    (0..frames)
        .map(|t| {
            let s = t as f64 / frames as f64;
            terms
                .iter()
                .map(|&(f, ph, a)| a * (2.0 * PI * f * s + ph).sin())
                .sum()
        })
        .collect()
}

impl Motion {
    /// Generates the motion of `frames` frames of a `height` x `width` sensor, identity at
    /// `reference_frame`; `seed` drives the random models.
    pub fn generate(
        config: &MotionConfig,
        frames: usize,
        reference_frame: usize,
        height: usize,
        width: usize,
        seed: u64,
    ) -> Result<Motion> {
        check_frames(frames, reference_frame)?;
        let zeros = vec![0.0; frames];
        let rel = |t: usize| t as f64 - reference_frame as f64;
        let mut motion = Motion {
            model: String::new(),
            frames,
            reference_frame,
            center: [(height as f64 - 1.0) / 2.0, (width as f64 - 1.0) / 2.0],
            dy: zeros.clone(),
            dx: zeros.clone(),
            theta_rad: zeros.clone(),
            object: None,
        };
        let finite = |v: f64, what: &str| -> Result<()> {
            if v.is_finite() {
                Ok(())
            } else {
                Err(Error::invalid(format!("motion {what} must be finite")))
            }
        };
        match *config {
            MotionConfig::Static => motion.model = "static".into(),
            MotionConfig::Pan { velocity } => {
                finite(velocity[0] + velocity[1], "velocity")?;
                motion.model = "pan".into();
                motion.dy = (0..frames).map(|t| velocity[0] * rel(t)).collect();
                motion.dx = (0..frames).map(|t| velocity[1] * rel(t)).collect();
            }
            MotionConfig::Handheld {
                amplitude_px,
                rotation_deg,
                cycles,
            }
            | MotionConfig::FastHandheld {
                amplitude_px,
                rotation_deg,
                cycles,
            } => {
                finite(amplitude_px + rotation_deg + cycles, "amplitude")?;
                if cycles <= 0.0 {
                    return Err(Error::invalid("handheld cycles must be positive"));
                }
                motion.model = if matches!(config, MotionConfig::Handheld { .. }) {
                    "handheld".into()
                } else {
                    "fast-handheld".into()
                };
                (motion.dy, motion.dx, motion.theta_rad) = handheld_signals(
                    frames,
                    reference_frame,
                    amplitude_px,
                    rotation_deg,
                    cycles,
                    seed,
                );
            }
            MotionConfig::Circular {
                radius_px,
                revolutions,
            } => {
                finite(radius_px + revolutions, "radius")?;
                motion.model = "circular".into();
                let omega = 2.0 * PI * revolutions / frames as f64;
                motion.dy = (0..frames)
                    .map(|t| radius_px * (omega * rel(t)).sin())
                    .collect();
                motion.dx = (0..frames)
                    .map(|t| radius_px * ((omega * rel(t)).cos() - 1.0))
                    .collect();
            }
            MotionConfig::Object {
                radius_frac,
                velocity,
            } => {
                finite(radius_frac + velocity[0] + velocity[1], "object parameters")?;
                if !(radius_frac > 0.0 && radius_frac <= 0.5) {
                    return Err(Error::invalid("object radius_frac must be in (0, 0.5]"));
                }
                motion.model = "object".into();
                motion.object = Some(ObjectTrack {
                    center: motion.center,
                    radius: radius_frac * height.min(width) as f64,
                    dy: (0..frames).map(|t| velocity[0] * rel(t)).collect(),
                    dx: (0..frames).map(|t| velocity[1] * rel(t)).collect(),
                });
            }
        }
        Ok(motion)
    }

    /// Camera map of frame `t`: where the reference-frame position `p = (y, x)` lands.
    pub fn forward(&self, t: usize, p: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.theta_rad[t].sin_cos();
        let (y, x) = (p[0] - self.center[0], p[1] - self.center[1]);
        [
            c * y + s * x + self.center[0] + self.dy[t],
            -s * y + c * x + self.center[1] + self.dx[t],
        ]
    }

    /// Inverse of [`Motion::forward`]: the reference-frame position seen at `q` in frame `t`.
    pub fn inverse(&self, t: usize, q: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.theta_rad[t].sin_cos();
        let (y, x) = (
            q[0] - self.center[0] - self.dy[t],
            q[1] - self.center[1] - self.dx[t],
        );
        [
            c * y - s * x + self.center[0],
            s * y + c * x + self.center[1],
        ]
    }

    /// The inverse camera map of frame `t` as an affine map `p = A·q + b`, returned as
    /// `([[a00, a01], [a10, a11]], [b0, b1])`.
    pub fn inverse_affine(&self, t: usize) -> ([[f64; 2]; 2], [f64; 2]) {
        let b = self.inverse(t, [0.0, 0.0]);
        let e0 = self.inverse(t, [1.0, 0.0]);
        let e1 = self.inverse(t, [0.0, 1.0]);
        (
            [[e0[0] - b[0], e1[0] - b[0]], [e0[1] - b[1], e1[1] - b[1]]],
            b,
        )
    }

    /// Whether the reference-frame position `p` lies on the moving object (if any).
    pub fn on_object(&self, p: [f64; 2]) -> bool {
        self.object.as_ref().is_some_and(|o| {
            let (y, x) = (p[0] - o.center[0], p[1] - o.center[1]);
            y * y + x * x < o.radius * o.radius
        })
    }

    /// True motion `(dy, dx)`: the scene point at `(y, x)` in the reference frame is at
    /// `(y + dy, x + dx)` in frame `frame`. Points on the moving object follow the object.
    pub fn true_displacement(&self, frame: usize, y: f64, x: f64) -> (f64, f64) {
        let p = [y, x];
        let moved = match &self.object {
            Some(o) if self.on_object(p) => [p[0] + o.dy[frame], p[1] + o.dx[frame]],
            _ => p,
        };
        let q = self.forward(frame, moved);
        (q[0] - y, q[1] - x)
    }

    /// Dense true flow `(H, W, 2)` at fractional frame `t` (linear between the two nearest
    /// frames), in the convention of the alignment: the scene point at p in the reference
    /// frame is at p + flow(p) in frame t.
    pub fn dense_flow(&self, t: f64, height: usize, width: usize) -> ndarray::Array3<f32> {
        let last = self.frames.saturating_sub(1);
        let t = t.clamp(0.0, last as f64);
        let (f0, f1) = (t.floor() as usize, (t.ceil() as usize).min(last));
        let a = t - f0 as f64;
        let mut flow = ndarray::Array3::<f32>::zeros((height, width, 2));
        for y in 0..height {
            for x in 0..width {
                let d0 = self.true_displacement(f0, y as f64, x as f64);
                let d1 = self.true_displacement(f1, y as f64, x as f64);
                flow[[y, x, 0]] = ((1.0 - a) * d0.0 + a * d1.0) as f32;
                flow[[y, x, 1]] = ((1.0 - a) * d0.1 + a * d1.1) as f32;
            }
        }
        flow
    }

    /// Largest distance, over frames and sensor corners, between a pixel and the reference
    /// position it sees: the scene margin needed around the sensor.
    pub fn max_excursion(&self, height: usize, width: usize) -> f64 {
        let corners = [
            [0.0, 0.0],
            [0.0, width as f64 - 1.0],
            [height as f64 - 1.0, 0.0],
            [height as f64 - 1.0, width as f64 - 1.0],
        ];
        (0..self.frames)
            .flat_map(|t| corners.iter().map(move |&q| (t, q)))
            .map(|(t, q)| {
                let p = self.inverse(t, q);
                (p[0] - q[0]).abs().max((p[1] - q[1]).abs())
            })
            .fold(0.0, f64::max)
    }

    /// `motion.toml`: this description serialised as TOML.
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string(self).map_err(|e| Error::invalid(format!("cannot serialise motion: {e}")))
    }
}
