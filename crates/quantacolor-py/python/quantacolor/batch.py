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

Every worker needs ``quantacolor`` installed (the README's wheel, ``pip install
dist/quantacolor-*.whl``: no Rust on the workers) and the capture and output paths visible at
the same names (a shared file system). One reconstruction uses every core of its worker
(rayon), so run one task per machine (``processes=1`` or ``threads_per_worker=1`` with one
worker per node).
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any, Iterable, Optional, Union

from . import RECONSTRUCTION_FILES

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["reconstruct_many", "reconstruct_video", "output_complete", "video_complete"]


def output_complete(out: PathLike) -> bool:
    """Whether a directory holds a finished reconstruction.

    Parameters
    ----------
    out : path
        An output directory of :func:`quantacolor.reconstruct_dir` or ``quantacolor
        reconstruct``.

    Returns
    -------
    bool
        True when ``out`` holds every file of a finished reconstruction
        (``quantacolor.RECONSTRUCTION_FILES``; ``report.toml`` is moved into place last).
    """
    return all((Path(out) / name).is_file() for name in RECONSTRUCTION_FILES)


def _interrupted(out: Path) -> bool:
    """True when ``out`` holds some, not all, of a reconstruction's files and nothing else: an
    interrupted commit (or a removed ``report.toml``), which a rerun replaces."""
    try:
        names = {p.name for p in out.iterdir()}
    except (FileNotFoundError, NotADirectoryError):
        return False
    return bool(names) and names <= set(RECONSTRUCTION_FILES)


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
    """Reconstructs many capture directories on a Dask cluster (paper §4, as
    :func:`quantacolor.reconstruct_dir`).

    Each capture goes to ``out_dir/<capture directory name>``, holding exactly what
    ``quantacolor reconstruct CAPTURE --out OUT`` writes with the same options (linear.npy,
    linear.exr and preview.png byte-identical; report.toml differs only in timings).

    Restartable: finished outputs are skipped (status ``"skipped"``), so an interrupted batch
    is resumed by running it again; an output holding only some of a reconstruction's files
    (an interrupted write) is redone. An output directory holding other files is refused, as
    ``reconstruct_dir`` refuses it, unless ``overwrite=True``. A capture that fails does not
    stop the others (status ``"failed"`` with the error).

    Parameters
    ----------
    captures : iterable of path
        Capture directories, with distinct directory names.
    out_dir : path
        Directory of the outputs, created if missing.
    client : dask.distributed.Client, optional
        The cluster to run on (a ``LocalCluster``'s, a scheduler's, dask-jobqueue's); see the
        module docstring. Default: a ``LocalCluster`` started and closed again.
    n_workers : int, optional
        Worker processes of that ``LocalCluster`` (default: dask's choice); ignored with
        ``client``.
    **options
        Those of :func:`quantacolor.reconstruct_dir` with its defaults (``method``,
        ``denoise``, ``scale``, ``config``, ``tonemap``, ``overwrite``, ...), but
        ``progress``.

    Returns
    -------
    list of dict
        One row per capture in input order: ``capture``, ``out``, ``status`` ("done",
        "skipped" or "failed"), ``error`` (None or the message), ``wall_seconds`` (s) and,
        for ones done now, ``reference_frame``, ``frames_used``, ``height``, ``width`` and
        ``seconds`` (stage time, s); ready for ``pandas.DataFrame(rows)``.

    Raises
    ------
    ValueError
        Two captures with the same directory name.
    TypeError
        A ``progress`` option (callbacks cannot run on remote workers).
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
            # The files of an interrupted run are this batch's own: replaced, not refused.
            opts = {**options, "overwrite": True} if _interrupted(out) else options
            todo.append((i, str(path), str(out), opts))
    if todo:
        out_root.mkdir(parents=True, exist_ok=True)
        with _OwnClient(client, n_workers) as c:
            futures = [
                c.submit(_reconstruct_one, capture, out, opts, pure=False)
                for _, capture, out, opts in todo
            ]
            results = c.gather(futures)
        for (i, _, _, _), row in zip(todo, results):
            rows[i] = row
    return [r for r in rows if r is not None]


def video_complete(out: PathLike) -> bool:
    """Whether a directory holds a finished video.

    Parameters
    ----------
    out : path
        An output directory of :func:`reconstruct_video` or ``quantacolor reconstruct
        --video``.

    Returns
    -------
    bool
        True when ``out`` holds ``video.toml``, which is moved into place last.
    """
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
    """Reconstructs a video of a long recording on a Dask cluster (paper §4 per frame;
    ``quantacolor reconstruct CAPTURE --out OUT_DIR --video --stride STRIDE --window WINDOW``).

    Writes the CLI's files byte for byte (``frame_NNNNN.png``, ``linear.npy`` (N, H, W, 3) and
    ``video.toml``, with ``capture`` given as the same path). Each video frame estimates its
    own motion (the CLI's default ``--video-motion per-frame``). Tasks of ``frames_per_task``
    consecutive video frames go to the workers.

    Restartable: finished frames wait in ``.<out_dir name>.video-parts`` beside ``out_dir``
    until every frame is done, a rerun makes only the missing ones, and a finished
    ``out_dir`` is skipped. The video is then written atomically and the parts removed. A
    failed frame raises (its error), keeping the finished ones for the next run.

    Parameters
    ----------
    capture : path
        Capture directory (docs/capture-format.md).
    out_dir : path
        Video directory, created if missing.
    stride : int
        Frames between consecutive video frames' reference frames, >= 1 (default 256).
    window : int, optional
        Binary frames each video frame is reconstructed from, centred on its reference frame,
        >= 1 (default None: every frame, which costs the whole recording per video frame;
        give a window, e.g. 2000, for long recordings).
    client : dask.distributed.Client, optional
        The cluster to run on. Default: a ``LocalCluster`` started and closed again.
    n_workers : int, optional
        Worker processes of that ``LocalCluster`` (default: dask's choice); ignored with
        ``client``.
    frames_per_task : int
        Video frames per Dask task, >= 1 (default 4).
    **options
        Those of :func:`quantacolor.reconstruct` with its defaults (``method``, ``denoise``,
        ``scale``, ``config``, ``sigma_y``, ``sigma_c``, ``block_size``,
        ``max_sub_block_motion``), but ``reference_frame``, ``window`` and ``progress``.

    Returns
    -------
    dict
        ``out``, ``status`` ("done" or "skipped"), ``frames`` (video frames; None when
        skipped), ``made`` (frames reconstructed by this call), ``frame_seconds`` (their
        times, s) and ``wall_seconds`` (s).

    Raises
    ------
    TypeError
        A ``progress``, ``reference_frame`` or ``window`` option, or an unknown one.
    ValueError
        A bad ``stride``, ``window``, ``frames_per_task`` or option value, or a bad capture.
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
