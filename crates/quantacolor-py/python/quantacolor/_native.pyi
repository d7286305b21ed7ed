"""Type stubs of the native module (Rust, pyo3). See the docstrings at run time too."""

from os import PathLike
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike[str]]
_Progress = Optional[Callable[[str, int, int], object]]

__version__: str
RECONSTRUCTION_FILES: list[str]

class Capture:
    """T binary frames, the colour filter array and the metadata (paper §3, Eq. 1–4). Made by
    ``Capture.open``, ``Capture.from_arrays`` or ``simulate``; immutable."""

    @staticmethod
    def open(path: _Path, *, detect_hot_pixels: bool = True) -> Capture:
        """Opens and validates a capture directory (frames.npy memory-mapped, cfa.npy/cfa.png,
        capture.toml; ground_truth.npy when present). Without a hot-pixel mask in the capture,
        one is detected from its frames (as ``quantacolor reconstruct`` does) unless
        ``detect_hot_pixels=False``."""
    @staticmethod
    def from_arrays(
        frames: npt.NDArray[Union[np.uint8, np.bool_]],
        cfa: npt.NDArray[np.uint8],
        exposure_s: float,
        dark_count_rate_hz: float = 0.0,
        w_weights: Optional[Sequence[float]] = None,
        hot_pixels: Optional[npt.NDArray[np.bool_]] = None,
        reference_frame: Optional[int] = None,
        ground_truth: Optional[npt.NDArray[np.float32]] = None,
    ) -> Capture:
        """``frames``: uint8 (T, H, ceil(W/8)) packed MSB first, or bool/uint8 0/1 (T, H, W);
        ``cfa``: uint8 (H, W) with 0=R 1=G 2=B 3=W; ``exposure_s``: seconds per binary frame;
        ``dark_count_rate_hz``: counts/s; ``w_weights`` default (1, 1, 1); ``reference_frame``
        default T // 2."""
    @property
    def frames(self) -> npt.NDArray[np.uint8]:
        """Packed frames, uint8 (T, H, ceil(W/8)), MSB first (a copy)."""
    @property
    def frame_count(self) -> int:
        """Number of binary frames T."""
    @property
    def height(self) -> int:
        """Height H, pixels."""
    @property
    def width(self) -> int:
        """Width W, pixels."""
    @property
    def cfa(self) -> npt.NDArray[np.uint8]:
        """uint8 (H, W): 0=R 1=G 2=B 3=W."""
    @property
    def ground_truth(self) -> Optional[npt.NDArray[np.float32]]:
        """float32 (H, W, 3) true λ (detections per binary frame) of simulated captures."""
    @property
    def hot_pixels(self) -> Optional[npt.NDArray[np.bool_]]:
        """bool (H, W), True = hot or dead; None without a mask."""
    @property
    def exposure_s(self) -> float:
        """Exposure of one binary frame, seconds."""
    @property
    def dark_count_rate_hz(self) -> float:
        """Mean dark count rate of a pixel, counts per second."""
    @property
    def w_weights(self) -> tuple[float, float, float]:
        """(wR, wG, wB) of W = wR·R + wG·G + wB·B."""
    @property
    def reference_frame(self) -> int:
        """Frame index the reconstruction is registered to."""

def reconstruct(
    capture: Capture,
    method: Optional[str] = None,
    denoise: Optional[str] = None,
    scale: Optional[int] = None,
    reference_frame: Optional[int] = None,
    config: Optional[dict[str, Any]] = None,
    *,
    sigma_y: Optional[float] = None,
    sigma_c: Optional[float] = None,
    block_size: Optional[int] = None,
    max_sub_block_motion: Optional[float] = None,
    window: Optional[int] = None,
    progress: _Progress = None,
) -> npt.NDArray[np.float32]:
    """Linear RGB float32 (H·scale, W·scale, 3), identical to the CLI's linear.npy.

    ``method``: "burst" (default) or "naive" (the plain sum); ``denoise``: "chroma-bm3d"
    (default; "none" when ``method="naive"`` is given without ``denoise``), "bm3d" or "none"; ``scale``: 1 (default) to 4; ``config``: the keys of report.toml's ``[config]``.
    ``None`` keeps the value of ``config`` (whose defaults are the CLI's)."""

def reconstruct_dir(
    capture_dir: _Path,
    out_dir: _Path,
    method: Optional[str] = None,
    denoise: Optional[str] = None,
    scale: Optional[int] = None,
    reference_frame: Optional[int] = None,
    config: Optional[dict[str, Any]] = None,
    *,
    sigma_y: Optional[float] = None,
    sigma_c: Optional[float] = None,
    block_size: Optional[int] = None,
    max_sub_block_motion: Optional[float] = None,
    window: Optional[int] = None,
    tonemap: str = "global",
    mesopic: Optional[Union[float, str]] = None,
    ccm: Optional[Union[_Path, Sequence[Sequence[float]]]] = None,
    overwrite: bool = False,
    progress: _Progress = None,
) -> dict[str, Any]:
    """``quantacolor reconstruct CAPTURE_DIR --out OUT_DIR``: the same four files, written
    atomically. A non-empty ``out_dir`` is refused (ValueError) unless ``overwrite=True``."""

def align(
    capture: Capture,
    reference_frame: Optional[int] = None,
    block_size: Optional[int] = None,
    *,
    config: Optional[dict[str, Any]] = None,
    progress: _Progress = None,
) -> dict[str, Any]:
    """The motion estimation of ``reconstruct``: ``flow`` float32 (n_blocks, tiles_y,
    tiles_x, 2) (dy, dx) plus the keys of flow.toml (block_center_frames, block_start_frames,
    tile_centers_y, ...), and ``camera`` float64 (T, 2, 3): per frame the affine camera map
    taking a reference-frame position (y, x, 1) to frame t (docs/motion.md)."""

def denoise(
    linear: npt.NDArray[np.floating[Any]],
    frames: float,
    method: str = "chroma-bm3d",
    *,
    sigma_y: Optional[float] = None,
    sigma_c: Optional[float] = None,
    w_weights: Optional[Sequence[float]] = None,
    dark_counts_per_frame: float = 0.0,
    config: Optional[dict[str, Any]] = None,
) -> npt.NDArray[np.float32]:
    """Chroma-BM3D (default), colour BM3D or no denoising of a linear image (paper §4.3);
    ``frames`` (>= 1) sets the binomial Anscombe transform; ``w_weights`` default (1, 1, 1)."""

def display(
    linear: npt.NDArray[np.floating[Any]],
    tonemap: str = "global",
    mesopic: Optional[Union[float, str]] = None,
    exposure: Optional[float] = None,
    *,
    w_weights: Optional[Sequence[float]] = None,
    ccm: Optional[Union[_Path, Sequence[Sequence[float]]]] = None,
    frames: Optional[float] = None,
) -> npt.NDArray[np.uint8]:
    """8-bit sRGB (H, W, 3) as ``quantacolor display`` renders it (paper §7); ``w_weights``
    default (1, 1, 1)."""

def evaluate_images(
    estimate: npt.NDArray[np.floating[Any]],
    truth: npt.NDArray[np.floating[Any]],
    border: int = 0,
    normalize_percentile: float = 99.5,
    lpips: bool = False,
) -> dict[str, float]:
    """The scores of ``quantacolor.evaluate`` (paper §6): psnr_linear, ssim_linear, psnr_srgb,
    ssim_srgb (PSNR in dB), and lpips_srgb with ``lpips=True``."""

def simulate(
    scene: str = "builtin:chart",
    motion: str = "handheld",
    frames: int = 512,
    flux: float = 0.1,
    cfa: str = "rgbw-75-regular",
    sensor: str = "spad",
    seed: int = 1,
    size: tuple[int, int] = (496, 254),
    *,
    cfa_seed: int = 0,
    hot_fraction: float = 0.02,
    reference_frame: Optional[int] = None,
    out: Optional[_Path] = None,
    progress: _Progress = None,
) -> Capture:
    """``quantacolor simulate`` (same defaults; ``size`` is (width, height)); a Capture with
    ground truth, also written to ``out`` when given."""

# The steps of quantacolor.batch.reconstruct_video (a video made in pieces).
def video_prepare(
    capture_dir: _Path, parts_dir: _Path, stride: int, window: Optional[int] = None
) -> list[tuple[int, int, int, int, bool]]:
    """The video's frames (index, reference_frame, first_frame, end_frame, done); saves the
    capture's hot-pixel mask into ``parts_dir``."""

def video_parts(
    capture_dir: _Path,
    parts_dir: _Path,
    indices: Sequence[int],
    stride: int,
    window: Optional[int] = None,
    options: Optional[dict[str, Any]] = None,
) -> list[float]:
    """Reconstructs video frames ``indices`` into parts; the seconds each took."""

def video_assemble(
    capture_dir: _Path,
    parts_dir: _Path,
    out_dir: _Path,
    stride: int,
    window: Optional[int] = None,
    options: Optional[dict[str, Any]] = None,
) -> Any:
    """Streams every part into the video directory ``out_dir``; returns its path."""
