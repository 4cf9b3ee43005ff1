"""Ring samples as a view's sampler leaves them: one sample a camera pixel along concentric circles
(the neighbour model's kernels' tests: tests/kernels/test_ring_checks.py, test_cross_checks.py)."""

import numpy as np

WIDTH, HEIGHT = 320, 240


def ring_circle(k, r, cx=160.0, cy=120.0, arc=(0.0, 2 * np.pi)):
    """One sample a camera pixel along a circle of radius r (px), as a ring's crossings are sampled:
    (u, v, pixel, ring k) arrays."""
    th = np.linspace(arc[0], arc[1], int((arc[1] - arc[0]) * r * 1.3), endpoint=False)
    u, v = cx + r * np.cos(th), cy + r * np.sin(th)
    p = np.round(v).astype(int) * WIDTH + np.round(u).astype(int)
    _, first = np.unique(p, return_index=True)
    first = np.sort(first)
    return u[first], v[first], p[first], np.full(first.size, k)


def ring_view(pieces):
    """The pieces (ring_circle's) as one view: uv (n, 2) float32, pixel and ring (n,) int32."""
    u, v, p, k = (np.concatenate(a) for a in zip(*pieces))
    return np.stack([u, v], 1).astype(np.float32), p.astype(np.int32), k.astype(np.int32)
