"""A test kernel around triangulation.fast_atan2 (kernels must live in files)."""

import numpy as np
import warp as wp

from ringscan.kernels.triangulation import fast_atan2


@wp.kernel
def fast_atan2_kernel(xy: wp.array(dtype=wp.vec2), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = fast_atan2(xy[i][1], xy[i][0])


def run_fast_atan2(xy: np.ndarray, device) -> np.ndarray:
    out = wp.zeros(len(xy), dtype=float, device=device)
    wp.launch(fast_atan2_kernel, len(xy), inputs=[wp.array(xy, dtype=wp.vec2, device=device)], outputs=[out],
              device=device)
    return out.numpy()
