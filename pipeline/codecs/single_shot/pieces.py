"""Line centres -> curves -> pieces: the units that the single-shot labeller gives
ring labels (cut where two rings' images may meet: forks, junctions, kinks).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ringscan.pipeline.codecs.single_shot.settings import TUNING, SingleShotSettings

log = logging.getLogger(__name__)

__all__ = ["Pieces", "build_pieces"]


@dataclass
class Pieces:
    """Line centres chained into curves and cut into pieces (NumPy, one entry per centre)."""

    curve: np.ndarray
    """(n,) int32 curve id (a chain of neighbouring centres), -1 where in none."""
    piece: np.ndarray
    """(n,) int32 piece id: a smooth stretch of a curve (curves are cut wherever
    their image bends or their brightness steps), -1 where in none. Pieces are
    the units that get ring labels."""
    normal: np.ndarray
    """(n, 2) float64 normals turned to agree along each curve."""


def build_pieces(uv: np.ndarray, normal: np.ndarray, pixel: np.ndarray, contrast: np.ndarray, width: int,
                 height: int, *, settings: SingleShotSettings = SingleShotSettings()) -> Pieces:
    """Chain line centres into curves and cut those into smooth pieces.

    Neighbouring centres (8-neighbour pixels) join when their normals agree within
    ``max_normal_turn_deg`` and they lie within ``max_piece_step_px`` of each other
    across the line; centres at forks and sharp junctions (and within 2 px of
    them) are left out; curves shorter than ``min_piece_samples`` are dropped.
    Each curve is then cut into pieces wherever two of its centres at most
    ``junction_px`` apart turn by more than ``segment_deg`` + d /
    ``segment_curvature_radius_px``, or turn by more than ``segment_deg`` while
    their contrast differs by a factor above ``segment_contrast_ratio``.

    Args:
        uv: (n, 2) sub-pixel centres; normal: (n, 2) unit normals; pixel: (n,)
            linear pixel index of each centre (at most one centre per pixel);
            contrast: (n,) line contrast of each centre.
        width, height: the image size.

    Returns:
        :class:`Pieces`.
    """
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    uv, normal, pixel, contrast = _centre_arrays(uv, normal, pixel, contrast)
    n = uv.shape[0]
    if n == 0:
        return Pieces(np.full(n, -1, np.int32), np.full(n, -1, np.int32), normal.copy())
    if pixel.min() < 0 or pixel.max() >= width * height or np.unique(pixel).size != n:
        raise ValueError("build_pieces: pixel indices must be distinct and inside the image")
    a, b = _neighbour_links(uv, normal, pixel, width, height, settings)
    fork = _forks(uv, normal, a, b, settings)
    tree = cKDTree(uv)
    pairs = _junction_pairs(uv, normal, tree, settings)
    a, b, drop = _drop_forks(uv, tree, a, b, fork, pairs, settings)
    g = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)).tocsr()
    curve = _components(g, ~drop, settings.min_piece_samples)
    sign = _normal_signs(g, curve, normal)
    piece = _cut_pieces(uv, contrast, curve, a, b, pairs, settings)
    return Pieces(curve, piece, normal * sign[:, None])


def _centre_arrays(uv, normal, pixel, contrast) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The centres' uv, normal, pixel and contrast as flat arrays of the build's dtypes, checked to agree."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    normal = np.asarray(normal, np.float64).reshape(-1, 2)
    pixel = np.asarray(pixel, np.int64).ravel()
    contrast = np.asarray(contrast, np.float64).ravel()
    n = uv.shape[0]
    if normal.shape != (n, 2) or pixel.shape != (n,) or contrast.shape != (n,):
        raise ValueError(f"build_pieces: uv {uv.shape}, normal {normal.shape}, pixel {pixel.shape} and contrast "
                         f"{contrast.shape} disagree")
    return uv, normal, pixel, contrast


def _neighbour_links(uv: np.ndarray, normal: np.ndarray, pixel: np.ndarray, width: int, height: int,
                     settings: SingleShotSettings) -> tuple[np.ndarray, np.ndarray]:
    """Links (a, b) between 8-neighbour centres whose normals agree and that lie close across the line."""
    n = uv.shape[0]
    smap = np.full(width * height, -1, np.int64)
    smap[pixel] = np.arange(n)
    x, y = pixel % width, pixel // width
    A, B = [], []
    for dx, dy in ((1, 0), (0, 1), (1, 1), (-1, 1)):
        xx, yy = x + dx, y + dy
        ok = (xx >= 0) & (xx < width) & (yy < height)
        j = np.full(n, -1, np.int64)
        j[ok] = smap[yy[ok] * width + xx[ok]]
        m = j >= 0
        A.append(np.nonzero(m)[0])
        B.append(j[m])
    a, b = np.concatenate(A), np.concatenate(B)
    d = uv[b] - uv[a]
    cos = np.abs(np.sum(normal[a] * normal[b], 1))
    across = np.maximum(np.abs(np.sum(d * normal[a], 1)), np.abs(np.sum(d * normal[b], 1)))
    keep = (cos >= math.cos(math.radians(TUNING.max_normal_turn_deg))) & (across <= TUNING.max_piece_step_px)
    return a[keep], b[keep]


def _forks(uv: np.ndarray, normal: np.ndarray, a: np.ndarray, b: np.ndarray,
           settings: SingleShotSettings) -> np.ndarray:
    """(n,) bool: centres at a fork (two linked neighbours on one side that lie apart across the line)."""
    n = uv.shape[0]
    # Forks: two neighbours on the same side of a centre (along its tangent) that
    # lie apart across the line.
    ends, other = np.concatenate([a, b]), np.concatenate([b, a])
    tang = np.stack([-normal[ends, 1], normal[ends, 0]], 1)
    side = np.sign(np.sum((uv[other] - uv[ends]) * tang, 1))
    order = np.lexsort((side, ends))
    ends, other, side = ends[order], other[order], side[order]
    fork = np.zeros(n, bool)
    for k in (1, 2, 3):
        if ends.size <= k:
            break
        s = (ends[k:] == ends[:-k]) & (side[k:] == side[:-k])
        e, q1, q2 = ends[:-k][s], other[:-k][s], other[k:][s]
        fork[e[np.abs(np.sum((uv[q1] - uv[q2]) * normal[e], 1)) > TUNING.fork_px]] = True
    return fork


def _junction_pairs(uv: np.ndarray, normal: np.ndarray, tree, settings: SingleShotSettings) -> tuple:
    """Centre pairs within ``junction_px``: (pairs, turn, distance, junction), junction where they turn too sharply."""
    # Sharp junctions and kinks: two centres d px apart (d <= ``junction_px``)
    # whose normals turn by more than ``junction_deg`` + d / ``min_curvature_radius_px``
    # (a ring ending on another where the object hides it, a kink where two
    # rings' images meet). A ring's own image turns by d / radius of curvature.
    pr = tree.query_pairs(TUNING.junction_px, output_type="ndarray").reshape(-1, 2)
    turn = np.arccos(np.clip(np.abs(np.sum(normal[pr[:, 0]] * normal[pr[:, 1]], 1)), 0.0, 1.0))
    dist = np.linalg.norm(uv[pr[:, 0]] - uv[pr[:, 1]], axis=1)
    junction = turn > math.radians(TUNING.junction_deg) + dist / TUNING.min_curvature_radius_px
    return pr, turn, dist, junction


def _drop_forks(uv: np.ndarray, tree, a: np.ndarray, b: np.ndarray, fork: np.ndarray, pairs: tuple,
                settings: SingleShotSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leave out forks and sharp junctions (not on clean loops) and centres within 2 px: links kept and dropped mask."""
    import scipy.sparse as sp

    n = uv.shape[0]
    pr, _, _, junction = pairs
    # A small ring's image (ring 0 of a pattern with a small rho0) bends more
    # tightly than any junction test allows; a chain that closes on itself, alone,
    # with nothing inside and all of it on one ellipse is one ring whatever its
    # curvature: its own bends are neither forks nor junctions.
    g0 = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)).tocsr()
    loop = _clean_loops(uv, g0, tree, settings)
    fork &= ~loop
    junction &= ~(loop[pr[:, 0]] & loop[pr[:, 1]])
    fork[pr[junction].ravel()] = True
    drop = np.zeros(n, bool)
    if fork.any():
        for near in tree.query_ball_point(uv[fork], 2.0):
            drop[near] = True
        keep = ~drop[a] & ~drop[b]
        a, b = a[keep], b[keep]
    return a, b, drop


def _normal_signs(g, curve: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(n,) +-1 that turn the normals to agree along each curve (breadth-first from one centre)."""
    from scipy.sparse.csgraph import breadth_first_order

    n = normal.shape[0]
    sign = np.ones(n)
    first = np.full(int(curve.max()) + 1, -1, np.int64)
    valid = np.nonzero(curve >= 0)[0]
    first[curve[valid[::-1]]] = valid[::-1]
    for root in first:
        order, pred = breadth_first_order(g, int(root), directed=False, return_predecessors=True)
        for v in order[1:]:
            p = pred[v]
            sign[v] = sign[p] if normal[v] @ normal[p] >= 0 else -sign[p]
    return sign


def _cut_pieces(uv: np.ndarray, contrast: np.ndarray, curve: np.ndarray, a: np.ndarray, b: np.ndarray,
                pairs: tuple, settings: SingleShotSettings) -> np.ndarray:
    """(n,) int32 piece ids: the curves cut where they bend or their brightness steps."""
    import scipy.sparse as sp

    n = uv.shape[0]
    pr, turn, dist, _ = pairs
    # Pieces: cut where the curve bends or its brightness steps, except on the
    # innermost closed loops (a loop around nothing is one ring whatever its
    # curvature; the centre anchor looks for one).
    same = (curve[pr[:, 0]] == curve[pr[:, 1]]) & (curve[pr[:, 0]] >= 0)
    loops = _innermost_loops(uv, curve, TUNING.closed_max_gap_deg)
    same &= ~np.isin(curve[pr[:, 0]], loops)
    step = np.abs(np.log(np.maximum(contrast[pr[:, 0]], 1e-6) / np.maximum(contrast[pr[:, 1]], 1e-6)))
    soft = math.radians(TUNING.segment_deg)
    cut = same & ((turn > soft + dist / TUNING.segment_curvature_radius_px)
                  | ((turn > soft) & (step > math.log(TUNING.segment_contrast_ratio))))
    barrier = np.zeros(n, bool)
    barrier[pr[cut].ravel()] = True
    keep = ~barrier[a] & ~barrier[b]
    gs = sp.coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(n, n)).tocsr()
    return _components(gs, (curve >= 0) & ~barrier, settings.min_piece_samples)


def _clean_loops(uv: np.ndarray, g, tree, settings: SingleShotSettings) -> np.ndarray:
    """Centres of chains that are one small ring's whole image: the chain closes
    around its centroid (no angular gap over ``closed_max_gap_deg``), holds no
    other centre inside, has no centre of another chain within ``junction_px``
    of it, and every centre lies within ``loop_fit_px`` of one ellipse fitted to
    them all (two rings' images joined never fit one ellipse so closely).
    Returns an (n,) bool mask; only chains that bend more tightly than
    ``min_curvature_radius_px`` are looked at (larger loops need no rescue)."""
    import cv2
    from scipy.sparse.csgraph import connected_components

    n = uv.shape[0]
    out = np.zeros(n, bool)
    _, comp = connected_components(g, directed=False)
    order = np.argsort(comp, kind="stable")
    bounds = np.flatnonzero(np.diff(comp[order])) + 1
    for idx in np.split(order, bounds):
        if idx.size < max(settings.min_piece_samples, 6):
            continue
        q = uv[idx]
        span = q.max(0) - q.min(0)
        if span.min() > 4.0 * TUNING.min_curvature_radius_px:
            continue  # bends gently enough for the junction test
        if _closed_loop_order(q, TUNING.closed_max_gap_deg) is None:
            continue
        (cx, cy), (w, h), ang = cv2.fitEllipse(q.astype(np.float32).reshape(-1, 1, 2))
        if not (w > 0 and h > 0):
            continue
        t = np.radians(ang)
        d = q - (cx, cy)
        x = d[:, 0] * np.cos(t) + d[:, 1] * np.sin(t)
        y = -d[:, 0] * np.sin(t) + d[:, 1] * np.cos(t)
        sc = np.hypot(x / (0.5 * w), y / (0.5 * h))
        if np.max(np.hypot(x, y) * np.abs(1.0 - 1.0 / np.maximum(sc, 1e-9))) > settings.loop_fit_px:
            continue
        near = np.unique(np.concatenate(tree.query_ball_point(q, TUNING.junction_px)))
        if np.setdiff1d(near, idx).size:
            continue  # another chain touches it
        others = np.setdiff1d(np.arange(n), idx)
        order_q = _closed_loop_order(q, TUNING.closed_max_gap_deg)
        if np.any(_inside(uv[others], q[order_q])):
            continue
        out[idx] = True
    return out


def _closed_loop_order(q: np.ndarray, max_gap_deg: float) -> np.ndarray | None:
    """The order of points q around their centroid if they surround it with no
    angular gap wider than max_gap_deg (a closed loop), else None."""
    c = q.mean(0)
    ang = np.arctan2(q[:, 1] - c[1], q[:, 0] - c[0])
    order = np.argsort(ang)
    gaps = np.diff(np.concatenate([ang[order], ang[order][:1] + 2 * np.pi]))
    return order if np.degrees(gaps.max()) <= max_gap_deg else None


def _inside(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Which points (rounded to pixels) lie inside polygon poly (both (k, 2), px)."""
    import cv2

    lo = np.floor(poly.min(0)).astype(np.int64) - 1
    hi = np.ceil(poly.max(0)).astype(np.int64) + 1
    q = np.rint(points).astype(np.int64) - lo
    size = hi - lo + 1
    ok = np.all((q >= 0) & (q < size), axis=1)
    out = np.zeros(len(points), bool)
    if ok.any():
        mask = np.zeros((int(size[1]), int(size[0])), np.uint8)
        cv2.fillPoly(mask, [np.rint(poly - lo).astype(np.int32).reshape(-1, 1, 2)], 1)
        out[ok] = mask[q[ok, 1], q[ok, 0]] > 0
    return out


def _innermost_loops(uv: np.ndarray, curve: np.ndarray, max_gap_deg: float) -> list[int]:
    """Curves that close around their centroid with no centre of another curve inside."""
    out = []
    others = curve >= 0
    for cid in range(int(curve.max()) + 1):
        idx = np.nonzero(curve == cid)[0]
        order = _closed_loop_order(uv[idx], max_gap_deg)
        if order is None:
            continue
        if not np.any(_inside(uv[others & (curve != cid)], uv[idx][order])):
            out.append(cid)
    return out


def _components(g, allowed: np.ndarray, min_size: int) -> np.ndarray:
    """Connected components of graph g over the allowed nodes with at least
    min_size nodes, numbered 0.. in order of their first node; -1 elsewhere."""
    from scipy.sparse.csgraph import connected_components

    _, comp = connected_components(g, directed=False)
    sizes = np.bincount(comp[allowed], minlength=comp.max() + 1)
    good = allowed & (sizes[comp] >= min_size)
    uniq, lab = np.unique(np.where(good, comp, -1), return_inverse=True)
    lab = lab.ravel().astype(np.int32)
    if uniq[0] == -1:
        lab -= 1
    # number in order of first appearance
    out = np.full(lab.size, -1, np.int32)
    v = np.nonzero(lab >= 0)[0]
    if v.size:
        _, first = np.unique(lab[v], return_index=True)
        rank = np.empty(first.size, np.int32)
        rank[np.argsort(first)] = np.arange(first.size, dtype=np.int32)
        out[v] = rank[lab[v]]
    return out
