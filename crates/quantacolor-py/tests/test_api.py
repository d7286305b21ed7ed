"""The Python API against the CLI and the library: round trips, errors, determinism, GIL."""

import subprocess
import threading
import tomllib

import numpy as np
import pytest

import quantacolor as qc


def run_cli(cli, *args):
    r = subprocess.run([str(cli), *map(str, args)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r


def test_simulate_matches_cli(cli, tmp_path, capture_dirs):
    run_cli(cli, "simulate", "--frames", 64, "--size", "64x64", "--seed", 1,
            "--motion", "handheld", "--out", tmp_path / "c")
    for name in ["frames.npy", "cfa.npy", "ground_truth.npy", "hot_pixels.npy"]:
        assert (tmp_path / "c" / name).read_bytes() == (capture_dirs[0] / name).read_bytes(), name


@pytest.mark.parametrize(
    "options, flags",
    [
        ({}, []),
        ({"method": "naive"}, ["--method", "naive"]),
        ({"denoise": "none", "scale": 2}, ["--denoise", "none", "--scale", "2"]),
        ({"config": {"denoise": {"luma_gain": 2.0}}, "reference_frame": 10},
         ["--config", "CONFIG", "--reference-frame", "10"]),
    ],
)
def test_reconstruct_equals_cli_linear_npy(cli, tmp_path, capture_dirs, capture, options, flags):
    if "CONFIG" in flags:
        (tmp_path / "cfg.toml").write_text("[denoise]\nluma_gain = 2.0\n")
        flags = [str(tmp_path / "cfg.toml") if f == "CONFIG" else f for f in flags]
    run_cli(cli, "reconstruct", capture_dirs[0], "--out", tmp_path / "rec", *flags)
    expected = np.load(tmp_path / "rec" / "linear.npy")
    got = qc.reconstruct(capture, **options)
    assert got.dtype == np.float32
    assert got.shape == expected.shape
    assert np.array_equal(got, expected)


def test_capture_without_mask_gets_the_cli_hot_pixel_detection(cli, tmp_path):
    # A capture without a hot-pixel mask (512 frames: enough for the detector to find the
    # simulated hot pixels): Python opens it as the CLI does, detection included.
    cap = tmp_path / "nomask"
    run_cli(cli, "simulate", "--frames", 512, "--size", "64x64", "--seed", 1, "--out", cap)
    (cap / "hot_pixels.npy").unlink()
    meta = (cap / "capture.toml").read_text()
    (cap / "capture.toml").write_text(
        "\n".join(l for l in meta.splitlines() if not l.startswith("hot_pixels")) + "\n")
    run_cli(cli, "reconstruct", cap, "--out", tmp_path / "rec", "--denoise", "none")
    expected = np.load(tmp_path / "rec" / "linear.npy")
    assert np.array_equal(qc.reconstruct(qc.Capture.open(cap), denoise="none"), expected)
    plain = qc.reconstruct(qc.Capture.open(cap, detect_hot_pixels=False), denoise="none")
    assert not np.array_equal(plain, expected), "the detector found no hot pixel"


def test_reconstruct_dir_byte_identical_to_cli(cli, tmp_path, capture_dirs):
    cap = capture_dirs[1]
    run_cli(cli, "reconstruct", cap, "--out", tmp_path / "cli", "--tonemap", "mantiuk06")
    summary = qc.reconstruct_dir(cap, tmp_path / "py", tonemap="mantiuk06")
    assert summary["height"] == 64 and summary["frames_used"] == 64
    for name in ["linear.npy", "linear.exr", "preview.png"]:
        assert (tmp_path / "cli" / name).read_bytes() == (tmp_path / "py" / name).read_bytes()
    a = tomllib.loads((tmp_path / "cli" / "report.toml").read_text())
    b = tomllib.loads((tmp_path / "py" / "report.toml").read_text())
    del a["timings"], b["timings"]
    assert a == b


def test_reconstruct_dir_refuses_a_non_empty_out_dir_unless_overwrite(tmp_path, capture_dirs):
    """The CLI's rule: an output directory that holds files is refused before any work (so the
    error names it, not the missing capture), unless overwrite=True."""
    cap = capture_dirs[0]
    out = tmp_path / "rec"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError) as info:
        qc.reconstruct_dir(tmp_path / "no-such-capture", out, method="naive")
    assert str(out) in str(info.value) and "overwrite=True" in str(info.value), info.value
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]

    qc.reconstruct_dir(cap, out, method="naive", overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == sorted([*qc.RECONSTRUCTION_FILES, "notes.txt"])
    first = (out / "linear.npy").read_bytes()
    with pytest.raises(ValueError, match="overwrite=True"):
        qc.reconstruct_dir(cap, out, method="naive", denoise="bm3d")
    assert (out / "linear.npy").read_bytes() == first
    qc.reconstruct_dir(cap, out, method="naive", denoise="bm3d", overwrite=True)
    assert (out / "linear.npy").read_bytes() != first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"], "no staging left behind"

    empty = tmp_path / "empty"
    empty.mkdir()
    qc.reconstruct_dir(cap, empty, method="naive")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a directory"):
        qc.reconstruct_dir(cap, tmp_path / "file", method="naive", overwrite=True)


def test_from_arrays_packed_and_unpacked(capture):
    packed = capture.frames
    assert packed.dtype == np.uint8 and packed.shape == (64, 64, 8)
    bits = np.unpackbits(packed, axis=-1)[:, :, : capture.width]
    kw = dict(
        exposure_s=capture.exposure_s,
        dark_count_rate_hz=capture.dark_count_rate_hz,
        hot_pixels=capture.hot_pixels,
    )
    expected = qc.reconstruct(capture)
    for frames in [packed, bits, bits.astype(bool)]:
        c = qc.Capture.from_arrays(frames, capture.cfa, **kw)
        assert (c.frame_count, c.height, c.width) == (64, 64, 64)
        assert np.array_equal(c.frames, packed)
        assert np.array_equal(c.cfa, capture.cfa)
        assert c.ground_truth is None
        assert np.array_equal(qc.reconstruct(c), expected)


def test_odd_width_round_trip():
    rng = np.random.default_rng(0)
    bits = rng.random((5, 6, 13)) < 0.3
    cfa = rng.integers(0, 4, (6, 13), dtype=np.uint8)
    c = qc.Capture.from_arrays(bits, cfa, 1e-4)
    assert c.frames.shape == (5, 6, 2)
    assert np.array_equal(np.unpackbits(c.frames, axis=-1)[:, :, :13], bits)
    c2 = qc.Capture.from_arrays(c.frames, cfa, 1e-4)
    assert np.array_equal(c2.frames, c.frames)


def test_ground_truth_and_properties(capture, capture_dirs):
    truth = np.load(capture_dirs[0] / "ground_truth.npy")
    assert np.array_equal(capture.ground_truth, truth)
    assert capture.w_weights == (1.0, 1.0, 1.0)
    assert capture.reference_frame == 32
    assert capture.hot_pixels.dtype == np.bool_


def test_deterministic(capture):
    a = qc.reconstruct(capture)
    b = qc.reconstruct(capture)
    assert a.tobytes() == b.tobytes()


def test_stages(capture):
    al = qc.align(capture)
    assert al["flow"].dtype == np.float32 and al["flow"].ndim == 4
    assert al["flow"].shape[0] == len(al["block_center_frames"])
    assert al["flow"].shape[1:3] == (len(al["tile_centers_y"]), len(al["tile_centers_x"]))
    lin = qc.reconstruct(capture, denoise="none")
    den = qc.denoise(lin, frames=64)
    assert den.shape == lin.shape and not np.array_equal(den, lin)
    assert np.array_equal(qc.denoise(lin, frames=64, method="none"), lin)
    rgb = qc.display(lin)
    assert rgb.dtype == np.uint8 and rgb.shape == (64, 64, 3)
    assert not np.array_equal(qc.display(lin, tonemap="none"), rgb)
    # Low-light view: a fixed L0 with the number of frames merged, or "auto".
    for mesopic in (0.0, "auto"):
        low = qc.display(lin, mesopic=mesopic, frames=64)
        assert low.shape == rgb.shape and low.dtype == np.uint8
    truth = capture.ground_truth
    assert qc.psnr(truth, truth) == np.inf or qc.psnr(truth, truth) > 90
    assert qc.ssim(truth, truth) == pytest.approx(1.0)
    # The default reconstruction (chroma-BM3D) scores above the bare merge (+0.6 dB here).
    assert qc.psnr(qc.reconstruct(capture), truth) > qc.psnr(lin, truth) > 10
    scores = qc.evaluate(lin, truth, border=4)
    assert set(scores) == {"psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb"}
    assert scores["psnr_srgb"] == qc.psnr(lin, truth, border=4, space="srgb")


def test_align_camera_matches_the_cli_and_the_simulated_motion(cli, tmp_path):
    """`align()["camera"]` is `quantacolor align`'s camera.npy, and it maps reference-frame
    positions to where the simulator's motion.toml puts them (docs/motion.md)."""
    cap = tmp_path / "cap"
    capture = qc.simulate(frames=256, size=(128, 96), seed=4, motion="handheld", out=cap)
    al = qc.align(capture)
    camera = al["camera"]
    assert camera.dtype == np.float64 and camera.shape == (256, 2, 3)
    assert "flow" in al and "block_center_frames" in al
    run_cli(cli, "align", cap, "--out", tmp_path / "al")
    assert np.array_equal(np.load(tmp_path / "al" / "camera.npy"), camera)
    # The simulator's rigid map: q = R(θ)·(p − c) + c + (dy, dx).
    truth = tomllib.loads((cap / "motion.toml").read_text())
    c = np.array(truth["center"])
    ys, xs = np.mgrid[16:80:4, 16:112:4]
    p = np.stack([ys.ravel(), xs.ravel()], axis=1).astype(np.float64)
    errors = []
    for t in range(0, 256, 8):
        th = truth["theta_rad"][t]
        rot = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
        want = (p - c) @ rot.T + c + [truth["dy"][t], truth["dx"][t]]
        got = p @ camera[t, :, :2].T + camera[t, :, 2]
        errors.append(np.hypot(*(got - want).T))
    assert np.median(np.concatenate(errors)) < 0.3
    # At the reference frame the map is the identity.
    ref = capture.reference_frame
    assert np.allclose(camera[ref], [[1, 0, 0], [0, 1, 0]], atol=1e-6)
    with pytest.raises(ValueError, match="reference_frame"):
        qc.align(capture, reference_frame=256)


def test_progress_callback(capture):
    calls = []
    qc.reconstruct(capture, progress=lambda stage, done, total: calls.append((stage, done, total)))
    assert calls, "no progress reported"
    assert all(isinstance(s, str) and 0 <= d <= t for s, d, t in calls)
    # Through the last stage: the denoiser reports too, up to its total.
    denoise = [(d, t) for s, d, t in calls if s == "denoise"]
    assert denoise and denoise[-1][0] == denoise[-1][1], calls[-5:]

    def boom(stage, done, total):
        raise KeyError("stop")

    with pytest.raises(KeyError):
        qc.reconstruct(capture, progress=boom)


def test_gil_released(capture):
    """Two threads: reconstructions in one, a counter in the other. With a huge switch
    interval the GIL changes hands only when a thread lets go of it (the counter thread at each
    `sleep(0)`), so were the GIL held during `reconstruct` the counter could not move between
    the readings just before and just after the call (a GIL-holding C call such as
    `sum(range(10**7))` gives exactly 0 here)."""
    import sys
    import time

    counter = [0]
    deltas = []
    done = threading.Event()

    def work():
        try:
            for _ in range(3):
                before = counter[0]
                qc.reconstruct(capture, scale=2)
                deltas.append(counter[0] - before)
        finally:
            done.set()

    old = sys.getswitchinterval()
    sys.setswitchinterval(1000.0)
    try:
        t = threading.Thread(target=work)
        t.start()
        while not done.is_set():
            counter[0] += 1
            time.sleep(0)
        t.join()
    finally:
        sys.setswitchinterval(old)
    assert len(deltas) == 3
    assert all(d > 0 for d in deltas), deltas


BAD = np.zeros((4, 8, 8), np.uint8)
CFA = np.zeros((8, 8), np.uint8)


@pytest.mark.parametrize(
    "kwargs, exc, words",
    [
        (dict(frames=[[0]], cfa=CFA), TypeError, ["frames", "numpy array"]),
        (dict(frames=BAD.astype(np.float32), cfa=CFA), TypeError, ["frames", "dtype"]),
        (dict(frames=BAD[0], cfa=CFA), ValueError, ["frames", "3 dimensions"]),
        (dict(frames=BAD[:0], cfa=CFA), ValueError, ["frames", "T = 0"]),
        (dict(frames=BAD, cfa=CFA.astype(np.int64)), TypeError, ["cfa", "uint8"]),
        (dict(frames=BAD, cfa=CFA[None]), ValueError, ["cfa", "2 dimensions"]),
        (dict(frames=BAD, cfa=np.full((8, 8), 4, np.uint8)), ValueError, ["cfa", "code 4"]),
        (dict(frames=BAD, cfa=np.zeros((7, 8), np.uint8)), ValueError, ["frames", "height"]),
        (dict(frames=np.zeros((4, 8, 5), np.uint8), cfa=CFA), ValueError, ["frames", "last axis"]),
        (dict(frames=np.full((4, 8, 8), 2, np.uint8), cfa=CFA), ValueError, ["frames", "0 or 1"]),
        (dict(frames=BAD, cfa=CFA, hot_pixels=np.zeros((8, 8), np.uint8)), TypeError,
         ["hot_pixels", "bool"]),
        (dict(frames=BAD, cfa=CFA, hot_pixels=np.zeros((8, 7), bool)), ValueError,
         ["hot_pixels", "shape"]),
        (dict(frames=BAD, cfa=CFA, reference_frame=4), ValueError, ["reference_frame", "T = 4"]),
        (dict(frames=BAD, cfa=CFA, reference_frame=-1), ValueError, ["reference_frame", ">= 0"]),
        (dict(frames=BAD, cfa=CFA, exposure_s=0.0), ValueError, ["exposure_s"]),
        (dict(frames=BAD, cfa=CFA, w_weights=(1, 1)), ValueError, ["w_weights", "three"]),
    ],
)
def test_from_arrays_bad_input(kwargs, exc, words):
    kwargs.setdefault("exposure_s", 1e-4)
    with pytest.raises(exc) as info:
        qc.Capture.from_arrays(**kwargs)
    for w in words:
        assert w in str(info.value), (w, str(info.value))


@pytest.mark.parametrize(
    "call, exc, words",
    [
        (lambda c: qc.reconstruct("not a capture"), TypeError, ["capture", "Capture"]),
        (lambda c: qc.reconstruct(c, method="magic"), ValueError, ["method", "magic"]),
        (lambda c: qc.reconstruct(c, denoise="magic"), ValueError, ["denoise", "magic"]),
        (lambda c: qc.reconstruct(c, scale=5), ValueError, ["scale"]),
        (lambda c: qc.reconstruct(c, scale=0), ValueError, ["scale"]),
        (lambda c: qc.reconstruct(c, reference_frame=64), ValueError, ["reference frame 64"]),
        (lambda c: qc.reconstruct(c, config=[1]), TypeError, ["config", "dict"]),
        (lambda c: qc.reconstruct(c, config={"denoise": {"luma_gain": "x"}}), ValueError,
         ["config", "luma_gain"]),
        (lambda c: qc.reconstruct(c, config={"burst": {"refine": {"pases": 1}}}), ValueError,
         ["config", "burst.refine.pases"]),
        (lambda c: qc.reconstruct(c, sigma_y=-1.0), ValueError, ["sigma_y"]),
        (lambda c: qc.reconstruct(c, progress=3), TypeError, ["progress", "callable"]),
        (lambda c: qc.display(np.zeros((4, 4))), ValueError, ["linear", "(H, W, 3)"]),
        (lambda c: qc.display(np.zeros((4, 4, 3), np.int32)), TypeError, ["linear", "dtype"]),
        (lambda c: qc.display(np.zeros((4, 4, 3)), tonemap="x"), ValueError, ["tonemap"]),
        (lambda c: qc.display(np.zeros((4, 4, 3)), mesopic="dim"), ValueError, ["dim"]),
        (lambda c: qc.display(np.zeros((4, 4, 3)), mesopic=[1]), TypeError, ["mesopic"]),
        (lambda c: qc.display(np.zeros((4, 4, 3)), mesopic=0.0, frames=-1.0), ValueError,
         ["frames"]),
        (lambda c: qc.denoise(np.zeros((4, 4, 3)), frames=0), ValueError, ["frames"]),
        (lambda c: qc.psnr(np.zeros((4, 4, 3)), np.zeros((5, 4, 3))), ValueError, ["shape"]),
        (lambda c: qc.simulate(frames=0), ValueError, ["frames"]),
        (lambda c: qc.simulate(motion="wobble"), ValueError, ["motion"]),
        (lambda c: qc.simulate(sensor="cmos"), ValueError, ["sensor"]),
        (lambda c: qc.Capture.open("/nonexistent/capture"), OSError, ["/nonexistent/capture"]),
    ],
)
def test_bad_arguments(capture, call, exc, words):
    with pytest.raises(exc) as info:
        call(capture)
    for w in words:
        assert w in str(info.value), (w, str(info.value))


def test_open_bad_capture_names_file(tmp_path, capture_dirs):
    import shutil

    d = shutil.copytree(capture_dirs[0], tmp_path / "c")
    (d / "capture.toml").write_text("exposure_s = -1\n")
    with pytest.raises(ValueError, match="capture.toml"):
        qc.Capture.open(d)


def test_readme_python_snippet_runs():
    """The README's Python example, run as written (the docs cannot drift from the package)."""
    from conftest import REPO

    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("## Python"):]
    start = section.index("```python\n") + len("```python\n")
    code = section[start : section.index("```", start)]
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["linear"].shape == (254, 496, 3)
    assert namespace["rgb8"].dtype.name == "uint8"


def test_show_renders_a_png_for_jupyter(capture):
    import zlib

    linear = qc.reconstruct(capture, method="naive")
    image = qc.show(linear, tonemap="global")
    png = image._repr_png_()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    h, w, _ = linear.shape
    assert int.from_bytes(png[16:20], "big") == w and int.from_bytes(png[20:24], "big") == h
    # The pixels are display()'s: undo the filter-0 rows of the IDAT chunk.
    start = png.index(b"IDAT") + 4
    length = int.from_bytes(png[start - 8 : start - 4], "big")
    raw = np.frombuffer(zlib.decompress(png[start : start + length]), np.uint8)
    pixels = raw.reshape(h, 1 + w * 3)[:, 1:].reshape(h, w, 3)
    np.testing.assert_array_equal(pixels, qc.display(linear, tonemap="global"))
    assert repr(image) == f"quantacolor.Image({w}x{h} sRGB)"
    with pytest.raises(ValueError, match="H, W, 3"):
        qc.Image(np.zeros((4, 4), np.uint8))


def test_reconstruct_explains_itself():
    """help(quantacolor.reconstruct) lists the options, their allowed values and what comes back."""
    doc = qc.reconstruct.__doc__
    for text in ["Parameters", "Returns", "Raises", '"burst"', '"naive"', '"chroma-bm3d"',
                 "float32", "progress"]:
        assert text in doc, text
    for function, texts in [(qc.simulate, ['"fast-handheld"', '"jot"', "Returns"]),
                            (qc.display, ['"mantiuk06"', "uint8", "Returns"]),
                            (qc.reconstruct_dir, ['"mantiuk06"', "overwrite", "Raises"])]:
        for text in ["Parameters", *texts]:
            assert text in function.__doc__, (function.__name__, text)


def _public_api():
    """(name, object) of every public function, class and static method of the package:
    ``quantacolor.__all__`` (but its constants) and ``quantacolor.batch``."""
    import quantacolor.batch as batch

    api = [(f"quantacolor.{n}", getattr(qc, n)) for n in qc.__all__ if callable(getattr(qc, n))]
    api += [(f"quantacolor.batch.{n}", getattr(batch, n)) for n in batch.__all__]
    api += [("quantacolor.Capture.open", qc.Capture.open),
            ("quantacolor.Capture.from_arrays", qc.Capture.from_arrays)]
    return api


def _sections(doc):
    """The numpydoc sections of ``doc`` (title underlined with dashes) as {title: lines}."""
    import inspect

    lines = inspect.cleandoc(doc).splitlines()
    sections, title = {}, None
    for i, line in enumerate(lines):
        underline = lines[i + 1].strip() if i + 1 < len(lines) else ""
        if line.strip() and underline and set(underline) == {"-"} and len(underline) == len(line.strip()):
            title = line.strip()
            sections[title] = []
        elif title is not None and not (line.strip() and set(line.strip()) == {"-"}):
            sections[title].append(line)
    return sections


def _entries(lines):
    """The entries of a Parameters / Attributes section in order: [(name, text)]; ``a, b : t``
    gives an entry for each name, ``**options`` the name ``options``."""
    entries = []
    for line in lines:
        if line.strip() and not line[0].isspace():
            head = line.split(" : ")[0]
            names = [n.strip().lstrip("*") for n in head.split(",")]
            entries.extend([n, line] for n in names)
        elif entries:
            for entry in entries[-len(names):]:
                entry[1] += " " + line.strip()
    return [(n, t) for n, t in entries]


def _default_words(default):
    """How a literal default is written in a docstring (None when it is not a literal)."""
    if isinstance(default, bool):
        return [str(default)]
    if isinstance(default, str):
        return [f'"{default}"']
    if isinstance(default, (int, float)):
        return [str(default)] + ([str(int(default))] if float(default).is_integer() else [])
    if isinstance(default, tuple):
        return [str(default)]
    return None


def test_batch_all_names_every_public_function():
    import inspect

    import quantacolor.batch as batch

    defined = {name for name, obj in vars(batch).items()
               if inspect.isfunction(obj) and obj.__module__ == batch.__name__
               and not name.startswith("_")}
    assert defined == set(batch.__all__), defined ^ set(batch.__all__)


_API = _public_api()


@pytest.mark.parametrize("name,obj", _API, ids=[name for name, _ in _API])
def test_every_public_name_documents_its_signature(name, obj):
    """numpydoc docstrings that cannot drift: a summary line, Parameters listing exactly the
    signature's parameters in order (each default stated), Returns for every function."""
    import inspect

    doc = obj.__doc__
    assert doc and doc.strip().splitlines()[0].strip(), f"{name}: no summary line"
    sections = _sections(doc)
    if inspect.isclass(obj) and obj is qc.Capture:
        # No constructor: the properties are its interface, each with a docstring.
        properties = [n for n, v in vars(obj).items() if inspect.isgetsetdescriptor(v)]
        assert properties
        documented = [n for n, _ in _entries(sections.get("Attributes", []))]
        assert sorted(documented) == sorted(properties), name
        for p in properties:
            assert (getattr(obj, p).__doc__ or "").strip(), f"{name}.{p}: no docstring"
        with pytest.raises(TypeError):
            obj()
        return
    signature = inspect.signature(obj)
    params = [p for p in signature.parameters.values() if p.name not in ("self", "cls")]
    assert "Parameters" in sections, f"{name}: no Parameters section"
    entries = _entries(sections["Parameters"])
    assert [n for n, _ in entries] == [p.name for p in params], name
    for p, (_, text) in zip(params, entries):
        if p.default is inspect.Parameter.empty:
            continue
        assert "default" in text.lower(), f"{name}: {p.name} does not state its default"
        words = _default_words(p.default)
        if words is not None:
            assert any(w in text for w in words), f"{name}: {p.name} default {p.default!r}"
    if not inspect.isclass(obj):
        assert sections.get("Returns"), f"{name}: no Returns section"


def test_the_stub_matches_the_native_module():
    """_native.pyi names every native function, method and property with the run-time
    signature's parameters, kinds and (literal) defaults."""
    import ast
    import inspect
    from pathlib import Path

    from quantacolor import _native

    stub = ast.parse((Path(_native.__file__).parent / "_native.pyi").read_text())

    def check(node, runtime, where):
        params = [p for p in inspect.signature(runtime).parameters.values()
                  if p.name not in ("self", "cls")]
        a = node.args
        positional = [x.arg for x in a.args]
        stub_names = positional + [x.arg for x in a.kwonlyargs]
        assert stub_names == [p.name for p in params], where
        kw_only = {p.name for p in params if p.kind is p.KEYWORD_ONLY}
        assert {x.arg for x in a.kwonlyargs} == kw_only, where
        defaults = dict(zip(positional[len(positional) - len(a.defaults):], a.defaults))
        defaults.update({x.arg: d for x, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None})
        for p in params:
            if p.default is inspect.Parameter.empty:
                assert p.name not in defaults, (where, p.name)
            else:
                assert p.name in defaults, (where, p.name)
                if p.default is not Ellipsis:
                    stub_default = ast.literal_eval(defaults[p.name])
                    assert stub_default == p.default, (where, p.name, stub_default, p.default)

    seen = set()
    for node in stub.body:
        if isinstance(node, ast.FunctionDef):
            check(node, getattr(_native, node.name), node.name)
            seen.add(node.name)
        elif isinstance(node, ast.ClassDef):
            cls = getattr(_native, node.name)
            seen.add(node.name)
            props = set()
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    if any(getattr(d, "id", None) == "property" for d in item.decorator_list):
                        props.add(item.name)
                    else:
                        check(item, getattr(cls, item.name), f"{node.name}.{item.name}")
            runtime_props = {n for n, v in vars(cls).items() if inspect.isgetsetdescriptor(v)}
            assert props == runtime_props, props ^ runtime_props
    public = {n for n in dir(_native) if not n.startswith("_") and callable(getattr(_native, n))}
    assert public <= seen, public - seen
