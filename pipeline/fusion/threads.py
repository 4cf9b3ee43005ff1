"""Open3D's CPU threads, limited where results must be the same from run to run.

Open3D runs ICP, RANSAC and normal estimation on oneAPI TBB threads and its screened
Poisson on threads of its own. With more than one thread the order in which partial
sums meet depends on scheduling: ICP transforms differ in their last bits from run
to run, and Poisson's vertices come out in another order with other last bits (a
triangle more or less after trimming: 57607 against 57608). Seeding RANSAC
(``o3d.utility.random.seed``) alone does not help. With one thread each of these is
a fixed sequence of operations, so fusion and meshing default to one thread
(``FuseSettings.threads``, ``PoseSettings.threads``, ``MeshSettings.threads``): the
same input gives the same bytes (docs/fusion.md, "Reproducibility").
"""

from __future__ import annotations

import contextlib

from ringscan.pipeline.formats.meshes import open3d_lib

__all__ = ["open3d_threads", "check_threads", "poisson_threads"]


def check_threads(owner: str, n) -> None:
    """``n`` must be an integer >= 0 (0: Open3D's own choice, every core)."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ValueError(f"{owner}.threads must be an integer >= 0 (0: every core), got {n!r}")


def poisson_threads(n: int) -> int:
    """Open3D's Poisson ``n_threads`` for a ``threads`` setting (0 -> -1, every core)."""
    return -1 if n == 0 else int(n)


@contextlib.contextmanager
def open3d_threads(n: int):
    """Inside the block Open3D uses at most ``n`` CPU threads (0: no limit); the
    limit before it is put back afterwards."""
    o3d = open3d_lib()
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(int(n))
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)
