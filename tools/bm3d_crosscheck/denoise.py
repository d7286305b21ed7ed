"""Run the reference `bm3d` package (Mäkinen, Azzari, Foi) on one greyscale image.

Usage: python denoise.py NOISY.npy SIGMA OUT.npy

Reads a 2D array, calls `bm3d.bm3d(noisy, sigma_psd=SIGMA, profile="np")` (both steps, the
package's normal profile) on the image as given (same intensity scale as SIGMA), writes the
estimate as float32 to OUT.npy and prints `seconds=<wall time of the bm3d call>`.

The package is under a non-commercial licence: it is only invoked here, never vendored or ported.
"""

import sys
import time

import numpy as np
import bm3d


def main() -> None:
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    noisy = np.load(sys.argv[1]).astype(np.float64)
    sigma = float(sys.argv[2])
    start = time.perf_counter()
    out = bm3d.bm3d(noisy, sigma_psd=sigma, profile="np")
    seconds = time.perf_counter() - start
    np.save(sys.argv[3], np.asarray(out, dtype=np.float32))
    print(f"seconds={seconds:.6f}")


if __name__ == "__main__":
    main()
