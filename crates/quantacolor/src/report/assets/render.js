// quantacolor report: the display pipeline of `quantacolor display`, in the browser.
//
// The same formulas, in the same order and at the same float precision (Math.fround where the
// Rust code computes in f32), as crates/quantacolor/src/display/:
//   noise-aware low-light blend (mesopic.rs, supplement Eq. 9-10)
//   -> sanitise (non-finite and negative values to 0) -> exposure -> tone map
//      (tonemap.rs: `none` = exposure and clip, `global` = Reinhard et al. 2002 Eq. 1-4)
//   -> sRGB (srgb.rs, IEC 61966-2-1) -> 8 bits (render.rs quantise8).
// Mantiuk06 is not here: the page shows it pre-rendered by the Rust code.
// Checked against the Rust code on sample pixels by crates/quantacolor/tests/report_render.rs
// (node) and against `quantacolor display` by crates/quantacolor-cli/tests/report_browser.rs.
"use strict";
(function (root, factory) {
  const api = factory();
  if (typeof module === "object" && module.exports) {
    module.exports = api;
  } else {
    root.QCRender = api;
  }
})(typeof self !== "undefined" ? self : this, function () {
  const f32 = Math.fround;
  // tonemap.rs REC709_LUMA (f32 constants).
  const LUMA = [f32(0.2126), f32(0.7152), f32(0.0722)];
  // exposure.rs AUTO_EXPOSURE_PERCENTILE.
  const AUTO_EXPOSURE_PERCENTILE = 99.5;
  // tonemap.rs GlobalConfig::default().
  const GLOBAL_KEY = f32(0.18);
  const GLOBAL_WHITE_PERCENTILE = 99.9;
  // mesopic.rs MESOPIC_C1, MESOPIC_C2, DETECTIONS_PER_W_UNIT.
  const MESOPIC_C1 = 0.0;
  const MESOPIC_C2 = -2.0;
  const DETECTIONS_PER_W_UNIT = 100.0;
  // srgb.rs constants (f32).
  const SRGB_KNEE = f32(0.0031308);
  const SRGB_SLOPE = f32(12.92);
  const SRGB_A = f32(1.055);
  const SRGB_B = f32(0.055);
  const SRGB_EXP = f32(1.0 / f32(2.4));

  // f64::MIN_POSITIVE (smallest normal double), the floor of the log-average's delta.
  const F64_MIN_POSITIVE = 2.2250738585072014e-308;

  let halfTable = null;

  // binary16 bit pattern -> value (report/encode.rs).
  function halfToFloat(h) {
    const sign = h & 0x8000 ? -1 : 1;
    const e = (h >> 10) & 0x1f;
    const m = h & 0x3ff;
    if (e === 0) {
      return sign * m * Math.pow(2, -24);
    }
    if (e === 31) {
      return m ? NaN : sign * Infinity;
    }
    return sign * (1 + m / 1024) * Math.pow(2, e - 15);
  }

  function base64Bytes(b64) {
    if (typeof atob === "function") {
      const s = atob(b64);
      const out = new Uint8Array(s.length);
      for (let i = 0; i < s.length; i++) {
        out[i] = s.charCodeAt(i);
      }
      return out;
    }
    return new Uint8Array(Buffer.from(b64, "base64"));
  }

  // Decodes the page's linear data: base64 of little-endian binary16 samples of
  // value * 2^scaleLog2 -> Float32Array (H * W * 3).
  function decodeHalf(b64, scaleLog2) {
    if (halfTable === null) {
      halfTable = new Float32Array(65536);
      for (let h = 0; h < 65536; h++) {
        halfTable[h] = halfToFloat(h);
      }
    }
    const bytes = base64Bytes(b64);
    const n = bytes.length >> 1;
    const out = new Float32Array(n);
    const factor = Math.pow(2, -scaleLog2);
    for (let i = 0; i < n; i++) {
      out[i] = halfTable[bytes[2 * i] | (bytes[2 * i + 1] << 8)] * factor;
    }
    return out;
  }

  // srgb.rs linear_to_srgb (f32).
  function linearToSrgb(v) {
    v = Math.min(Math.max(v, 0), 1);
    if (v <= SRGB_KNEE) {
      return f32(SRGB_SLOPE * v);
    }
    return f32(f32(SRGB_A * f32(Math.pow(v, SRGB_EXP))) - SRGB_B);
  }

  // render.rs quantise8 for one display-referred linear value.
  function quantise8(v) {
    if (!Number.isFinite(v)) {
      v = 0;
    }
    return Math.round(f32(linearToSrgb(v) * 255));
  }

  // mesopic.rs mesopic_weight: colour weight p of Eq. 9 for W in hundreds of detections.
  function mesopicWeight(w, l0) {
    if (w === Infinity) {
      return 1;
    }
    if (Number.isNaN(w) || w <= 0) {
      return 0;
    }
    const p = (Math.log10(w) + l0 - MESOPIC_C2) / (MESOPIC_C1 - MESOPIC_C2);
    return Math.min(Math.max(p, 0), 1);
  }

  // mesopic.rs mesopic_blend (Eq. 10) into a new array; `l0` as the CLI parses it (f32).
  function mesopicBlend(src, l0, frames, wWeights) {
    const out = new Float32Array(src.length);
    const sum = wWeights[0] + wWeights[1] + wWeights[2];
    const scale = frames / DETECTIONS_PER_W_UNIT;
    const l0d = f32(l0);
    for (let i = 0; i < src.length; i += 3) {
      const r = src[i];
      const g = src[i + 1];
      const b = src[i + 2];
      const w = wWeights[0] * r + wWeights[1] * g + wWeights[2] * b;
      const p = mesopicWeight(w * scale, l0d);
      const grey = w / sum;
      out[i] = p * r + (1 - p) * grey;
      out[i + 1] = p * g + (1 - p) * grey;
      out[i + 2] = p * b + (1 - p) * grey;
    }
    return out;
  }

  // exposure.rs percentile (nearest rank) of an array already sorted ascending.
  function rankOf(n, p) {
    return Math.min(Math.round((p / 100) * (n - 1)), n - 1);
  }

  // tonemap.rs luminance (f32 arithmetic, left to right).
  function luminance(r, g, b) {
    return f32(f32(f32(LUMA[0] * r) + f32(LUMA[1] * g)) + f32(LUMA[2] * b));
  }

  // Everything that depends on the image and the low-light blend but not on the exposure:
  // the sanitised blended image, its luminance and the statistics of the automatic exposures.
  // `mesopic` is null (off) or {l0, frames}.
  function prepare(linear, mesopic, wWeights) {
    const blended =
      mesopic === null ? linear : mesopicBlend(linear, mesopic.l0, mesopic.frames, wWeights);
    const n = blended.length / 3;
    const img = new Float32Array(blended.length);
    const lum = new Float32Array(n);
    const maxima = new Float32Array(n);
    let lumMax = 0;
    for (let i = 0, j = 0; j < n; i += 3, j++) {
      for (let c = 0; c < 3; c++) {
        const v = blended[i + c];
        img[i + c] = Number.isFinite(v) ? Math.max(v, 0) : 0;
      }
      const l = luminance(img[i], img[i + 1], img[i + 2]);
      lum[j] = l;
      lumMax = Math.max(lumMax, l);
      maxima[j] = Math.max(img[i], img[i + 1], img[i + 2]);
    }
    // Global operator, automatic exposure: key on the log-average luminance (Reinhard Eq. 1).
    const delta = 1e-6 * Math.max(lumMax, F64_MIN_POSITIVE);
    let sumLog = 0;
    for (let j = 0; j < n; j++) {
      sumLog += Math.log(lum[j] + delta);
    }
    const avg = Math.exp(sumLog / Math.max(n, 1));
    const globalAuto = avg > 0 ? GLOBAL_KEY / avg : 1;
    // White point: the percentile of scaled luminance; scaling is monotone, so it is the
    // percentile of the luminance times the scale.
    const sortedLum = Float32Array.from(lum).sort();
    const lumAtWhite = n > 0 ? sortedLum[rankOf(n, GLOBAL_WHITE_PERCENTILE)] : 0;
    // `none`, automatic exposure: 99.5th percentile of the brightest channel to white.
    const sortedMax = maxima.sort();
    const top = n > 0 ? sortedMax[rankOf(n, AUTO_EXPOSURE_PERCENTILE)] : 0;
    const noneAuto = top > 0 ? f32(1 / top) : 1;
    return { img, lum, n, globalAuto, noneAuto, lumAtWhite };
  }

  // The exposure `display` picks without --exposure.
  function autoExposure(prep, tonemap) {
    return tonemap === "global" ? prep.globalAuto : prep.noneAuto;
  }

  // Renders to 8-bit sRGB RGBA. `exposure` null = automatic (as `display` without
  // --exposure), else the value given to `display --exposure` (rounded to f32 like the CLI).
  function render(prep, tonemap, exposure, out) {
    const { img, lum, n } = prep;
    const rgba = out || new Uint8ClampedArray(n * 4);
    if (tonemap === "none") {
      const s = exposure === null ? prep.noneAuto : f32(exposure);
      for (let i = 0, j = 0; j < n; i += 3, j++) {
        for (let c = 0; c < 3; c++) {
          rgba[4 * j + c] = quantise8(Math.min(Math.max(f32(img[i + c] * s), 0), 1));
        }
        rgba[4 * j + 3] = 255;
      }
      return rgba;
    }
    if (tonemap !== "global") {
      throw new Error("unknown tone map " + tonemap);
    }
    const scale = exposure === null ? prep.globalAuto : f32(exposure);
    let white = f32(prep.lumAtWhite * f32(scale));
    if (!(white > 0)) {
      white = 1;
    }
    const white2 = white * white;
    for (let i = 0, j = 0; j < n; i += 3, j++) {
      const l = lum[j] * scale;
      if (l > 0) {
        const ld = (l * (1 + l / white2)) / (1 + l);
        const k = f32((ld / l) * scale);
        for (let c = 0; c < 3; c++) {
          rgba[4 * j + c] = quantise8(Math.min(Math.max(f32(img[i + c] * k), 0), 1));
        }
      } else {
        rgba[4 * j] = rgba[4 * j + 1] = rgba[4 * j + 2] = quantise8(0);
      }
      rgba[4 * j + 3] = 255;
    }
    return rgba;
  }

  return {
    decodeHalf,
    halfToFloat,
    linearToSrgb,
    quantise8,
    mesopicWeight,
    mesopicBlend,
    prepare,
    autoExposure,
    render,
  };
});
