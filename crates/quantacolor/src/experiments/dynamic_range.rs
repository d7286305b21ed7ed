//! `dynamic-range`: SNR against flux and dynamic range against the W filter's weight (paper §7,
//! Eq. 9–10, Fig. 19), from the photon model alone (no simulation).
//!
//! Setting (the reading of §7): the SPAD of Table 1 (24 kfps, PDE 9/14/13 %, 2 cps) over
//! 1 s total exposure, n = 24,000 binary frames; the SNR of one pixel's flux estimate is
//! [`model::snr`] (Eq. 9) and its dynamic range [`model::dynamic_range`] (SNR >= 1, capped at the
//! saturation flux). For the simplified RGBW model `wR = wG = wB = w`, a W pixel under grey light
//! detects `λ_W = 3w·λ_c`, i.e. a colour pixel sees `1/(3w)` of a W pixel's detections. With
//! `[a, b]` the single-pixel range in detections per frame, the W pixel covers `λ_W ∈ [a, b]` and
//! a colour pixel `λ_W ∈ [3w·a, 3w·b]`:
//!
//! - best-performance DR (every pixel SNR >= 1): the intersection of the two ranges;
//! - extended DR (W or colour pixels SNR >= 1): their union (Eq. 10).
//!
//! For `w >= 1/3` this gives `DR_bp = DR_1 − 20·log10(3w)` and `DR_ext = DR_1 + 20·log10(3w)`,
//! so `DR_ext − DR_bp = 40·log10(3w)` exactly, whatever the single-pixel range; for `w < 1/3`
//! the roles of W and colour swap and the gap is `40·|log10(3w)|`. The conventional reference is
//! the Bayer CMOS of Table 1 (240 fps, 2.4 e- read noise, 1 e-/s, 10 bits at 1 e-/DN, so a full
//! well of 1023 e-) over the same 1 s: 240 frames summed, [`model::conventional_dynamic_range`].
#![forbid(unsafe_code)]

use super::common::csv;
use super::plot::{self, LinePlot, Series};
use super::{summary_markdown, Artifact, Claim, ExperimentOptions, ExperimentOutput};
use crate::error::{Error, Result};
use crate::model::{self, DynamicRange};
use crate::simulate::{SensorKind, SensorModel};
use ndarray::Array3;

/// Total exposure of the comparison, seconds (§7).
pub const EXPOSURE_S: f64 = 1.0;

/// One row of `dynamic_range.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DrRow {
    /// Weight of each colour band in the W pixel (`wR = wG = wB = w`).
    pub w: f64,
    pub best_performance_db: f64,
    pub extended_db: f64,
    /// Conventional Bayer burst (independent of w).
    pub conventional_db: f64,
}

/// Frames in [`EXPOSURE_S`] and dark counts per frame of `sensor`.
fn frames_and_dark(sensor: &SensorModel) -> (f64, f64) {
    let n = (sensor.frame_rate_hz * EXPOSURE_S).round();
    (n, sensor.dark_count_rate_hz * sensor.exposure_s())
}

/// Single-pixel SPAD dynamic range (SNR >= 1) of the Table 1 SPAD over [`EXPOSURE_S`].
pub fn spad_pixel_range() -> Result<DynamicRange> {
    let (n, d) = frames_and_dark(&SensorModel::table1(SensorKind::Spad));
    model::dynamic_range(n, d, 1.0)
}

/// Dynamic range of the Table 1 CMOS burst over [`EXPOSURE_S`] (one pixel, SNR >= 1).
pub fn conventional_range() -> Result<DynamicRange> {
    let cmos = SensorModel::table1(SensorKind::Cmos);
    let (n, d) = frames_and_dark(&cmos);
    let full_well = f64::from((1u32 << cmos.bit_depth) - 1); // e-, at 1 e-/DN
    model::conventional_dynamic_range(n, d, cmos.read_noise_e, 1.0, full_well, 1.0)
}

/// Best-performance and extended DR (dB) of the RGBW sensor with weight `w`, from the
/// single-pixel range `pixel` (see the module documentation).
pub fn rgbw_ranges(pixel: &DynamicRange, w: f64) -> Result<(f64, f64)> {
    if !(w.is_finite() && w > 0.0) {
        return Err(Error::invalid(format!("W weight {w} must be positive")));
    }
    let k = 3.0 * w; // λ_W / λ_colour under grey light
    let (w_lo, w_hi) = (pixel.min_flux, pixel.max_flux);
    let (c_lo, c_hi) = (k * pixel.min_flux, k * pixel.max_flux);
    let (bp_lo, bp_hi) = (w_lo.max(c_lo), w_hi.min(c_hi));
    if bp_hi <= bp_lo {
        return Err(Error::invalid(format!(
            "w = {w}: no flux where W and colour pixels both reach SNR 1"
        )));
    }
    let (ext_lo, ext_hi) = (w_lo.min(c_lo), w_hi.max(c_hi));
    Ok((
        model::ratio_to_db(bp_hi / bp_lo),
        model::ratio_to_db(ext_hi / ext_lo),
    ))
}

/// The w grid: k/30 for k = 3..=30 (0.1 to 1, including 1/3 exactly).
pub fn w_grid() -> Vec<f64> {
    (3..=30).map(|k| k as f64 / 30.0).collect()
}

/// Rows of `dynamic_range.csv`.
pub fn dr_table() -> Result<Vec<DrRow>> {
    let pixel = spad_pixel_range()?;
    let conventional_db = conventional_range()?.db;
    w_grid()
        .into_iter()
        .map(|w| {
            let (best_performance_db, extended_db) = rgbw_ranges(&pixel, w)?;
            Ok(DrRow {
                w,
                best_performance_db,
                extended_db,
                conventional_db,
            })
        })
        .collect()
}

/// One row of `snr.csv`: SNR (dB) at an incident photon flux per colour band.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SnrRow {
    /// Photons per second reaching the pixel in each of the R, G, B bands (grey light).
    pub photons_per_s: f64,
    /// SPAD W pixel (W = R + G + B, PDE 9 + 14 + 13 %).
    pub snr_w_db: f64,
    /// SPAD R pixel (PDE 9 %).
    pub snr_r_db: f64,
    /// CMOS R pixel (QE 59 %), NaN above the full well.
    pub snr_cmos_r_db: f64,
}

/// SNR curves at `points` log-spaced fluxes from 0.1 to 1e7 photons/s per band.
pub fn snr_table(points: usize) -> Vec<SnrRow> {
    let spad = SensorModel::table1(SensorKind::Spad);
    let cmos = SensorModel::table1(SensorKind::Cmos);
    let (n, d) = frames_and_dark(&spad);
    let (nc, dc) = frames_and_dark(&cmos);
    let full_well = f64::from((1u32 << cmos.bit_depth) - 1);
    let eta = spad.quantum_efficiency;
    (0..points)
        .map(|i| {
            let phi = 10f64.powf(-1.0 + 8.0 * i as f64 / (points - 1).max(1) as f64);
            let lw = phi * (eta[0] + eta[1] + eta[2]) * spad.exposure_s();
            let lr = phi * eta[0] * spad.exposure_s();
            let lc = phi * cmos.quantum_efficiency[0] * cmos.exposure_s();
            let snr_cmos = if lc + dc <= full_well {
                model::ratio_to_db(model::conventional_snr(lc, nc, dc, cmos.read_noise_e, 1.0))
            } else {
                f64::NAN
            };
            SnrRow {
                photons_per_s: phi,
                snr_w_db: model::ratio_to_db(model::snr(lw, n, d)),
                snr_r_db: model::ratio_to_db(model::snr(lr, n, d)),
                snr_cmos_r_db: snr_cmos,
            }
        })
        .collect()
}

/// Plotted SNR: floored at −20 dB so the curves stay on a readable scale; NaN (saturated) stays
/// NaN and is not drawn.
fn floor_db(v: f64) -> f64 {
    if v.is_nan() {
        v
    } else {
        v.max(-20.0)
    }
}

/// Runs the experiment (analytic: `quick` changes only the number of SNR points).
pub fn run(options: &ExperimentOptions) -> Result<ExperimentOutput> {
    if let Some(scene) = &options.scene {
        return Err(Error::invalid(format!(
            "--scene {scene}: the dynamic-range experiment is analytic and takes no scene"
        )));
    }
    let pixel = spad_pixel_range()?;
    let conventional = conventional_range()?;
    let rows = dr_table()?;
    let snr_rows = snr_table(if options.quick { 33 } else { 161 });

    let dr_csv = csv(
        "w,best_performance_db,extended_db,conventional_db",
        rows.iter().map(|r| {
            format!(
                "{},{},{},{}",
                r.w, r.best_performance_db, r.extended_db, r.conventional_db
            )
        }),
    );
    let snr_csv = csv(
        "photons_per_s,snr_w_db,snr_r_db,snr_cmos_r_db",
        snr_rows.iter().map(|r| {
            format!(
                "{},{},{},{}",
                r.photons_per_s, r.snr_w_db, r.snr_r_db, r.snr_cmos_r_db
            )
        }),
    );

    let dr_plot = dr_plot(&rows)?;
    let snr_plot = snr_plot(&snr_rows)?;
    let claims = vec![gap_claim(&rows), dr_claim(&rows, &pixel, &conventional)];
    let summary = summary_markdown(
        "Dynamic range (paper §7, Eq. 9–10, Fig. 19)",
        "Photon model only (crate::model): SPAD of Table 1 over 1 s (24,000 binary frames, \
         2 cps), SNR >= 1 defines the range, saturation at ln(2n) detections/frame; conventional \
         reference: Table 1 CMOS, 240 frames summed, 2.4 e- read noise, full well 1023 e-. \
         Files: dynamic_range.csv / dynamic_range.png (DR against w), snr.csv / snr.png (SNR \
         against photons/s per band for SPAD W, SPAD R and CMOS R pixels).",
        &claims,
        "For w < 1/3 the colour pixels see more light than W and the gap is 40·|log10(3w)| dB \
         (the CSV covers w from 0.1). The 40·log10(3w) relation follows from the range of a \
         colour pixel being the W pixel's range scaled by 3w, so it holds exactly for any \
         single-pixel SNR model; the absolute DR values depend on the model's SNR (Eq. 9) and \
         the saturation cap.",
    );
    Ok(ExperimentOutput {
        files: vec![
            ("dynamic_range.csv".into(), Artifact::Text(dr_csv)),
            ("snr.csv".into(), Artifact::Text(snr_csv)),
            ("dynamic_range.png".into(), Artifact::Png(dr_plot)),
            ("snr.png".into(), Artifact::Png(snr_plot)),
            ("summary.md".into(), Artifact::Text(summary)),
        ],
        claims,
    })
}

/// Dynamic range against w (Fig. 19's axes) of the three readings.
fn dr_plot(rows: &[DrRow]) -> Result<Array3<u8>> {
    plot::render(&LinePlot {
        title: "DYNAMIC RANGE VS W - SPAD 1 S (24000 FRAMES), CMOS 1 S (240 FRAMES)".into(),
        x_label: "W (WR = WG = WB = W)".into(),
        y_label: "DR DB (SNR >= 1)".into(),
        series: vec![
            Series {
                name: "BEST PERFORMANCE".into(),
                points: rows.iter().map(|r| (r.w, r.best_performance_db)).collect(),
            },
            Series {
                name: "EXTENDED".into(),
                points: rows.iter().map(|r| (r.w, r.extended_db)).collect(),
            },
            Series {
                name: "CONVENTIONAL".into(),
                points: rows.iter().map(|r| (r.w, r.conventional_db)).collect(),
            },
        ],
        x_categories: None,
    })
}

/// SNR against flux of the SPAD W and R pixels and the CMOS R pixel.
fn snr_plot(snr_rows: &[SnrRow]) -> Result<Array3<u8>> {
    plot::render(&LinePlot {
        title: "SNR VS FLUX - 1 S TOTAL EXPOSURE".into(),
        x_label: "LOG10 PHOTONS/S PER BAND".into(),
        y_label: "SNR DB".into(),
        series: vec![
            Series {
                name: "SPAD W".into(),
                points: snr_rows
                    .iter()
                    .map(|r| (r.photons_per_s.log10(), floor_db(r.snr_w_db)))
                    .collect(),
            },
            Series {
                name: "SPAD R".into(),
                points: snr_rows
                    .iter()
                    .map(|r| (r.photons_per_s.log10(), floor_db(r.snr_r_db)))
                    .collect(),
            },
            Series {
                name: "CMOS R".into(),
                points: snr_rows
                    .iter()
                    .map(|r| (r.photons_per_s.log10(), floor_db(r.snr_cmos_r_db)))
                    .collect(),
            },
        ],
        x_categories: None,
    })
}

/// Claim 1: the gap between the extended and best-performance ranges is 40·log10(3w) dB for
/// w >= 1/3 (§7, Eq. 10).
fn gap_claim(rows: &[DrRow]) -> Claim {
    let worst = rows
        .iter()
        .filter(|r| r.w >= 1.0 / 3.0)
        .map(|r| (r.extended_db - r.best_performance_db - 40.0 * (3.0 * r.w).log10()).abs())
        .fold(0.0_f64, f64::max);
    let at_one = rows.last().expect("grid is not empty");
    Claim {
        statement: "extended minus best-performance DR grows as 40·log10(3w) dB for w >= 1/3 \
                    (§7, Eq. 10)"
            .into(),
        reproduced: worst < 1e-9,
        evidence: format!(
            "largest |DR_ext − DR_bp − 40·log10(3w)| over the {} grid points with w >= 1/3: \
             {worst:.3e} dB; at w = 1: DR_bp {:.2} dB, DR_ext {:.2} dB, gap {:.4} dB \
             (40·log10 3 = {:.4} dB)",
            rows.iter().filter(|r| r.w >= 1.0 / 3.0).count(),
            at_one.best_performance_db,
            at_one.extended_db,
            at_one.extended_db - at_one.best_performance_db,
            40.0 * 3f64.log10()
        ),
    }
}

/// Claim 2: the single-photon burst's range exceeds the conventional burst's (Fig. 19).
fn dr_claim(rows: &[DrRow], pixel: &DynamicRange, conventional: &DynamicRange) -> Claim {
    let at_one = rows.last().expect("grid is not empty");
    let third = rows
        .iter()
        .find(|r| (r.w - 1.0 / 3.0).abs() < 1e-12)
        .expect("grid holds 1/3");
    Claim {
        statement: "single-photon (SPAD) bursts have a higher dynamic range than a conventional \
                    burst of the same total exposure (Fig. 19)"
            .into(),
        reproduced: third.best_performance_db > conventional.db,
        evidence: format!(
            "SPAD pixel {:.2} dB ({:.3e}..{:.3} detections/frame, upper end set by {:?}); \
             RGBW at w = 1/3 (W and colour alike) {:.2} dB, best-performance at w = 1 {:.2} dB, \
             extended at w = 1 {:.2} dB; conventional CMOS burst {:.2} dB ({:.3}..{:.0} e-/frame)",
            pixel.db,
            pixel.min_flux,
            pixel.max_flux,
            pixel.upper_limit,
            third.best_performance_db,
            at_one.best_performance_db,
            at_one.extended_db,
            conventional.db,
            conventional.min_flux,
            conventional.max_flux
        ),
    }
}
