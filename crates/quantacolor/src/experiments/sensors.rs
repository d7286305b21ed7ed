//! `sensors` (paper Fig. 11, Fig. 12, supplement Fig. 4): the same scene, light and total
//! exposure time through the sensors of paper Table 1 — conventional CMOS behind a Bayer CFA,
//! SPAD behind Bayer and behind the blue-noise 75 % W RGBW CFA, and a binary jot behind the same
//! RGBW CFA — in daylight and at night (an HDR scene with a light source), under slow and fast
//! hand shake.
//!
//! Every capture goes through the one reconstruction pipeline: the binary ones with the paper's
//! burst method, the CMOS one with each frame its own block and the Gaussian–Poisson model
//! (§6.1, [`crate::model::PixelModel`]); no denoising, as in the other experiments, so that the
//! numbers compare sensors and merge rather than the denoiser.
//!
//! Equal light: the scene sends the same photons per second to every sensor. A white pixel
//! (reflectance 1) receives Φ photons per second in each of R, G and B, so a pixel behind filter
//! c of sensor s sees λ_c = Φ·r_c·QE_{s,c}·τ_s per frame (paper Eq. 2–3; τ_s the frame time of
//! Table 1). The simulator's light level ([`FluxSpec::Mean`], mean W detections per frame) is set
//! per sensor from Φ and the scene's mean reflectances ([`sensor_flux`]). Equal motion: the hand
//! shake is defined over the whole burst ([`MotionConfig::Handheld`]), so with equal total
//! exposure every sensor sees the same trajectory in time.
//!
//! The paper's observations tested here: a SPAD with the RGBW CFA beats the conventional sensor
//! at night (no read noise) and matches it in daylight; jots (higher quantum efficiency, no dark
//! counts, but 1 kfps) win when the motion is slow and lose when it is fast (their frames blur).
#![forbid(unsafe_code)]

use super::common::{csv, score, tone_mapped_sheet, trial};
use super::plot::{self, LinePlot, Series};
use super::{summary_markdown, Artifact, Claim, ExperimentOptions, ExperimentOutput};
use crate::cfa::{self, Pattern};
use crate::error::Result;
use crate::progress::Progress;
use crate::simulate::{FluxSpec, MotionConfig, Scene, SensorKind, SensorModel, SimulationConfig};
use ndarray::{Array3, Axis};

/// The sensors compared: (name, kind, CFA), paper Table 1.
pub const SENSORS: [(&str, SensorKind, &str); 4] = [
    ("cmos", SensorKind::Cmos, "bayer"),
    ("spad", SensorKind::Spad, "bayer"),
    ("spad", SensorKind::Spad, "rgbw-75-bluenoise"),
    ("jot", SensorKind::Jot, "rgbw-75-bluenoise"),
];

/// The light levels: (name, default scene, Φ photons per second per pixel per colour band at
/// reflectance 1).
pub const LIGHTS: [(&str, &str, f64); 2] = [
    // A SPAD W pixel sees about 3 detections per frame on white; the CMOS green pixel ~540 e-.
    ("daylight", "builtin:chart", 2.0e5),
    // White: 0.015 SPAD W detections per frame, 2.7 e- per CMOS green frame (read noise 2.4 e-);
    // the light source of the HDR chart is 1000x brighter.
    ("night", "builtin:chart-hdr", 1.0e3),
];

/// The motions: (name, hand shake over the whole burst).
pub fn motions() -> [(&'static str, MotionConfig); 2] {
    [
        (
            "slow",
            // Peak 2 px, 0.75 cycles of the slowest component over the burst.
            MotionConfig::Handheld {
                amplitude_px: 2.0,
                rotation_deg: 0.2,
                cycles: 0.75,
            },
        ),
        (
            "fast",
            // Peak 8 px, 1.5 cycles: several px per CMOS frame, about 1 px per jot frame.
            MotionConfig::FastHandheld {
                amplitude_px: 8.0,
                rotation_deg: 1.0,
                cycles: 1.5,
            },
        ),
    ]
}

/// Mean reflectance of R, G and B of `scene` over an `height` x `width` sensor.
pub fn scene_channel_means(scene: &Scene, height: usize, width: usize) -> [f64; 3] {
    let raster = scene.rasterise(height, width, 0.0);
    [0, 1, 2].map(|c| {
        raster
            .planes
            .index_axis(Axis(0), c)
            .mean()
            .map_or(0.0, f64::from)
    })
}

/// The simulator's light level for `sensor` (mean W detections per frame, dark excluded) when a
/// white pixel receives `photons_per_s` photons per second per colour band and the scene's mean
/// reflectances are `means`: Φ·τ·Σ_c QE_c·m_c.
pub fn sensor_flux(sensor: &SensorModel, photons_per_s: f64, means: [f64; 3]) -> f64 {
    let qe = sensor.quantum_efficiency;
    photons_per_s * sensor.exposure_s() * (0..3).map(|c| qe[c] * means[c]).sum::<f64>()
}

/// One row of `sensors.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorRow {
    pub scene: String,
    pub light: String,
    pub motion: String,
    pub sensor: String,
    pub cfa: String,
    /// sRGB PSNR, dB.
    pub psnr: f64,
    /// sRGB SSIM.
    pub ssim: f64,
}

/// Sizes of one run.
struct Setting {
    height: usize,
    width: usize,
    /// Total exposure time, seconds (the same for every sensor).
    exposure_s: f64,
    border: usize,
    crop: usize,
}

fn setting(quick: bool) -> Setting {
    if quick {
        Setting {
            height: 48,
            width: 64,
            exposure_s: 0.025, // SPAD 600, jot 25, CMOS 6 frames
            border: 6,
            crop: 48,
        }
    } else {
        Setting {
            height: 192,
            width: 256,
            exposure_s: 0.1, // SPAD 2400, jot 100, CMOS 24 frames
            border: 16,
            crop: 128,
        }
    }
}

/// Runs the experiment; default scenes `builtin:chart` (daylight) and `builtin:chart-hdr`
/// (night); `--scene` replaces both.
pub fn run(options: &ExperimentOptions, progress: &dyn Progress) -> Result<ExperimentOutput> {
    let st = setting(options.quick);
    let Trials {
        rows,
        sheet,
        settings_text,
    } = run_trials(options, &st, progress)?;
    let table = csv(
        "scene,light,motion,sensor,cfa,psnr,ssim",
        rows.iter().map(|r| {
            format!(
                "{},{},{},{},{},{:.4},{:.5}",
                r.scene, r.light, r.motion, r.sensor, r.cfa, r.psnr, r.ssim
            )
        }),
    );
    let png = sensors_plot(&rows)?;
    let sheet_refs: Vec<Vec<(&Array3<f32>, &Array3<f32>)>> = sheet
        .iter()
        .map(|pairs| pairs.iter().map(|(t, e)| (t, e)).collect())
        .collect();
    let contact = tone_mapped_sheet(&sheet_refs, st.crop)?;

    let claims = claims(&rows);
    let summary = summary_markdown(
        "Sensors: conventional CMOS, SPAD and jot (paper Fig. 11, Fig. 12, supplement Fig. 4)",
        &setup_text(options, &st, &settings_text),
        &claims,
        "Pass criteria (this project's reading of Fig. 11–12): \"beats\" = higher sRGB PSNR under \
         both motions; \"matches\" = the mean PSNR difference over the two motions is within \
         ±1 dB or in the SPAD's favour; the jot claims compare the jot with the SPAD behind the \
         same RGBW CFA at night (in daylight a 1 kfps binary jot saturates: about 150 \
         detections per frame on white).",
    );
    Ok(ExperimentOutput {
        files: vec![
            ("sensors.csv".into(), Artifact::Text(table)),
            ("sensors.png".into(), Artifact::Png(png)),
            ("contact_sheet.png".into(), Artifact::Png(contact)),
            ("summary.md".into(), Artifact::Text(summary)),
        ],
        claims,
    })
}

/// What the simulations of [`run`] give: a row per capture, (truth, estimate) of every sensor
/// per light and motion, and each sensor's frames and flux per light.
struct Trials {
    rows: Vec<SensorRow>,
    sheet: Vec<Vec<(Array3<f32>, Array3<f32>)>>,
    settings_text: Vec<String>,
}

/// Simulates and reconstructs every sensor under every light and motion.
fn run_trials(
    options: &ExperimentOptions,
    st: &Setting,
    progress: &dyn Progress,
) -> Result<Trials> {
    let mut rows = Vec::new();
    // (truth, estimate) of every sensor, per light and motion.
    let mut sheet: Vec<Vec<(Array3<f32>, Array3<f32>)>> = Vec::new();
    let mut settings_text = Vec::new();
    for (light, default_scene, photons) in LIGHTS {
        let spec = options.scene.as_deref().unwrap_or(default_scene);
        let scene = Scene::from_spec(spec)?;
        let means = scene_channel_means(&scene, st.height, st.width);
        for (mname, motion) in motions() {
            let mut pairs = Vec::new();
            for (sname, kind, cfa_name) in SENSORS {
                let sensor = SensorModel::table1(kind);
                let frames = (st.exposure_s * sensor.frame_rate_hz).round().max(1.0) as usize;
                let flux = sensor_flux(&sensor, photons, means);
                let config = SimulationConfig {
                    height: st.height,
                    width: st.width,
                    frames,
                    cfa: cfa_name.into(),
                    cfa_seed: options.seed,
                    sensor: kind,
                    flux: FluxSpec::Mean { flux },
                    motion: motion.clone(),
                    seed: options.seed,
                    ..SimulationConfig::default()
                };
                if mname == "slow" {
                    settings_text.push(format!(
                        "{light} {sname} {cfa_name}: {frames} frames, {flux:.4} W \
                         detections/pixel/frame"
                    ));
                }
                let pattern: Pattern = cfa_name.parse()?;
                let cfa = cfa::generate(&pattern, st.height, st.width, options.seed)?;
                let t = trial(&config, &scene, Some(&cfa), false, progress)?;
                let s = score(&t.burst, &t.truth, st.border)?;
                rows.push(SensorRow {
                    scene: scene.name(),
                    light: light.into(),
                    motion: mname.into(),
                    sensor: sname.into(),
                    cfa: cfa_name.into(),
                    psnr: s.psnr_srgb,
                    ssim: s.ssim_srgb,
                });
                pairs.push((t.truth, t.burst));
            }
            sheet.push(pairs);
        }
    }

    Ok(Trials {
        rows,
        sheet,
        settings_text,
    })
}

/// sRGB PSNR of every sensor per light and motion.
fn sensors_plot(rows: &[SensorRow]) -> Result<Array3<u8>> {
    let conditions: Vec<(String, String)> = LIGHTS
        .iter()
        .flat_map(|(l, _, _)| motions().map(|(m, _)| (l.to_string(), m.to_string())))
        .collect();
    plot::render(&LinePlot {
        title: "SENSORS AT EQUAL LIGHT AND EXPOSURE (FIG. 11-12)".into(),
        x_label: "LIGHT / MOTION".into(),
        y_label: "SRGB PSNR DB".into(),
        series: SENSORS
            .iter()
            .map(|(s, _, c)| Series {
                name: format!("{s} {c}").to_uppercase(),
                points: conditions
                    .iter()
                    .enumerate()
                    .filter_map(|(i, (l, m))| find(rows, l, m, s, c).map(|r| (i as f64, r.psnr)))
                    .collect(),
            })
            .collect(),
        x_categories: Some(
            conditions
                .iter()
                .map(|(l, m)| format!("{l} {m}").to_uppercase())
                .collect(),
        ),
    })
}

/// The setup paragraph of the summary.
fn setup_text(options: &ExperimentOptions, st: &Setting, settings_text: &[String]) -> String {
    format!(
        "{}x{} px, {} s total exposure for every sensor (Table 1 frame rates, quantum \
             efficiencies, dark counts, read noise; CMOS 10 bits, 1 e-/DN, 16 DN black level), \
             seed {}; light: a white pixel receives {:.0} photons/s per colour band in daylight \
             (scene `{}`) and {:.0} at night (scene `{}`); motion: slow hand shake (peak 2 px, \
             0.75 cycles over the exposure) and fast (peak 8 px, 1.5 cycles). Each capture is \
             reconstructed by the burst method (CMOS: each frame its own block, Gaussian–Poisson \
             model, §6.1) without denoising and scored by sRGB PSNR / SSIM after a {}-px border \
             crop (§6 protocol). Per sensor: {}. contact_sheet.png: one row per light and \
             motion (daylight slow, daylight fast, night slow, night fast), columns truth, \
             CMOS Bayer, SPAD Bayer, SPAD RGBW, jot RGBW (centre {} px crops, global tone map \
             at the truth's exposure).",
        st.width,
        st.height,
        st.exposure_s,
        options.seed,
        LIGHTS[0].2,
        options.scene.as_deref().unwrap_or(LIGHTS[0].1),
        LIGHTS[1].2,
        options.scene.as_deref().unwrap_or(LIGHTS[1].1),
        st.border,
        settings_text.join("; "),
        st.crop,
    )
}

fn find<'a>(
    rows: &'a [SensorRow],
    light: &str,
    motion: &str,
    sensor: &str,
    cfa: &str,
) -> Option<&'a SensorRow> {
    rows.iter()
        .find(|r| r.light == light && r.motion == motion && r.sensor == sensor && r.cfa == cfa)
}

fn claims(rows: &[SensorRow]) -> Vec<Claim> {
    let psnr =
        |l: &str, m: &str, s: &str, c: &str| find(rows, l, m, s, c).map_or(f64::NAN, |r| r.psnr);
    let rgbw = "rgbw-75-bluenoise";
    let spad = |l: &str, m: &str| psnr(l, m, "spad", rgbw);
    let cmos = |l: &str, m: &str| psnr(l, m, "cmos", "bayer");
    let jot = |l: &str, m: &str| psnr(l, m, "jot", rgbw);
    let night_gap = ["slow", "fast"].map(|m| spad("night", m) - cmos("night", m));
    let day_gap = ["slow", "fast"].map(|m| spad("daylight", m) - cmos("daylight", m));
    let day_mean = (day_gap[0] + day_gap[1]) / 2.0;
    let (jot_slow, jot_fast) = (
        jot("night", "slow") - spad("night", "slow"),
        jot("night", "fast") - spad("night", "fast"),
    );
    vec![
        Claim {
            statement: "a SPAD with the RGBW CFA beats a conventional CMOS sensor at night \
                        (Fig. 11)"
                .into(),
            reproduced: night_gap.iter().all(|g| *g > 0.0),
            evidence: format!(
                "night sRGB PSNR, SPAD RGBW vs CMOS Bayer: slow {:.2} vs {:.2} dB ({:+.2}), fast \
                 {:.2} vs {:.2} dB ({:+.2})",
                spad("night", "slow"),
                cmos("night", "slow"),
                night_gap[0],
                spad("night", "fast"),
                cmos("night", "fast"),
                night_gap[1]
            ),
        },
        Claim {
            statement: "a SPAD with the RGBW CFA matches a conventional CMOS sensor in daylight \
                        (Fig. 11)"
                .into(),
            reproduced: day_mean >= -1.0,
            evidence: format!(
                "daylight sRGB PSNR, SPAD RGBW vs CMOS Bayer: slow {:.2} vs {:.2} dB ({:+.2}), \
                 fast {:.2} vs {:.2} dB ({:+.2}); mean difference {day_mean:+.2} dB",
                spad("daylight", "slow"),
                cmos("daylight", "slow"),
                day_gap[0],
                spad("daylight", "fast"),
                cmos("daylight", "fast"),
                day_gap[1]
            ),
        },
        Claim {
            statement: "jots win on slow motion (Fig. 12, supplement Fig. 4)".into(),
            reproduced: jot_slow > 0.0,
            evidence: format!(
                "night, slow: jot RGBW {:.2} dB vs SPAD RGBW {:.2} dB ({jot_slow:+.2})",
                jot("night", "slow"),
                spad("night", "slow")
            ),
        },
        Claim {
            statement: "jots lose on fast motion (Fig. 12, supplement Fig. 4)".into(),
            reproduced: jot_fast < 0.0,
            evidence: format!(
                "night, fast: jot RGBW {:.2} dB vs SPAD RGBW {:.2} dB ({jot_fast:+.2})",
                jot("night", "fast"),
                spad("night", "fast")
            ),
        },
    ]
}
