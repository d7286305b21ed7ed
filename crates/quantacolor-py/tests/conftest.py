"""Shared fixtures: small simulated captures (64x64, 64 frames) and the CLI binary."""

import os
import shutil
from pathlib import Path

import pytest

import quantacolor as qc

REPO = Path(__file__).resolve().parents[3]

# Set by .ci/run: a test that would skip (a missing CLI binary or dask) fails instead, and a
# session with any skipped test fails, so CI never counts a skip as a pass.
REQUIRE_ALL = os.environ.get("QUANTACOLOR_REQUIRE_ALL_TESTS", "") not in ("", "0")


def skip_or_fail(why):
    if REQUIRE_ALL:
        pytest.fail(f"{why} (QUANTACOLOR_REQUIRE_ALL_TESTS is set, so it may not skip)")
    pytest.skip(why)


def pytest_sessionfinish(session, exitstatus):
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if REQUIRE_ALL and reporter is not None and reporter.stats.get("skipped"):
        print("\nQUANTACOLOR_REQUIRE_ALL_TESTS is set: skipped tests fail the run")
        session.exitstatus = 1


def cli_binary():
    """The `quantacolor` CLI: $QUANTACOLOR_CLI, else the workspace's release build."""
    env = os.environ.get("QUANTACOLOR_CLI")
    if env:
        return Path(env)
    path = REPO / "target" / "release" / "quantacolor"
    return path if path.is_file() else None


@pytest.fixture(scope="session")
def cli():
    path = cli_binary()
    if path is None:
        skip_or_fail("CLI binary not built (cargo build --release) and QUANTACOLOR_CLI unset")
    return path


@pytest.fixture(scope="session")
def capture_dirs(tmp_path_factory):
    """Three small simulated capture directories (different seeds and motions)."""
    root = tmp_path_factory.mktemp("captures")
    dirs = []
    for seed, motion in [(1, "handheld"), (2, "static"), (3, "pan")]:
        d = root / f"cap{seed}"
        qc.simulate(frames=64, size=(64, 64), seed=seed, motion=motion, out=d)
        dirs.append(d)
    return dirs


@pytest.fixture(scope="session")
def capture(capture_dirs):
    return qc.Capture.open(capture_dirs[0])


def copy_dir(src, dst):
    shutil.copytree(src, dst)
    return dst
