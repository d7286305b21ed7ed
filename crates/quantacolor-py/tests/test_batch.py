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
