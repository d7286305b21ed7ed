// quantacolor report: the comparison page (written by `quantacolor report`).
// Panels side by side with synchronised zoom and pan (wheel, drag; nearest-neighbour, so pixel
// exact at high zoom), re-rendered from the linear data (report-data.js, binary16) by
// render.js on every change of exposure, tone map or low-light L0. The settings live in the
// URL hash (#tm=global&ev=0&l0=off&lock=0&z=..&cx=..&cy=..), so a link reproduces a view.
"use strict";
(function () {
  const data = window.QC_DATA;
  const R = window.QCRender;
  // Zoom levels the wheel steps through, screen pixels per image pixel (at the integer ones
  // every image pixel is a square of whole screen pixels).
  const ZOOM_LEVELS = [0.125, 0.25, 0.5, 0.75, 1, 1.5, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64];
  const $ = (id) => document.getElementById(id);

  const state = { tonemap: data.tonemap, ev: 0, l0: null, lock: false };
  const view = { zoom: 1, cx: 0, cy: 0, fit: true };
  const panels = [];
  const QC = { state, view, panels, ready: false, renders: 0 };
  window.QC = QC;

  function parseHash() {
    const h = new URLSearchParams(location.hash.slice(1));
    if (h.has("tm") && ["global", "none", "mantiuk06"].includes(h.get("tm"))) {
      state.tonemap = h.get("tm");
    }
    if (h.has("ev") && Number.isFinite(parseFloat(h.get("ev")))) {
      state.ev = parseFloat(h.get("ev"));
    }
    if (h.has("l0")) {
      const v = parseFloat(h.get("l0"));
      state.l0 = Number.isFinite(v) ? v : null;
    }
    state.lock = h.get("lock") === "1";
    if (h.has("z") && h.has("cx") && h.has("cy")) {
      const z = parseFloat(h.get("z"));
      const cx = parseFloat(h.get("cx"));
      const cy = parseFloat(h.get("cy"));
      if ([z, cx, cy].every(Number.isFinite) && z > 0) {
        Object.assign(view, { zoom: z, cx, cy, fit: false });
      }
    }
  }

  function writeHash() {
    const h = new URLSearchParams();
    h.set("tm", state.tonemap);
    h.set("ev", String(state.ev));
    h.set("l0", state.l0 === null ? "off" : String(state.l0));
    h.set("lock", state.lock ? "1" : "0");
    if (!view.fit) {
      h.set("z", String(view.zoom));
      h.set("cx", view.cx.toFixed(2));
      h.set("cy", view.cy.toFixed(2));
    }
    history.replaceState(null, "", "#" + h.toString());
  }

  // ---- layout --------------------------------------------------------------------------
  const ref = data.panels[data.reference];

  function viewSize() {
    const n = data.panels.length;
    const cols = n <= 3 ? n : n === 4 ? 2 : 3;
    const avail = Math.max(200, document.documentElement.clientWidth - 32);
    const w = Math.max(160, Math.floor((avail - (cols - 1) * 12) / cols));
    const h = Math.max(120, Math.min(Math.round((w * ref.height) / ref.width), 720));
    return { w, h };
  }

  function fitView() {
    const { w, h } = QC.size;
    view.zoom = Math.min(w / ref.width, h / ref.height);
    view.cx = ref.width / 2;
    view.cy = ref.height / 2;
    view.fit = true;
  }

  // Image coordinates (continuous; pixel i covers [i, i+1)) under canvas point (sx, sy).
  function toImage(sx, sy) {
    const { w, h } = QC.size;
    return [view.cx + (sx - w / 2) / view.zoom, view.cy + (sy - h / 2) / view.zoom];
  }
  QC.toImage = toImage;

  function draw() {
    const { w, h } = QC.size;
    const dpr = window.devicePixelRatio || 1;
    for (const p of panels) {
      const ctx = p.canvas.getContext("2d");
      ctx.setTransform(1, 0, 0, 1, 0, 0);
      ctx.fillStyle = "#202020";
      ctx.fillRect(0, 0, p.canvas.width, p.canvas.height);
      const src = state.tonemap === "mantiuk06" ? p.mantiuk : p.offscreen;
      if (!src) {
        continue;
      }
      ctx.imageSmoothingEnabled = view.zoom < 1;
      const z = view.zoom * dpr;
      ctx.setTransform(z, 0, 0, z, (w / 2 - view.cx * view.zoom) * dpr, (h / 2 - view.cy * view.zoom) * dpr);
      ctx.drawImage(src, 0, 0);
    }
    $("zoom").textContent = view.fit ? "fit" : view.zoom + "\u00d7";
  }

  // ---- rendering -----------------------------------------------------------------------
  function mesopicOf(p) {
    if (state.l0 === null || !(p.frames > 0)) {
      return null;
    }
    return { l0: state.l0, frames: p.frames };
  }

  // Exposure given to render() for panel p: null = automatic (`display` without --exposure);
  // else auto x 2^EV, or the reference panel's when exposures are locked.
  function exposureOf(p) {
    const base = state.lock ? panels[data.reference] : p;
    if (state.ev === 0 && base === p) {
      return null;
    }
    return Math.fround(R.autoExposure(base.prep, state.tonemap) * Math.pow(2, state.ev));
  }
  QC.exposureOf = (i) => exposureOf(panels[i]);

  function prepareAll() {
    for (const p of panels) {
      p.prep = R.prepare(p.linear, mesopicOf(p), p.w_weights);
    }
  }

  function renderAll() {
    const mantiuk = state.tonemap === "mantiuk06";
    for (const p of panels) {
      const el = p.caption;
      if (mantiuk) {
        el.textContent = "Mantiuk06, pre-rendered (auto exposure, no low-light view)";
        continue;
      }
      const e = exposureOf(p);
      const shown = e === null ? R.autoExposure(p.prep, state.tonemap) : e;
      R.render(p.prep, state.tonemap, e, p.image.data);
      p.offscreen.getContext("2d").putImageData(p.image, 0, 0);
      let text = "exposure \u00d7" + shown.toPrecision(6) + (e === null ? " (auto)" : "");
      if (state.l0 !== null) {
        text += p.frames > 0 ? ", L0 " + state.l0 : ", no frame count: low-light view off";
      }
      el.textContent = text;
    }
    QC.renders += 1;
    draw();
  }

  function syncControls() {
    $("tonemap").value = state.tonemap;
    $("ev").value = state.ev;
    $("ev-value").textContent = (state.ev > 0 ? "+" : "") + state.ev.toFixed(1);
    $("mesopic").checked = state.l0 !== null;
    $("l0").disabled = state.l0 === null;
    if (state.l0 !== null) {
      $("l0").value = state.l0;
    }
    $("l0-value").textContent = state.l0 === null ? "off" : state.l0.toFixed(1);
    $("lock").checked = state.lock;
    const mantiuk = state.tonemap === "mantiuk06";
    for (const id of ["ev", "mesopic", "l0", "lock"]) {
      $(id).closest("label").classList.toggle("inactive", mantiuk);
    }
  }

  function changed(needPrepare) {
    if (needPrepare) {
      prepareAll();
    }
    syncControls();
    renderAll();
    writeHash();
  }

  // ---- interaction ---------------------------------------------------------------------
  function zoomAt(p, sx, sy, direction) {
    const [ix, iy] = toImage(sx, sy);
    let next;
    if (direction > 0) {
      next = ZOOM_LEVELS.find((z) => z > view.zoom * 1.0001);
    } else {
      next = [...ZOOM_LEVELS].reverse().find((z) => z < view.zoom / 1.0001);
    }
    if (next === undefined) {
      return;
    }
    const { w, h } = QC.size;
    view.zoom = next;
    view.cx = ix - (sx - w / 2) / next;
    view.cy = iy - (sy - h / 2) / next;
    view.fit = false;
    draw();
    writeHash();
  }

  function attach(p) {
    const c = p.canvas;
    c.addEventListener(
      "wheel",
      (ev) => {
        ev.preventDefault();
        const r = c.getBoundingClientRect();
        zoomAt(p, ev.clientX - r.left, ev.clientY - r.top, ev.deltaY < 0 ? 1 : -1);
      },
      { passive: false }
    );
    let drag = null;
    c.addEventListener("pointerdown", (ev) => {
      drag = { x: ev.clientX, y: ev.clientY };
      c.setPointerCapture(ev.pointerId);
    });
    c.addEventListener("pointermove", (ev) => {
      const r = c.getBoundingClientRect();
      const [ix, iy] = toImage(ev.clientX - r.left, ev.clientY - r.top);
      showPixel(p, Math.floor(ix), Math.floor(iy));
      if (drag) {
        view.cx -= (ev.clientX - drag.x) / view.zoom;
        view.cy -= (ev.clientY - drag.y) / view.zoom;
        view.fit = false;
        drag = { x: ev.clientX, y: ev.clientY };
        draw();
      }
    });
    const end = () => {
      if (drag) {
        drag = null;
        writeHash();
      }
    };
    c.addEventListener("pointerup", end);
    c.addEventListener("pointercancel", end);
    c.addEventListener("dblclick", () => {
      fitView();
      draw();
      writeHash();
    });
  }

  // Linear values under the pointer, in every panel (detections per frame).
  function showPixel(p, x, y) {
    const parts = [];
    for (const q of panels) {
      if (x < 0 || y < 0 || x >= q.width || y >= q.height) {
        continue;
      }
      const i = 3 * (y * q.width + x);
      const v = [0, 1, 2].map((c) => q.linear[i + c].toPrecision(4)).join(" ");
      parts.push(q.label + ": " + v);
    }
    $("pixel").textContent = parts.length ? "x " + x + ", y " + y + " \u2014 " + parts.join(" \u00b7 ") : "";
  }

  function build() {
    QC.size = viewSize();
    const grid = $("panels");
    const cols = Math.round((grid.clientWidth + 12) / (QC.size.w + 12)) || 1;
    grid.style.gridTemplateColumns = "repeat(" + Math.max(1, cols) + ", " + QC.size.w + "px)";
    const dpr = window.devicePixelRatio || 1;
    data.panels.forEach((d, i) => {
      const fig = document.createElement("figure");
      fig.className = "panel" + (d.kind === "truth" ? " truth" : "");
      const canvas = document.createElement("canvas");
      canvas.width = Math.round(QC.size.w * dpr);
      canvas.height = Math.round(QC.size.h * dpr);
      canvas.style.width = QC.size.w + "px";
      canvas.style.height = QC.size.h + "px";
      canvas.id = "panel-" + i;
      const cap = document.createElement("figcaption");
      const name = document.createElement("strong");
      name.textContent = d.label;
      const caption = document.createElement("span");
      cap.append(name, " ", caption);
      fig.append(canvas, cap);
      grid.append(fig);
      const offscreen = document.createElement("canvas");
      offscreen.width = d.width;
      offscreen.height = d.height;
      const p = {
        label: d.label,
        width: d.width,
        height: d.height,
        frames: d.frames,
        w_weights: d.w_weights,
        linear: R.decodeHalf(d.half, d.scale_log2),
        canvas,
        caption,
        offscreen,
        image: new ImageData(d.width, d.height),
        mantiuk: null,
      };
      panels.push(p);
      attach(p);
    });
  }

  function loadMantiuk() {
    return Promise.all(
      data.panels.map(
        (d, i) =>
          new Promise((resolve) => {
            const img = new Image();
            img.onload = () => {
              panels[i].mantiuk = img;
              resolve();
            };
            img.onerror = () => resolve();
            img.src = d.mantiuk06;
          })
      )
    );
  }

  function init() {
    parseHash();
    build();
    if (view.fit) {
      fitView();
    }
    $("tonemap").addEventListener("change", (e) => {
      state.tonemap = e.target.value;
      changed(false);
    });
    $("ev").addEventListener("input", (e) => {
      state.ev = Math.round(parseFloat(e.target.value) * 10) / 10;
      changed(false);
    });
    $("mesopic").addEventListener("change", (e) => {
      state.l0 = e.target.checked ? Math.round(parseFloat($("l0").value) * 10) / 10 : null;
      changed(true);
    });
    $("l0").addEventListener("input", (e) => {
      state.l0 = Math.round(parseFloat(e.target.value) * 10) / 10;
      changed(true);
    });
    $("lock").addEventListener("change", (e) => {
      state.lock = e.target.checked;
      changed(false);
    });
    $("fit").addEventListener("click", () => {
      fitView();
      draw();
      writeHash();
    });
    window.addEventListener("hashchange", () => {
      const before = JSON.stringify([state, view]);
      parseHash();
      if (JSON.stringify([state, view]) !== before) {
        changed(true);
      }
    });
    loadMantiuk().then(() => {
      changed(true);
      QC.ready = true;
      document.body.classList.add("ready");
    });
  }

  init();
})();
