"""quantacolor: colour burst photography for single-photon cameras.

Python face of the Rust library (Ma et al., "Seeing Photons in Color", SIGGRAPH 2023): numpy in
and out, keyword options with the command line's names and defaults. Every computation runs in
the Rust core with the GIL released; ``progress=`` takes a callable ``(stage, done, total)``.

>>> import quantacolor as qc
>>> cap = qc.simulate(frames=256, size=(128, 96), seed=1)
>>> linear = qc.reconstruct(cap)                 # float32 (H, W, 3), like the CLI's linear.npy
>>> qc.psnr(linear, cap.ground_truth)
>>> rgb8 = qc.display(linear, tonemap="global")  # uint8 (H, W, 3)
>>> qc.show(linear)                              # inline in Jupyter

Batch processing over a Dask cluster: :func:`quantacolor.batch.reconstruct_many`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._native import (
    RECONSTRUCTION_FILES,
    Capture,
    __version__,
    align,
    denoise,
    display,
    evaluate_images,
    reconstruct,
    reconstruct_dir,
    simulate,
)

__all__ = [
    "Capture",
    "Image",
    "align",
    "denoise",
    "display",
    "evaluate",
    "psnr",
    "reconstruct",
    "reconstruct_dir",
    "show",
    "simulate",
    "ssim",
    "RECONSTRUCTION_FILES",
    "__version__",
]


def evaluate(
    estimate: np.ndarray,
    truth: np.ndarray,
    border: int = 0,
    normalize_percentile: float = 99.5,
    lpips: bool = False,
) -> dict[str, float]:
    """Scores an estimate against ground truth as ``quantacolor eval`` does (paper §6, Table 2).

    ``border`` pixels are cropped from every side, both images are scaled so that the truth's
    ``normalize_percentile`` is 1 and clipped to [0, 1]; PSNR and SSIM (scikit-image's
    conventions) are taken on those linear values and again after sRGB encoding.

    Parameters
    ----------
    estimate : numpy.ndarray
        Linear RGB (H, W, 3), e.g. from :func:`reconstruct`.
    truth : numpy.ndarray
        Linear RGB (H, W, 3) of the same shape, e.g. ``Capture.ground_truth``.
    border : int
        Pixels cropped from every side, >= 0 (default 0; the README's examples use 16).
    normalize_percentile : float
        Percentile of ``truth``, in percent, scaled to 1; 0 = no scaling (default 99.5).
    lpips : bool
        Also compute LPIPS (AlexNet, v0.1) on the sRGB images (default False; about 0.2 s
        for 496x254 on 2 cores, no download).

    Returns
    -------
    dict
        ``psnr_linear`` and ``psnr_srgb`` (dB), ``ssim_linear`` and ``ssim_srgb`` (0 to 1),
        and ``lpips_srgb`` (lower is better) when ``lpips=True``.

    Raises
    ------
    TypeError, ValueError
        A bad argument or shapes that differ (the message names it).
    """
    return evaluate_images(estimate, truth, border, normalize_percentile, lpips)


def _pick(space: str, metric: str) -> str:
    if space not in ("linear", "srgb"):
        raise ValueError(f"space must be 'linear' or 'srgb', got {space!r}")
    return f"{metric}_{space}"


def psnr(
    estimate: np.ndarray,
    truth: np.ndarray,
    border: int = 0,
    normalize_percentile: float = 99.5,
    space: str = "linear",
) -> float:
    """PSNR of an estimate against ground truth with the CLI's conventions (paper §6).

    Parameters
    ----------
    estimate, truth : numpy.ndarray
        Linear RGB (H, W, 3) of the same shape.
    border : int
        Pixels cropped from every side, >= 0 (default 0).
    normalize_percentile : float
        Percentile of ``truth``, in percent, scaled to 1; 0 = no scaling (default 99.5).
    space : {"linear", "srgb"}
        Score the linear values (default "linear") or their sRGB encoding.

    Returns
    -------
    float
        PSNR in dB (see :func:`evaluate`).

    Raises
    ------
    ValueError
        An unknown ``space``, or a bad image (as :func:`evaluate`).
    """
    key = _pick(space, "psnr")
    return evaluate(estimate, truth, border, normalize_percentile)[key]


def ssim(
    estimate: np.ndarray,
    truth: np.ndarray,
    border: int = 0,
    normalize_percentile: float = 99.5,
    space: str = "linear",
) -> float:
    """SSIM of an estimate against ground truth with the CLI's conventions (paper §6).

    Parameters
    ----------
    estimate, truth : numpy.ndarray
        Linear RGB (H, W, 3) of the same shape.
    border : int
        Pixels cropped from every side, >= 0 (default 0).
    normalize_percentile : float
        Percentile of ``truth``, in percent, scaled to 1; 0 = no scaling (default 99.5).
    space : {"linear", "srgb"}
        Score the linear values (default "linear") or their sRGB encoding.

    Returns
    -------
    float
        SSIM, 1 for identical images (scikit-image's conventions; see :func:`evaluate`).

    Raises
    ------
    ValueError
        An unknown ``space``, or a bad image (as :func:`evaluate`).
    """
    key = _pick(space, "ssim")
    return evaluate(estimate, truth, border, normalize_percentile)[key]


class Image:
    """An 8-bit sRGB image that Jupyter shows inline (as PNG, ``_repr_png_``).

    Made by :func:`show`; wrap any display-ready image the same way.

    Parameters
    ----------
    rgb8 : numpy.ndarray
        sRGB pixels (H, W, 3), converted to contiguous uint8 (0 to 255), e.g. from
        :func:`display`.

    Attributes
    ----------
    rgb8 : numpy.ndarray
        The pixels, uint8 (H, W, 3).

    Raises
    ------
    ValueError
        ``rgb8`` not of shape (H, W, 3).
    """

    def __init__(self, rgb8: np.ndarray):
        rgb8 = np.ascontiguousarray(rgb8, dtype=np.uint8)
        if rgb8.ndim != 3 or rgb8.shape[2] != 3:
            raise ValueError(f"rgb8 must be (H, W, 3), got shape {rgb8.shape}")
        self.rgb8 = rgb8

    def _repr_png_(self) -> bytes:
        return _encode_png(self.rgb8)

    def __repr__(self) -> str:
        h, w, _ = self.rgb8.shape
        return f"quantacolor.Image({w}x{h} sRGB)"


def show(linear: np.ndarray, **options: Any) -> Image:
    """Renders a linear image for a Jupyter cell (paper §7): :func:`display` as an :class:`Image`.

    Parameters
    ----------
    linear : numpy.ndarray
        Linear RGB (H, W, 3), e.g. from :func:`reconstruct`.
    **options
        Those of :func:`display`, with its defaults: ``tonemap`` ({"global", "mantiuk06",
        "none"}, default "global"), ``mesopic``, ``exposure``, ``w_weights``, ``ccm``,
        ``frames``.

    Returns
    -------
    Image
        Shown inline when it is a cell's value; ``.rgb8`` holds the uint8 (H, W, 3) pixels.

    Raises
    ------
    TypeError, ValueError
        A bad argument (as :func:`display`).
    """
    return Image(display(linear, **options))


def _encode_png(rgb8: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 image (8-bit RGB, no interlace, filter 0 per row)."""
    import struct
    import zlib

    h, w, _ = rgb8.shape
    rows = np.concatenate([np.zeros((h, 1), np.uint8), rgb8.reshape(h, w * 3)], axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF
        )

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


def __getattr__(name: str) -> Any:
    # `quantacolor.batch` imports dask only when used.
    if name == "batch":
        import importlib

        return importlib.import_module(".batch", __name__)
    raise AttributeError(f"module 'quantacolor' has no attribute {name!r}")


