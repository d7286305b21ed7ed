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
                            (qc.display, ['"mantiuk06"', "uint8", "Returns"])]:
        for text in ["Parameters", *texts]:
            assert text in function.__doc__, (function.__name__, text)
