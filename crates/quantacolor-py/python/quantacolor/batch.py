"""Batch reconstruction on a Dask cluster: many capture directories, or the frames of one long
video.

:func:`reconstruct_video` spreads the frames of ``quantacolor reconstruct CAPTURE --video``
(per-frame motion, each frame from its ``window``) over the workers and writes the same files;
:func:`reconstruct_many` maps :func:`quantacolor.reconstruct_dir` (the library's
``quantacolor reconstruct``: same files, same bytes) over capture directories with
``dask.distributed``. It is restartable: an output directory that already holds every file of a
finished reconstruction is skipped, and outputs are written atomically, so a killed run leaves
no half-written result to be mistaken for a finished one.

Pointing it at a real cluster::

    from dask.distributed import Client
    client = Client("tcp://scheduler:8786")        # a running dask scheduler
    rows = reconstruct_many(paths, "out", client=client, denoise="chroma-bm3d")

or on SLURM with dask-jobqueue::

    from dask_jobqueue import SLURMCluster
    cluster = SLURMCluster(cores=16, processes=1, memory="32GB", walltime="04:00:00")
    cluster.scale(jobs=20)
    rows = reconstruct_many(paths, "out", client=Client(cluster))

Every worker needs ``quantacolor`` installed (``pip install ./crates/quantacolor-py``) and the
capture and output paths visible at the same names (a shared file system). One reconstruction
uses every core of its worker (rayon), so run one task per machine (``processes=1`` or
``threads_per_worker=1`` with one worker per node).
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any, Iterable, Optional, Union

from . import RECONSTRUCTION_FILES

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["reconstruct_many", "reconstruct_video", "output_complete"]


def output_complete(out: PathLike) -> bool:
    """True when ``out`` holds every file of a finished reconstruction (``report.toml`` is
    moved into place last)."""
    return all((Path(out) / name).is_file() for name in RECONSTRUCTION_FILES)


def _reconstruct_one(capture: str, out: str, options: dict[str, Any]) -> dict[str, Any]:
    """One task: reconstruct ``capture`` into ``out``; never raises (the row says why)."""
    import quantacolor

    start = time.perf_counter()
    row: dict[str, Any] = {"capture": capture, "out": out}
    try:
        summary = quantacolor.reconstruct_dir(capture, out, **options)
        row.update(summary)
        row["capture"], row["out"] = capture, out
        row["status"] = "done"
        row["error"] = None
    except Exception as e:  # reported in the table, the other captures go on
        row.update(status="failed", error=f"{type(e).__name__}: {e}")
    row["wall_seconds"] = time.perf_counter() - start
    return row


class _OwnClient:
    """``client``, or a ``LocalCluster`` of ``n_workers`` worker processes started for the
    duration of a ``with`` block."""

    def __init__(self, client: Optional[Any], n_workers: Optional[int]):
        self.client, self.n_workers, self.cluster = client, n_workers, None

    def __enter__(self) -> Any:
        if self.client is None:
            from dask.distributed import Client, LocalCluster

            self.cluster = LocalCluster(
                n_workers=self.n_workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",
            )
            self.client = Client(self.cluster)
        return self.client

    def __exit__(self, *exc: Any) -> None:
        if self.cluster is not None:
            self.client.close()
            self.cluster.close()


def reconstruct_many(
    captures: Iterable[PathLike],
    out_dir: PathLike,
    client: Optional[Any] = None,
    *,
    n_workers: Optional[int] = None,
    **options: Any,
) -> list[dict[str, Any]]:
    """Reconstructs every capture directory in ``captures`` into ``out_dir/<capture name>``.

    ``options`` are those of :func:`quantacolor.reconstruct_dir` (``method``, ``denoise``,
    ``scale``, ``config``, ``tonemap``, ...); each output directory holds exactly what
    ``quantacolor reconstruct CAPTURE --out OUT`` writes with the same options (linear.npy,
    linear.exr and preview.png byte-identical; report.toml differs only in timings).

    ``client`` is a ``dask.distributed.Client``; without one a ``LocalCluster`` with
    ``n_workers`` worker processes (dask's default when None) is started and closed again.

    Finished outputs are skipped (status ``"skipped"``), so an interrupted batch is resumed by
    running it again. A capture that fails does not stop the others (status ``"failed"`` with
    the error). Returns one row (dict) per capture in input order: ``capture``, ``out``,
    ``status``, ``error``, ``wall_seconds`` and, for finished ones, ``reference_frame``,
    ``frames_used``, ``height``, ``width``, ``seconds`` (stage time) — ready for
    ``pandas.DataFrame(rows)``.
    """
    capture_paths = [Path(c) for c in captures]
    out_root = Path(out_dir)
    names = [p.resolve().name for p in capture_paths]
    seen: dict[str, Path] = {}
    for name, path in zip(names, capture_paths):
        if name in seen:
            raise ValueError(
                f"captures: {seen[name]} and {path} would both write {out_root / name}; "
                "give captures distinct directory names"
            )
        seen[name] = path
    if "progress" in options:
        raise TypeError("options: progress callbacks cannot run on remote workers")
    rows: list[Optional[dict[str, Any]]] = [None] * len(capture_paths)
    todo = []
    for i, (path, name) in enumerate(zip(capture_paths, names)):
        out = out_root / name
        if output_complete(out):
            rows[i] = {"capture": str(path), "out": str(out), "status": "skipped", "error": None}
        else:
            todo.append((i, str(path), str(out)))
    if todo:
        out_root.mkdir(parents=True, exist_ok=True)
        with _OwnClient(client, n_workers) as c:
            futures = [
                c.submit(_reconstruct_one, capture, out, options, pure=False)
                for _, capture, out in todo
            ]
            results = c.gather(futures)
        for (i, _, _), row in zip(todo, results):
            rows[i] = row
    return [r for r in rows if r is not None]


def video_complete(out: PathLike) -> bool:
    """True when ``out`` holds a finished video (``video.toml`` is moved into place last)."""
    return (Path(out) / "video.toml").is_file()


def _video_parts_dir(out: Path) -> Path:
    """Where the finished frames of an unfinished video wait (beside ``out``)."""
    return out.parent / f".{out.name}.video-parts"


def _video_frames(
    capture: str, parts: str, indices: list[int], stride: int, window: Optional[int],
    options: dict[str, Any],
) -> list[float]:
    """One task: reconstruct the video frames ``indices`` into parts."""
    from . import _native

    return _native.video_parts(capture, parts, indices, stride, window, options)


def reconstruct_video(
    capture: PathLike,
    out_dir: PathLike,
    stride: int = 256,
    window: Optional[int] = None,
    client: Optional[Any] = None,
    *,
    n_workers: Optional[int] = None,
    frames_per_task: int = 4,
    **options: Any,
) -> dict[str, Any]:
    """Reconstructs a video of the capture directory ``capture`` into ``out_dir`` on a Dask
    cluster: the files of ``quantacolor reconstruct CAPTURE --out OUT_DIR --video --stride
    STRIDE --window WINDOW`` (``frame_NNNNN.png``, ``linear.npy`` (N, H, W, 3) and
    ``video.toml``, byte for byte, with ``capture`` given as the same path).

    A reference frame every ``stride`` frames; each video frame is reconstructed from the
    ``window`` frames centred on it (``None``: every frame, which costs the whole recording
    per video frame; give a window for long recordings). Tasks of ``frames_per_task``
    consecutive video frames go to the workers; ``options`` are those of
    :func:`quantacolor.reconstruct` but ``reference_frame``, ``window`` and ``progress``
    (``method``, ``denoise``, ``scale``, ``config``, ``sigma_y``, ``sigma_c``, ``block_size``,
    ``max_sub_block_motion``). Each frame estimates its own motion (the CLI's default
    ``--video-motion per-frame``).

    Restartable: finished frames wait in ``.<out_dir name>.video-parts`` beside ``out_dir``
    until every frame is done, a rerun makes only the missing ones, and a finished
    ``out_dir`` is skipped. The video is then written atomically and the parts removed.

    ``client`` is a ``dask.distributed.Client``; without one a ``LocalCluster`` of
    ``n_workers`` processes is started and closed again. A failed frame raises (its error),
    keeping the finished ones for the next run. Returns a dict: ``out``, ``status``
    (``"done"`` or ``"skipped"``), ``frames`` (video frames), ``made`` (frames reconstructed by
    this call), ``frame_seconds`` (their times) and ``wall_seconds``.
    """
    from . import _native

    start = time.perf_counter()
    out = Path(out_dir)
    if "progress" in options:
        raise TypeError("options: progress callbacks cannot run on remote workers")
    for key in ("reference_frame", "window"):
        if key in options:
            raise TypeError(f"options: {key} is set by the video")
    if frames_per_task < 1:
        raise ValueError(f"frames_per_task must be >= 1, got {frames_per_task}")
    row: dict[str, Any] = {"out": str(out), "made": 0, "frame_seconds": []}
    if video_complete(out):
        row.update(status="skipped", frames=None, wall_seconds=time.perf_counter() - start)
        return row
    cap = os.fspath(capture)
    parts = _video_parts_dir(out)
    plan = _native.video_prepare(cap, str(parts), stride, window)
    todo = [index for index, _, _, _, done in plan if not done]
    if todo:
        tasks = [todo[k : k + frames_per_task] for k in range(0, len(todo), frames_per_task)]
        with _OwnClient(client, n_workers) as c:
            futures = [
                c.submit(_video_frames, cap, str(parts), t, stride, window, options, pure=False)
                for t in tasks
            ]
            row["frame_seconds"] = [s for seconds in c.gather(futures) for s in seconds]
        row["made"] = len(todo)
    _native.video_assemble(cap, str(parts), str(out), stride, window, options)
    shutil.rmtree(parts, ignore_errors=True)
    row.update(status="done", frames=len(plan), wall_seconds=time.perf_counter() - start)
    return row
