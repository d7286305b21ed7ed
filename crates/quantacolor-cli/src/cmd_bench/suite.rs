//! The quality suite's captures: real photographs and OpenEXR scenes simulated as colour-SPAD
//! (paper Table 1) or Bayer captures, in a tuning set and a held-out validation set.

#![forbid(unsafe_code)]

use super::SuiteSet;
use anyhow::Result;
use quantacolor::cfa::{self, Pattern};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulatedCapture, SimulationConfig,
};
use std::fmt::Write as _;
use std::path::Path;

/// The colour filter array of a suite capture.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum CfaKind {
    /// The real colour-SPAD CFA (its top-left crop for smaller sensors).
    ColorSpad,
    /// RGGB Bayer.
    Bayer,
}

/// One capture of the quality suite.
pub(super) struct Case {
    pub(super) set: SuiteSet,
    pub(super) scene: &'static str,
    /// Short motion name for the table.
    pub(super) motion_name: &'static str,
    pub(super) motion: MotionConfig,
    pub(super) frames: usize,
    pub(super) flux: FluxSpec,
    pub(super) cfa: CfaKind,
    /// Sensor (height, width).
    pub(super) size: (usize, usize),
    /// Pixel supersampling of the simulator: 2 for the 2x-detail captures (scored at scale 2
    /// as well).
    pub(super) supersampling: usize,
    pub(super) seed: u64,
}

impl Case {
    /// Table label.
    pub(super) fn label(&self) -> String {
        let scene = self.scene.rsplit_once('.').map_or(self.scene, |(a, _)| a);
        let flux = match self.flux {
            FluxSpec::Mean { flux } => format!("{flux}"),
            FluxSpec::Percentile { percentile, peak } => format!("HDR p{percentile}={peak}"),
        };
        let mut label = format!(
            "{scene} / {} / {} fr / {flux}",
            self.motion_name, self.frames
        );
        if self.cfa == CfaKind::Bayer {
            label.push_str(" / Bayer");
        }
        if self.supersampling > 1 {
            let (h, w) = self.size;
            write!(label, " / {}x detail {w}x{h}", self.supersampling).ok();
        }
        label
    }

    /// Id for `--only` and the progress lines.
    pub(super) fn id(&self) -> String {
        let set = if self.set == SuiteSet::Tuning {
            "t"
        } else {
            "v"
        };
        let scene = self.scene.rsplit_once('.').map_or(self.scene, |(a, _)| a);
        let motion = self.motion_name.replace(' ', "-");
        let mut id = format!("{set}-{scene}-{motion}-{}", self.frames);
        if self.cfa == CfaKind::Bayer {
            id.push_str("-bayer");
        }
        match self.flux {
            FluxSpec::Mean { flux } if flux < 0.1 => id.push_str("-dark"),
            FluxSpec::Percentile { peak, .. } if peak > 1.0 => id.push_str("-bright"),
            _ => {}
        }
        if self.supersampling > 1 {
            id.push_str("-2x");
        }
        id
    }
}

/// The quality suite. Tuning set: kodim02, kodim07, kodim15, ScanLines_StillLife, seeds 200+;
/// validation set: kodim04, kodim12, kodim22, ScanLines_Cannon, MultiResolution_Bonita, seeds
/// 300+. Each set has one capture of every kind (handheld, pan or static, moving object, fast
/// handheld, long HDR handheld, dark, Bayer, 2x detail, bright HDR handheld, and shaky
/// handheld: a photograph, a bright HDR scene and a Bayer capture).
pub(super) fn suite() -> Vec<Case> {
    let mut cases = tuning_cases();
    cases.extend(validation_cases());
    let (mut t, mut v) = (200, 300);
    for c in &mut cases {
        let next = if c.set == SuiteSet::Tuning {
            &mut t
        } else {
            &mut v
        };
        c.seed = *next;
        *next += 1;
    }
    cases
}

/// Mean flux of most captures, photons per pixel per frame.
const MEAN: FluxSpec = FluxSpec::Mean { flux: 0.1 };
/// Flux of the dark captures.
const DARK: FluxSpec = FluxSpec::Mean { flux: 0.02 };
/// HDR scenes: the median W pixel at 0.1.
const HDR: FluxSpec = FluxSpec::Percentile {
    percentile: 50.0,
    peak: 0.1,
};
/// Bright HDR scenes (issue's high-light case): the 99th-percentile W pixel at 4 detections
/// per frame, where the photons allow a merge as sharp as the pixel itself.
const BRIGHT: FluxSpec = FluxSpec::Percentile {
    percentile: 99.0,
    peak: 4.0,
};
/// Sensor (height, width) of the 1x captures.
const FULL: (usize, usize) = (254, 496);
/// 2x-detail sensor: ~2.9 photograph pixels per sensor pixel.
const SMALL: (usize, usize) = (127, 248);

fn handheld() -> MotionConfig {
    "handheld".parse::<MotionConfig>().expect("known motion")
}

/// Hand shake of a few pixels per block (12 px, 2°, 3 cycles over the capture): each block's
/// frames smear its grey image, the case of `[burst.merge] sharpen_blocks_px` (issue 45).
fn shaky_handheld() -> MotionConfig {
    MotionConfig::Handheld {
        amplitude_px: 12.0,
        rotation_deg: 2.0,
        cycles: 3.0,
    }
}

fn fast_handheld() -> MotionConfig {
    MotionConfig::FastHandheld {
        amplitude_px: 40.0,
        rotation_deg: 2.0,
        cycles: 3.0,
    }
}

/// A full-size colour-SPAD capture at 1x detail (seed set by [`suite`]).
fn case(
    set: SuiteSet,
    scene: &'static str,
    motion_name: &'static str,
    motion: MotionConfig,
    frames: usize,
    flux: FluxSpec,
) -> Case {
    Case {
        set,
        scene,
        motion_name,
        motion,
        frames,
        flux,
        cfa: CfaKind::ColorSpad,
        size: FULL,
        supersampling: 1,
        seed: 0,
    }
}

/// The tuning set, in report order.
fn tuning_cases() -> Vec<Case> {
    use SuiteSet::Tuning as T;
    vec![
        case(T, "kodim02.png", "handheld", handheld(), 512, MEAN),
        case(T, "kodim07.png", "static", MotionConfig::Static, 512, MEAN),
        case(
            T,
            "kodim15.png",
            "object",
            "object".parse().expect("known"),
            512,
            MEAN,
        ),
        case(
            T,
            "kodim15.png",
            "fast handheld",
            fast_handheld(),
            512,
            MEAN,
        ),
        case(
            T,
            "ScanLines_StillLife.exr",
            "handheld",
            handheld(),
            2000,
            HDR,
        ),
        case(T, "kodim02.png", "handheld", handheld(), 2000, DARK),
        Case {
            cfa: CfaKind::Bayer,
            ..case(T, "kodim07.png", "handheld", handheld(), 512, MEAN)
        },
        Case {
            size: SMALL,
            supersampling: 2,
            ..case(T, "kodim15.png", "handheld", handheld(), 2000, MEAN)
        },
        case(
            T,
            "ScanLines_StillLife.exr",
            "handheld",
            handheld(),
            2000,
            BRIGHT,
        ),
        case(
            T,
            "kodim07.png",
            "shaky handheld",
            shaky_handheld(),
            2000,
            MEAN,
        ),
        case(
            T,
            "ScanLines_StillLife.exr",
            "shaky handheld",
            shaky_handheld(),
            2000,
            BRIGHT,
        ),
        Case {
            cfa: CfaKind::Bayer,
            ..case(
                T,
                "kodim07.png",
                "shaky handheld",
                shaky_handheld(),
                2000,
                MEAN,
            )
        },
    ]
}

/// The validation set, in report order.
fn validation_cases() -> Vec<Case> {
    use SuiteSet::Validation as V;
    vec![
        case(
            V,
            "kodim04.png",
            "pan",
            "pan".parse().expect("known"),
            512,
            MEAN,
        ),
        case(
            V,
            "kodim12.png",
            "object",
            "object".parse().expect("known"),
            512,
            MEAN,
        ),
        case(
            V,
            "kodim22.png",
            "fast handheld",
            fast_handheld(),
            512,
            MEAN,
        ),
        case(
            V,
            "ScanLines_Cannon.exr",
            "pan",
            "pan".parse().expect("known"),
            2000,
            HDR,
        ),
        case(
            V,
            "MultiResolution_Bonita.exr",
            "handheld",
            handheld(),
            3000,
            HDR,
        ),
        case(V, "kodim12.png", "handheld", handheld(), 2000, DARK),
        Case {
            cfa: CfaKind::Bayer,
            ..case(V, "kodim04.png", "handheld", handheld(), 512, MEAN)
        },
        Case {
            size: SMALL,
            supersampling: 2,
            ..case(V, "kodim22.png", "handheld", handheld(), 2000, MEAN)
        },
        case(
            V,
            "MultiResolution_Bonita.exr",
            "handheld",
            handheld(),
            2000,
            BRIGHT,
        ),
        case(
            V,
            "kodim04.png",
            "shaky handheld",
            shaky_handheld(),
            2000,
            MEAN,
        ),
        case(
            V,
            "MultiResolution_Bonita.exr",
            "shaky handheld",
            shaky_handheld(),
            2000,
            BRIGHT,
        ),
        Case {
            cfa: CfaKind::Bayer,
            ..case(
                V,
                "kodim12.png",
                "shaky handheld",
                shaky_handheld(),
                2000,
                MEAN,
            )
        },
    ]
}

pub(super) fn simulate_case(scenes: &Path, case: &Case) -> Result<SimulatedCapture> {
    let path = scenes.join(case.scene);
    let scene = Scene::load(&path)?;
    let (height, width) = case.size;
    let config = SimulationConfig {
        height,
        width,
        frames: case.frames,
        flux: case.flux,
        motion: case.motion.clone(),
        hot_fraction: 0.02,
        seed: case.seed,
        pixel_supersampling: case.supersampling,
        ..SimulationConfig::default()
    };
    let pattern = match case.cfa {
        CfaKind::ColorSpad => Pattern::Colorspad,
        CfaKind::Bayer => Pattern::Bayer,
    };
    let cfa = cfa::generate(&pattern, height, width, 0)?;
    Ok(simulate_with_cfa(&config, &scene, &cfa, &Silent)?)
}
