"""quantacolor.batch.reconstruct_many on a local two-worker Dask cluster."""

import subprocess

import pytest

import quantacolor as qc

distributed = pytest.importorskip("dask.distributed", reason="dask[distributed] not installed")


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    )
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


def test_reconstruct_many(client, cli, capture_dirs, tmp_path):
    from quantacolor.batch import output_complete, reconstruct_many

    out = tmp_path / "out"
    rows = reconstruct_many(capture_dirs, out, client=client, denoise="chroma-bm3d")
    assert [r["status"] for r in rows] == ["done"] * 3, rows
    assert [r["capture"] for r in rows] == [str(d) for d in capture_dirs]
    for d in capture_dirs:
        assert output_complete(out / d.name)
        ref = tmp_path / ("cli-" + d.name)
        r = subprocess.run(
            [str(cli), "reconstruct", str(d), "--out", str(ref), "--denoise", "chroma-bm3d"],
            capture_output=True,
            text=True,
        )
        assert r.returncode == 0, r.stderr
        for name in ["linear.npy", "linear.exr", "preview.png"]:
            assert (ref / name).read_bytes() == (out / d.name / name).read_bytes(), name

    # Restartable: finished outputs are skipped, a removed one is redone.
    (out / capture_dirs[1].name / "report.toml").unlink()
    rows = reconstruct_many(capture_dirs, out, client=client)
    assert [r["status"] for r in rows] == ["skipped", "done", "skipped"]


def test_interrupted_outputs_are_redone_and_other_files_refused(client, capture_dirs, tmp_path):
    """An output holding only some reconstruction files (an interrupted write) is redone; one
    holding other files is refused as reconstruct_dir refuses it, unless overwrite=True."""
    from quantacolor.batch import output_complete, reconstruct_many

    out = tmp_path / "out"
    interrupted, foreign = out / capture_dirs[0].name, out / capture_dirs[1].name
    interrupted.mkdir(parents=True)
    (interrupted / "linear.npy").write_bytes(b"half")
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    rows = reconstruct_many(capture_dirs[:2], out, client=client, method="naive")
    assert [r["status"] for r in rows] == ["done", "failed"], rows
    assert output_complete(interrupted)
    assert str(foreign) in rows[1]["error"] and "overwrite=True" in rows[1]["error"], rows[1]
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]

    rows = reconstruct_many(capture_dirs[:2], out, client=client, method="naive", overwrite=True)
    assert [r["status"] for r in rows] == ["skipped", "done"], rows
    assert output_complete(foreign) and (foreign / "notes.txt").read_text() == "mine"


def test_failures_are_reported(client, capture_dirs, tmp_path):
    from quantacolor.batch import reconstruct_many

    bad = tmp_path / "empty"
    bad.mkdir()
    rows = reconstruct_many([capture_dirs[0], bad], tmp_path / "out", client=client,
                            method="naive")
    assert rows[0]["status"] == "done"
    assert rows[1]["status"] == "failed" and "capture.toml" in rows[1]["error"]
    assert not (tmp_path / "out" / "empty").exists()


def test_duplicate_names_rejected(capture_dirs, tmp_path):
    from quantacolor.batch import reconstruct_many

    with pytest.raises(ValueError, match="distinct"):
        reconstruct_many([capture_dirs[0], capture_dirs[0]], tmp_path / "o")


def test_default_local_cluster(capture_dirs, tmp_path):
    from quantacolor.batch import reconstruct_many

    rows = reconstruct_many(capture_dirs[:1], tmp_path / "o", n_workers=1, method="naive")
    assert rows[0]["status"] == "done"


def test_reconstruct_video(client, cli, tmp_path):
    """The Dask video is the CLI's `--video --window` output byte for byte, restartable."""
    from quantacolor.batch import reconstruct_video

    cap = tmp_path / "long"
    qc.simulate(frames=192, size=(64, 64), seed=4, motion="handheld", out=cap)
    ref = tmp_path / "cli-video"
    args = ["--video", "--stride", "32", "--window", "64", "--denoise", "none"]
    r = subprocess.run(
        [str(cli), "reconstruct", str(cap), "--out", str(ref), *args],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    out = tmp_path / "video"
    row = reconstruct_video(cap, out, stride=32, window=64, client=client,
                            frames_per_task=2, denoise="none")
    assert row["status"] == "done" and row["frames"] == 6 and row["made"] == 6, row
    names = sorted(p.name for p in ref.iterdir())
    assert names == sorted(p.name for p in out.iterdir())
    assert names[:6] == [f"frame_{i:05d}.png" for i in range(6)]
    for name in names:
        assert (ref / name).read_bytes() == (out / name).read_bytes(), name
    assert not any(p.name.endswith("video-parts") for p in tmp_path.iterdir())

    # A finished video is skipped; an interrupted one resumes from its finished frames.
    assert reconstruct_video(cap, out, stride=32, window=64, client=client)["status"] == "skipped"
    from quantacolor import _native

    again = tmp_path / "again"
    parts = tmp_path / ".again.video-parts"
    _native.video_prepare(str(cap), str(parts), 32, 64)
    _native.video_parts(str(cap), str(parts), [0, 3], 32, 64, {"denoise": "none"})
    row = reconstruct_video(cap, again, stride=32, window=64, client=client, denoise="none")
    assert row["made"] == 4, row
    for name in names:
        assert (ref / name).read_bytes() == (again / name).read_bytes(), name

    with pytest.raises(ValueError, match="stride"):
        reconstruct_video(cap, tmp_path / "none", stride=1000, client=client)
    with pytest.raises(TypeError, match="unknown option"):
        reconstruct_video(cap, tmp_path / "bad", stride=32, window=64, client=client, tonemap="x")
    assert not (tmp_path / "none").exists() and not (tmp_path / "bad").exists()
