"""What two views' overlap fixes: the point-to-plane information of their matched points
and the rigid motions it leaves free (a sphere's turns, a cylinder's spin). Used by
:mod:`.turntable`'s refinement, which keeps the turntable pose along a free motion
(docs/fusion.md, "Symmetric objects")."""

from __future__ import annotations

import numpy as np

from ringscan.pipeline.formats.meshes import open3d_lib

__all__ = ["WEAK_MOTION_RATIO", "overlap_information", "weak_motions"]

WEAK_MOTION_RATIO = 5.0e-3
"""Which motions of a view its overlap with another view fixes. Point-to-plane ICP sees a
motion only as far as it moves the overlap's points along their normals: the overlap's
point-to-plane information (6 x 6, each rotation scaled by the overlap's RMS radius so that
every motion is in mm at the points) has one eigenvalue per motion, and a motion whose
eigenvalue is below this fraction of the largest one (it moves the points along their
normals by less than sqrt(5e-3) ~ 7 % of what the best-fixed motion does) is not fixed:
refinement keeps the turntable pose along it. Measured on 8-view scans (docs/fusion.md,
"Symmetric objects"): the three rotations of a sphere and the spin of a cylinder about
its axis 1e-5 to 3e-3; Spot, Blub, the goat head and a lumpy blob 1.4e-2 and above."""


# A rigid motion is m = (omega, v0): a rotation vector and the velocity it gives the origin,
# so a point x moves by omega x x + v0. A point
# p matched with a target point of normal n sees the motion only as n . (omega x p + v0) =
# omega . (p x n) + v0 . n: its row of the point-to-plane Jacobian is (p x n, n).


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _motion_frame(center: np.ndarray, scale: float) -> np.ndarray:
    """(6, 6) A taking a motion m = (omega, v0) to xi = (scale * omega, v0 + omega x center):
    the rotation as mm at ``scale`` from ``center``, the translation of ``center``."""
    A = np.eye(6)
    A[:3, :3] *= scale
    A[3:, :3] = -_skew(center)
    return A


def _matches(o3d, nns, pts: np.ndarray, dist: float) -> tuple[np.ndarray, np.ndarray]:
    """(indices into ``pts`` of the points whose nearest target point is within ``dist``, those target indices)."""
    idx, d2 = nns.knn_search(o3d.core.Tensor(pts), 1)
    ok = np.flatnonzero(np.sqrt(d2.numpy()[:, 0]) < dist)
    return ok, idx.numpy()[ok, 0].astype(np.int64)


def overlap_information(points: np.ndarray, target_points: np.ndarray, target_normals: np.ndarray, *,
                        max_distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The point-to-plane information of an overlap: how strongly each rigid motion of
    ``points`` moves them off the surface of ``target_points`` (unit ``target_normals``).

    Each point whose nearest target point lies within ``max_distance_mm`` adds j j^T, with
    j = (p x n, n): the row of point-to-plane ICP's Jacobian. Open3D's
    ``get_information_matrix_from_point_clouds`` is point-to-point: it counts a sphere's
    spin as fixed, since its points slide off their matches, but no surface moves.

    Returns:
        (H, matched): H (6, 6) for motions (omega, v0) about the origin, summed over the
        points of ``points`` that have a match (``matched``, (m, 3));
        ``weak_motions(H, matched)`` says which motions the overlap fixes.
    """
    o3d = open3d_lib()
    p = np.asarray(points, np.float64)
    q = np.asarray(target_points, np.float64)
    for name, a, n in (("points", p, None), ("target_points", q, None),
                       ("target_normals", np.asarray(target_normals), len(q))):
        if a.ndim != 2 or a.shape[1] != 3 or (n is not None and len(a) != n):
            raise ValueError(f"overlap_information: {name} must have shape ({'N' if n is None else n}, 3), "
                             f"got {a.shape}")
    if not max_distance_mm > 0:
        raise ValueError(f"overlap_information: max_distance_mm must be > 0, got {max_distance_mm}")
    if len(p) == 0 or len(q) == 0:
        return np.zeros((6, 6)), np.zeros((0, 3))
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(q))
    nns.knn_index()
    ok, idx = _matches(o3d, nns, p, max_distance_mm)
    n = np.asarray(target_normals, np.float64)[idx]
    # each row at its match on the target surface, where the plane n is tangent: a motion
    # that slides the surface along itself (a sphere's turn about its centre) moves no
    # target point off its plane; at the source point, up to a match distance away on a
    # curved surface, the same turn reads as fixed by ~(distance / radius)^2 (sparse ring
    # curves matched 1 mm apart on a 20 mm sphere: 1e-2 of the best-fixed motion)
    J = np.concatenate([np.cross(q[idx], n), n], axis=1)
    return J.T @ J, p[ok]


def _spectrum(H: np.ndarray, points: np.ndarray):
    """(eigenvalues ascending, eigenvectors, centre, scale) of ``H`` in the frame of ``points``:
    motions xi = (scale * omega, velocity of the centre) (:func:`_motion_frame`), the centre
    being the points' centroid and the scale their RMS distance from it."""
    pts = np.asarray(points, np.float64)
    c = pts.mean(axis=0) if len(pts) else np.zeros(3)
    scale = max(float(np.sqrt(np.mean(np.sum((pts - c) ** 2, axis=1)))) if len(pts) else 1.0, 1e-9)
    Ai = np.linalg.inv(_motion_frame(c, scale))
    Hx = Ai.T @ H @ Ai
    w, V = np.linalg.eigh(0.5 * (Hx + Hx.T))
    return w, V, c, scale


def weak_motions(H: np.ndarray, points: np.ndarray, *, ratio: float = WEAK_MOTION_RATIO,
                 axis: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[int, bool | None]:
    """Which motions an overlap's information ``H`` (:func:`overlap_information`) leaves free.

    The motions are measured at ``points`` (the matched points that made ``H``: rotations
    about their centroid, scaled by their RMS radius, so that every motion is in mm at the
    points); a motion is free when its eigenvalue is below ``ratio`` times the largest
    (:data:`WEAK_MOTION_RATIO`).

    Args:
        axis: (point, unit direction) of the turntable axis: also say whether a turn about it
            is free (its Rayleigh quotient below ``ratio`` times the largest eigenvalue).

    Returns:
        (the number of free motions, 0 to 6; whether the turn about ``axis`` is free, None
        without ``axis``). An empty ``H`` (no overlap) leaves all six free.
    """
    H = np.asarray(H, np.float64)
    if H.shape != (6, 6) or not np.all(np.isfinite(H)):
        raise ValueError(f"weak_motions: H must be a finite (6, 6) matrix, got shape {H.shape}")
    if np.ndim(points) != 2 or np.shape(points)[1] != 3:
        raise ValueError(f"weak_motions: points must have shape (N, 3), got {np.shape(points)}")
    if not 0 < ratio < 1:
        raise ValueError(f"weak_motions: ratio must lie in (0, 1), got {ratio}")
    w, V, c, scale = _spectrum(H, points)
    if not w[-1] > 0:
        return 6, None if axis is None else True
    free = int(np.count_nonzero(w < ratio * w[-1]))
    if axis is None:
        return free, None
    a0, a = (np.asarray(x, np.float64) for x in axis)
    xi = _motion_frame(c, scale) @ np.concatenate([a, np.cross(a0, a)])  # the turn: v0 = -a x a0
    Hx = V @ np.diag(w) @ V.T
    return free, bool(xi @ Hx @ xi < ratio * w[-1] * (xi @ xi))
