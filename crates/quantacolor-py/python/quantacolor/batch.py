"""Batch reconstruction of many capture directories on a Dask cluster.

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
import time
from pathlib import Path
from typing import Any, Iterable, Optional, Union

from . import RECONSTRUCTION_FILES

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["reconstruct_many", "output_complete"]


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
        own_client = client is None
        cluster = None
        if own_client:
            from dask.distributed import Client, LocalCluster

            cluster = LocalCluster(
                n_workers=n_workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",
            )
            client = Client(cluster)
        try:
            futures = [
                client.submit(_reconstruct_one, capture, out, options, pure=False)
                for _, capture, out in todo
            ]
            results = client.gather(futures)
        finally:
            if own_client:
                client.close()
                cluster.close()
        for (i, _, _), row in zip(todo, results):
            rows[i] = row
    return [r for r in rows if r is not None]
