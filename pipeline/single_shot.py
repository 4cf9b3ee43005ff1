"""The paper's single-shot ``rings`` codec: find the ring lines, label each with its
ring index, hand the samples to triangulation (DESIGN §1, §4, §5).

One frame shows ``count`` identical bright rings. Every line centre is found to
sub-pixel precision (``kernels.ring_lines``); the centres are chained into
*curves*, which are cut into smooth *pieces* wherever two rings' images might meet
(sharp bends, gentle bends with a step in brightness); each piece gets its ring
index j by image topology (nesting order outward from the centre) checked against
everything the rig file tells: the calibrated camera and light, the working volume
and the reference plane z = 0. A piece whose index is not certain is dropped and
counted, never guessed.

The rule (docs/single_shot.md has the full statement and its limits):

1. **Orientation.** A lit point that the camera sees faces both the light and the
   camera, so the map from the projector's pixel grid to the camera image keeps
   its orientation there (the sign ``sigma`` of its Jacobian is the same as on the
   reference plane). Along a ring piece the polar angle phi of its points on the
   pattern therefore runs one way, and the side of the piece where the rings grow
   (its *outward* side) is fixed by that direction: outward is the side s (+-1,
   along the piece's normal n) with s = sigma * sign(dphi / ds), s measured along
   the tangent (-n_y, n_x). Of the two places where a camera ray meets a ring's
   quadric, the two almost always run in opposite directions: once the outward
   side of a piece is known, so is the root of each of its samples.
2. **Anchors.** (a) The reference plane: a piece whose rays meet z = 0 on one
   ring's circle (within ``plane_tolerance_px`` on the pattern) over a contiguous
   arc of at least ``plane_min_arc_deg`` lies on the plane: that ring is its index
   (an arc of a piece off the plane cannot keep a constant radius over so wide an
   arc). (b) The centre: the one closed loop with no other line inside it, around
   whose inside the pattern axis passes, is ring 0 if all of it has its roots on
   ring 0 (a loop of ring k >= 1 has rays that pass too far from the axis).
3. **Nesting.** Across the clean dark gap on a piece's outward side lies the next
   ring out (j + 1), on its inward side the next ring in (j - 1), when the surface
   between them is continuous. Labels spread from the anchors along such links,
   strongest link first; a link is used only when its gap holds no faint line and,
   in 3D, it is consistent with a continuous lit and visible surface between the
   two rings: both pieces have their root under their labels, the patch between
   the two triangulated curves faces both the light and the camera, it spans at
   most ``max_step_pitches`` ring pitches, and the new piece's arc of its ring does
   not overlap an arc already given to that ring (the light lights one point per
   ring and polar angle).
4. **Consistency.** After the spreading, every link that passes the 3D test under
   the labels it predicts must agree with the labels given, and the labelled
   pieces of one curve must agree; a disagreement drops the pieces and everything
   labelled through them.
"""

from __future__ import annotations

import heapq
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ringscan.kernels.ring_lines import LineSettings, detect_ring_lines, link_lines, ring_roots

from .patterns import PatternSpec
from .rig import ParallelLight, Rig, undistort_normalized

log = logging.getLogger(__name__)

SECTOR_BITS = 8
PHI_BINS = 720

__all__ = ["SingleShotSettings", "RingLabelling", "SECTOR_BITS", "extract_rings", "build_pieces", "label_ring_lines",
           "orientation_sign"]


@dataclass(frozen=True)
class SingleShotSettings:
    """Settings of the single-shot ``rings`` stage (line detection and labelling)."""

    lines: LineSettings = field(default_factory=LineSettings)
    """Line (ridge) detector thresholds."""
    min_piece_samples: int = 12
    """Pieces with fewer line centres are dropped (noise, scraps at occlusions)."""
    max_normal_turn_deg: float = 30.0
    """Neighbouring centres join the same piece only if their normals turn less."""
    max_piece_step_px: float = 0.8
    """... and if they lie within this distance of each other across the line."""
    fork_px: float = 0.9
    """A centre with two neighbours on one side that lie this far apart across the
    line is a fork (two rings merging where they crowd together): the centres
    within 2 px of it are left out, so that no piece holds two rings."""
    junction_px: float = 3.0
    """Centres up to this far apart are compared for junctions: where their normals
    turn by more than ``junction_deg`` + d / ``min_curvature_radius_px`` (radians)
    over their distance d, two rings' images meet (a ring ending on another where
    the object hides it, a kink): the centres within 2 px are left out, so that no
    piece holds two rings."""
    junction_deg: float = 12.0
    """See ``junction_px``: the turn allowed for noise in the normals."""
    min_curvature_radius_px: float = 8.0
    """See ``junction_px``: the tightest curve (camera px) a ring's own image may
    make; ring 0 of a pattern must appear larger than this to serve as the
    centre anchor."""
    segment_deg: float = 6.0
    """Curves are cut into pieces (the units that get labels) where two centres
    up to ``junction_px`` apart turn by more than this + d /
    ``segment_curvature_radius_px``, or by more than this while their contrast
    steps by ``segment_contrast_ratio``: where two rings' images might meet
    gently. A label never passes along a curve through such a cut, only across
    gaps from neighbouring rings."""
    segment_curvature_radius_px: float = 30.0
    """See ``segment_deg``."""
    segment_contrast_ratio: float = 1.5
    """See ``segment_deg``."""
    max_gap_px: float = 0.0
    """How far across the dark gap to look for the next ring (camera px);
    0: three times the widest ring spacing on the reference plane."""
    plane_tolerance_px: float = 0.5
    """Plane anchor: largest distance (projector px) between a sample's ray's
    meeting with z = 0 and its ring's circle."""
    plane_min_arc_deg: float = 45.0
    """Plane anchor: the samples on the plane must cover a contiguous arc of at
    least this many degrees of the ring."""
    closed_max_gap_deg: float = 20.0
    """A piece counts as a closed loop when its centres leave no angular gap wider
    than this around the piece's centroid."""
    bump_contrast: float = 2.0
    """A gap between two linked rings must be one clean valley: a rise and fall of
    this many grey levels inside it (a faint ring left undetected between them)
    marks the pair as crossing a hidden ring."""
    max_bump_fraction: float = 0.05
    """A link whose pairs cross a faint ring more often than this is not used."""
    min_link_pairs: int = 8
    """Least number of sample pairs linking two pieces for a label to spread."""
    min_pass_fraction: float = 0.8
    """Least fraction of a link's pairs that must pass the 3D test."""
    min_root_fraction: float = 0.8
    """Least fraction of a piece's samples that must have their root (the one
    whose orientation matches the piece's outward side) under its label."""
    max_step_pitches: float = 8.0
    """Longest 3D step between two linked samples, in ring pitches at the object
    (a continuous surface between two neighbouring rings up to ~83 degrees steep)."""
    min_root_separation_mm: float = 3.0
    """Where a sample's two meetings with its ring lie closer than this (the ray
    nearly grazes the ring's quadric), the orientation does not choose between
    them: the sample's root is left undecided (sector -1)."""
    min_view_cos: float = 0.05
    """The patch between two linked rings must face the camera at least this much
    (cosine of the angle between its normal and the view direction)."""
    min_light_cos: float = 0.05
    """... and the light at least this much."""

    def __post_init__(self):
        if not isinstance(self.lines, LineSettings):
            raise ValueError(f"SingleShotSettings.lines: expected LineSettings, got {type(self.lines).__name__}")
        for name in ("min_piece_samples", "min_link_pairs"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"SingleShotSettings.{name}: expected an integer >= 1, got {v!r}")
        for name in ("max_normal_turn_deg", "max_piece_step_px", "fork_px", "junction_px", "junction_deg",
                     "min_curvature_radius_px", "segment_deg", "segment_curvature_radius_px", "segment_contrast_ratio",
                     "min_root_separation_mm",
                     "plane_tolerance_px", "bump_contrast",
                     "plane_min_arc_deg", "closed_max_gap_deg", "max_step_pitches"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"SingleShotSettings.{name}: must be a finite number > 0, got {v!r}")
        for name in ("min_pass_fraction", "min_root_fraction", "min_view_cos", "min_light_cos", "max_bump_fraction"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 <= v <= 1):
                raise ValueError(f"SingleShotSettings.{name}: must be in [0, 1], got {v!r}")
        if not (isinstance(self.max_gap_px, (int, float)) and math.isfinite(self.max_gap_px) and self.max_gap_px >= 0):
            raise ValueError(f"SingleShotSettings.max_gap_px: must be >= 0, got {self.max_gap_px!r}")


@dataclass
class RingLabelling:
    """Labels of the line samples of one frame (NumPy, one entry per sample)."""

    ring: np.ndarray
    """(n,) int32 ring index j, -1 where the sample's piece was dropped."""
    root: np.ndarray
    """(n,) int8 which meeting of the ray with ring j is the surface (0 nearer,
    1 farther), -1 where the orientation does not decide (or no label)."""
    phi: np.ndarray
    """(n,) float32 polar angle (radians, on the pattern) of the chosen root; NaN
    where ``root`` is -1."""
    piece: np.ndarray
    """(n,) int32 piece of each sample (-1: in no piece)."""
    curve: np.ndarray
    """(n,) int32 curve of each sample (-1: in no curve)."""
    stats: dict
    """Counts: pieces, labelled pieces, anchors, links, conflicts, dropped samples."""


# ----------------------------------------------------------------------------- rig geometry (NumPy)


def _camera_rays(rig: Rig, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), unit world directions (n, 3)) of the rays through pixels uv."""
    cam = rig.camera
    x, y = undistort_normalized(cam, uv[:, 0], uv[:, 1])
    d = np.stack([x, y, np.ones_like(x)], -1) @ cam.R
    return cam.center, d / np.linalg.norm(d, axis=1, keepdims=True)


def _projector_offset(rig: Rig, spec: PatternSpec, X: np.ndarray) -> np.ndarray:
    """(n, 2) offset p - c on the projector grid of world points X (n, 3)."""
    li = rig.light
    if isinstance(li, ParallelLight):
        XL = X @ li.R.T + li.t
        p = XL[:, :2] / li.pixel_pitch_mm + li.axis_px
    else:
        import cv2

        p = cv2.projectPoints(np.ascontiguousarray(X, np.float64).reshape(-1, 1, 3), cv2.Rodrigues(li.R)[0],
                              li.t.astype(np.float64), li.K, li.dist)[0].reshape(-1, 2)
    return p - np.asarray(spec.center, np.float64)


def _light_ray(rig: Rig, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A point and unit direction (world) of the light's ray through projector pixel p."""
    li = rig.light
    if isinstance(li, ParallelLight):
        XL = np.array([li.pixel_pitch_mm * (p[0] - li.axis_px[0]), li.pixel_pitch_mm * (p[1] - li.axis_px[1]), 0.0])
        return li.R.T @ (XL - li.t), li.R.T @ np.array([0.0, 0.0, -1.0])
    import cv2

    n = cv2.undistortPoints(np.array([[p]], np.float64), li.K, li.dist).ravel()
    d = li.R.T @ np.array([n[0], n[1], 1.0])
    return li.center, d / np.linalg.norm(d)


def _to_camera(rig: Rig, X: np.ndarray) -> np.ndarray:
    import cv2

    cam = rig.camera
    return cv2.projectPoints(np.ascontiguousarray(X, np.float64).reshape(-1, 1, 3), cv2.Rodrigues(cam.R)[0],
                             cam.t.astype(np.float64), cam.K, cam.dist)[0].reshape(-1, 2)


def _light_dirs(rig: Rig, X: np.ndarray) -> np.ndarray:
    """Unit directions from points X toward the light."""
    li = rig.light
    if isinstance(li, ParallelLight):
        return np.broadcast_to(li.R.T @ np.array([0.0, 0.0, 1.0]), X.shape)
    d = li.center - X
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _plane_point(rig: Rig, spec: PatternSpec, p) -> np.ndarray:
    o, d = _light_ray(rig, np.asarray(p, np.float64))
    return o + (-o[2] / d[2]) * d


def orientation_sign(rig: Rig, spec: PatternSpec) -> int:
    """Sign of the Jacobian d(camera px) / d(projector px) on the reference plane
    at the pattern centre: the same on every surface that faces both the light
    and the camera (both see it from its front)."""
    c = np.asarray(spec.center, np.float64)
    q = _to_camera(rig, np.stack([_plane_point(rig, spec, c + e) for e in ((0, 0), (1, 0), (0, 1))]))
    det = np.linalg.det(np.stack([q[1] - q[0], q[2] - q[0]], 1))
    if not np.isfinite(det) or det == 0:
        raise ValueError("orientation_sign: the camera does not see the reference plane at the pattern centre")
    return 1 if det > 0 else -1


def _pitch_mm(rig: Rig, spec: PatternSpec) -> float:
    """One ring pitch at the object (mm), on the reference plane at the centre."""
    c = np.asarray(spec.center, np.float64)
    a = _plane_point(rig, spec, c)
    b = _plane_point(rig, spec, c + np.array([spec.pitch, 0.0]))
    return float(np.linalg.norm(b - a))


def _plane_ring_spacing_px(rig: Rig, spec: PatternSpec) -> float:
    """Widest image spacing (camera px) between neighbouring rings on the reference plane."""
    radii = spec.ring_radii()
    r = float(np.median(radii))
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    c = np.asarray(spec.center, np.float64)
    pts = []
    for rr in (r, r + spec.pitch):
        pts.append(np.stack([_plane_point(rig, spec, c + rr * np.array([math.cos(a), math.sin(a)])) for a in ang]))
    q0, q1 = _to_camera(rig, pts[0]), _to_camera(rig, pts[1])
    return float(np.max(np.linalg.norm(q1 - q0, axis=1)))


# ----------------------------------------------------------------------------- pieces


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
    from scipy.sparse.csgraph import breadth_first_order
    from scipy.spatial import cKDTree

    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    normal = np.asarray(normal, np.float64).reshape(-1, 2)
    pixel = np.asarray(pixel, np.int64).ravel()
    contrast = np.asarray(contrast, np.float64).ravel()
    n = uv.shape[0]
    if normal.shape != (n, 2) or pixel.shape != (n,) or contrast.shape != (n,):
        raise ValueError(f"build_pieces: uv {uv.shape}, normal {normal.shape}, pixel {pixel.shape} and contrast "
                         f"{contrast.shape} disagree")
    if n == 0:
        return Pieces(np.full(n, -1, np.int32), np.full(n, -1, np.int32), normal.copy())
    if pixel.min() < 0 or pixel.max() >= width * height or np.unique(pixel).size != n:
        raise ValueError("build_pieces: pixel indices must be distinct and inside the image")
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
    keep = (cos >= math.cos(math.radians(settings.max_normal_turn_deg))) & (across <= settings.max_piece_step_px)
    a, b = a[keep], b[keep]
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
        fork[e[np.abs(np.sum((uv[q1] - uv[q2]) * normal[e], 1)) > settings.fork_px]] = True
    # Sharp junctions and kinks: two centres d px apart (d <= ``junction_px``)
    # whose normals turn by more than ``junction_deg`` + d / ``min_curvature_radius_px``
    # (a ring ending on another where the object hides it, a kink where two
    # rings' images meet). A ring's own image turns by d / radius of curvature.
    tree = cKDTree(uv)
    pr = tree.query_pairs(settings.junction_px, output_type="ndarray").reshape(-1, 2)
    turn = np.arccos(np.clip(np.abs(np.sum(normal[pr[:, 0]] * normal[pr[:, 1]], 1)), 0.0, 1.0))
    dist = np.linalg.norm(uv[pr[:, 0]] - uv[pr[:, 1]], axis=1)
    fork[pr[turn > math.radians(settings.junction_deg) + dist / settings.min_curvature_radius_px].ravel()] = True
    drop = np.zeros(n, bool)
    if fork.any():
        for near in tree.query_ball_point(uv[fork], 2.0):
            drop[near] = True
        keep = ~drop[a] & ~drop[b]
        a, b = a[keep], b[keep]
    g = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)).tocsr()
    curve = _components(g, ~drop, settings.min_piece_samples)
    # Turn the normals to agree along each curve (breadth-first from one centre).
    sign = np.ones(n)
    first = np.full(int(curve.max()) + 1, -1, np.int64)
    valid = np.nonzero(curve >= 0)[0]
    first[curve[valid[::-1]]] = valid[::-1]
    for root in first:
        order, pred = breadth_first_order(g, int(root), directed=False, return_predecessors=True)
        for v in order[1:]:
            p = pred[v]
            sign[v] = sign[p] if normal[v] @ normal[p] >= 0 else -sign[p]
    # Pieces: cut where the curve bends or its brightness steps, except on the
    # innermost closed loops (a loop around nothing is one ring whatever its
    # curvature; the centre anchor looks for one).
    same = (curve[pr[:, 0]] == curve[pr[:, 1]]) & (curve[pr[:, 0]] >= 0)
    loops = _innermost_loops(uv, curve, settings.closed_max_gap_deg)
    same &= ~np.isin(curve[pr[:, 0]], loops)
    step = np.abs(np.log(np.maximum(contrast[pr[:, 0]], 1e-6) / np.maximum(contrast[pr[:, 1]], 1e-6)))
    soft = math.radians(settings.segment_deg)
    cut = same & ((turn > soft + dist / settings.segment_curvature_radius_px)
                  | ((turn > soft) & (step > math.log(settings.segment_contrast_ratio))))
    barrier = np.zeros(n, bool)
    barrier[pr[cut].ravel()] = True
    keep = ~barrier[a] & ~barrier[b]
    gs = sp.coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(n, n)).tocsr()
    piece = _components(gs, (curve >= 0) & ~barrier, settings.min_piece_samples)
    return Pieces(curve, piece, normal * sign[:, None])


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


# ----------------------------------------------------------------------------- labelling


@dataclass(frozen=True)
class _Link:
    """Sample pairs linking piece a (the owner) to piece b across a's ``side``."""

    side: int
    """0: across a's +normal side, 1: its -normal side."""
    b: int
    """The linked piece."""
    pa: np.ndarray
    """Positions (in piece a) of the linked samples."""
    pb: np.ndarray
    """Positions (in piece b) of the samples they meet."""
    bumps: float
    """Fraction of the pairs whose gap holds a faint line."""


class _Labeller:
    """Pieces, their links and the per-(piece, ring) roots; anchors and spreading."""

    def __init__(self, uv, normal, piece, curve, neighbour, bump, rig, spec, settings, device):
        self.uv = uv
        self.normal = normal
        self.piece = piece
        self.curve = curve
        self.nb = neighbour
        self.bump = bump
        self.rig = rig
        self.spec = spec
        self.s = settings
        self.device = device
        self.radii = spec.ring_radii().astype(np.float64)
        self.count = self.radii.size
        self.sigma = orientation_sign(rig, spec)
        self.pitch_mm = _pitch_mm(rig, spec)
        self.cam_center = rig.camera.center
        self.n_pieces = int(piece.max()) + 1 if piece.size and piece.max() >= 0 else 0
        order = np.argsort(piece, kind="stable")
        bounds = np.searchsorted(piece[order], np.arange(self.n_pieces + 1))
        self.members = [order[bounds[p]:bounds[p + 1]] for p in range(self.n_pieces)]
        self._roots: dict = {}
        self.links = self._collect_links()
        self.state = np.full(self.n_pieces, -1, np.int64)  # ring index
        self.out = np.zeros(self.n_pieces, np.int64)       # outward side (+1: +normal)
        self.parent = np.full(self.n_pieces, -1, np.int64)
        self.kind = [""] * self.n_pieces
        self.occupied = np.zeros((self.count, PHI_BINS), np.int64) - 1  # piece holding each (ring, phi bin)
        self.stats = {"pieces": self.n_pieces, "anchors_plane": 0, "anchors_centre": 0, "links_used": 0,
                      "links_rejected": 0, "conflicts": 0}
        self.curve_pieces: dict = {}
        for p, idx in enumerate(self.members):
            self.curve_pieces.setdefault(int(curve[idx[0]]), []).append(p)

    # -- per-(piece, ring) roots

    def roots(self, p: int, j: int) -> dict:
        """Both meetings of piece p's rays with ring j: points (k, 2, 3), tangent
        steps (k, 2, 3), phi (k, 2), orientation (k, 2) int8 (0: no root)."""
        key = (p, j)
        if key in self._roots:
            return self._roots[key]
        idx = self.members[p]
        uv = self.uv[idx]
        t = np.stack([-self.normal[idx, 1], self.normal[idx, 0]], 1)
        both = np.concatenate([uv, uv + 0.5 * t]).astype(np.float32)
        vol = self.rig.volume
        r = ring_roots(wp.array(both, dtype=wp.vec2, device=self.device), [self.radii[j]], camera=self._cam(),
                       light=self._light(), volume=(vol.z_min, vol.z_max, vol.r_max), center=self.spec.center)
        P = r.points.numpy()[:, 0]
        off = r.offset.numpy()[:, 0].astype(np.float64)
        val = r.valid.numpy()[:, 0]
        k = idx.size
        ok = np.stack([(val & 1) > 0, (val & 2) > 0], -1)
        phi = np.arctan2(off[..., 1], off[..., 0])
        dphi = (phi[k:] - phi[:k] + np.pi) % (2 * np.pi) - np.pi
        both_ok = ok[:k] & ok[k:]
        o = np.where(both_ok, self.sigma * np.sign(dphi), 0).astype(np.int8)
        res = {"P": P[:k].astype(np.float64), "T": (P[k:] - P[:k]).astype(np.float64), "phi": phi[:k], "o": o}
        self._roots[key] = res
        return res

    def _cam(self):
        if not hasattr(self, "_cam_model"):
            from .reconstruct import camera_model_for, light_model_for

            self._cam_model = camera_model_for(self.rig)
            self._light_model = light_model_for(self.rig)
        return self._cam_model

    def _light(self):
        self._cam()
        return self._light_model

    def choose(self, p: int, j: int, out: int, sel: np.ndarray | None = None) -> np.ndarray:
        """Root index per sample of piece p (or of its members ``sel``, positions in
        the piece) under ring j with outward side ``out``: the one root whose
        orientation matches, -1 where none or both do."""
        o = self.roots(p, j)["o"]
        if sel is not None:
            o = o[sel]
        m = o == out
        return np.where(m[:, 0] & ~m[:, 1], 0, np.where(m[:, 1] & ~m[:, 0], 1, -1))

    # -- links

    def _collect_links(self) -> dict:
        """links[A] = list of :class:`_Link` from piece A to its neighbours."""
        pos = np.zeros(self.piece.size, np.int64)
        for p, idx in enumerate(self.members):
            pos[idx] = np.arange(idx.size)
        links: dict = {p: [] for p in range(self.n_pieces)}
        for side in (0, 1):
            i = np.nonzero((self.piece >= 0) & (self.nb[:, side] >= 0))[0]
            k = self.nb[i, side]
            pa, pb = self.piece[i], self.piece[k]
            m = (pb >= 0) & (pb != pa)
            i, k, pa, pb = i[m], k[m], pa[m], pb[m]
            order = np.lexsort((pb, pa))
            i, k, pa, pb = i[order], k[order], pa[order], pb[order]
            if i.size == 0:
                continue
            cut = np.nonzero((np.diff(pa) != 0) | (np.diff(pb) != 0))[0] + 1
            for grp in np.split(np.arange(i.size), cut):
                if grp.size >= self.s.min_link_pairs:
                    links[int(pa[grp[0]])].append(_Link(side, int(pb[grp[0]]), pos[i[grp]], pos[k[grp]],
                                                        float(np.mean(self.bump[i[grp], side] > 0))))
        return links

    def predict(self, a: int, link: _Link) -> tuple[int, int] | None:
        """(ring, outward side) of the linked piece from piece a's state."""
        side, b, pa, pb = link.side, link.b, link.pa, link.pb
        ia, ib = self.members[a][pa], self.members[b][pb]
        f = np.sign(np.sum((self.uv[ia] - self.uv[ib]) * self.normal[ib], 1))
        fb = np.sign(f.sum())
        if fb == 0 or np.mean(f == fb) < 0.9:
            return None
        outward = (1 if side == 0 else -1) == self.out[a]
        j = int(self.state[a]) + (1 if outward else -1)
        if not 0 <= j < self.count:
            return None
        return j, int(-fb if outward else fb)

    def check(self, a: int, link: _Link, jb: int, ob: int) -> bool:
        """The test of a link a -> b under b's predicted state (jb, ob): a clean
        gap, roots under both labels, and a lit, visible patch between them."""
        s = self.s
        b, pa, pb = link.b, link.pa, link.pb
        if link.bumps > s.max_bump_fraction:
            return False
        ja, oa = int(self.state[a]), int(self.out[a])
        if np.mean(self.choose(b, jb, ob) >= 0) < s.min_root_fraction:
            return False
        ra = self.choose(a, ja, oa, pa)
        rb = self.choose(b, jb, ob, pb)
        use = (ra >= 0) & (rb >= 0)
        if use.sum() < max(s.min_link_pairs, s.min_pass_fraction * use.size):
            return False
        k = np.nonzero(use)[0]
        Ra, Rb = self.roots(a, ja), self.roots(b, jb)
        Xa = Ra["P"][pa[k], ra[k]]
        Xb = Rb["P"][pb[k], rb[k]]
        T = Ra["T"][pa[k], ra[k]]
        D = Xb - Xa
        n = np.cross(D, T)
        nl = np.linalg.norm(n, axis=1)
        n = n / np.maximum(nl, 1e-12)[:, None]
        L = _light_dirs(self.rig, Xa)
        n = n * np.where(np.sum(n * L, 1) < 0, -1.0, 1.0)[:, None]
        V = self.cam_center - 0.5 * (Xa + Xb)
        V /= np.linalg.norm(V, axis=1, keepdims=True)
        ok = ((nl > 0) & (np.sum(n * V, 1) >= s.min_view_cos) & (np.sum(n * L, 1) >= s.min_light_cos)
              & (np.linalg.norm(D, axis=1) <= s.max_step_pitches * self.pitch_mm))
        return ok.sum() >= max(s.min_link_pairs, s.min_pass_fraction * use.size)

    # -- arcs of each ring (one lit point per ring and polar angle)

    def bins(self, p: int, j: int, out: int) -> np.ndarray:
        r = self.choose(p, j, out)
        k = np.nonzero(r >= 0)[0]
        phi = self.roots(p, j)["phi"][k, r[k]]
        return np.unique(((phi + np.pi) / (2 * np.pi) * PHI_BINS).astype(np.int64) % PHI_BINS)

    def overlaps(self, p: int, j: int, out: int) -> bool:
        held = self.occupied[j, self.bins(p, j, out)]
        return np.count_nonzero((held >= 0) & (held != p)) > 2

    def assign(self, p: int, j: int, out: int, kind: str, parent: int = -1) -> None:
        self.state[p], self.out[p], self.kind[p], self.parent[p] = j, out, kind, parent
        b = self.bins(p, j, out)
        self.occupied[j, b] = np.where(self.occupied[j, b] < 0, p, self.occupied[j, b])

    # -- anchors

    def plane_anchors(self) -> list[tuple[int, int, int]]:
        """(piece, ring, outward side) of pieces that lie on the reference plane."""
        s = self.s
        out = []
        for p, idx in enumerate(self.members):
            C, d = _camera_rays(self.rig, self.uv[idx])
            ok = d[:, 2] < -1e-6
            if ok.sum() < s.min_piece_samples:
                continue
            t = -C[2] / np.where(ok, d[:, 2], -1.0)
            X = C + t[:, None] * d
            off = _projector_offset(self.rig, self.spec, X)
            rho = np.hypot(off[:, 0], off[:, 1])
            j = np.argmin(np.abs(rho[:, None] - self.radii[None]), 1)
            near = ok & (np.abs(rho - self.radii[j]) <= s.plane_tolerance_px)
            if near.sum() < s.min_piece_samples:
                continue
            jj = int(np.bincount(j[near]).argmax())
            on = near & (j == jj)
            phi = np.sort(np.arctan2(off[on, 1], off[on, 0]))
            if _longest_run_deg(phi, max_gap_deg=2.0) < s.plane_min_arc_deg:
                continue
            # the plane root's orientation gives the outward side
            R = self.roots(p, jj)
            dz = np.abs(R["P"][..., 2] - 0.0)
            dz[R["o"] == 0] = np.inf
            m = np.argmin(dz, 1)
            k = np.nonzero(on & (dz[np.arange(idx.size), m] < 0.5))[0]
            o = R["o"][k, m[k]]
            if k.size < s.min_piece_samples:
                continue
            side = int(np.sign(o.sum()))
            if side == 0 or np.mean(o == side) < 0.9:
                continue
            out.append((p, jj, side))
        return out

    def centre_anchor(self) -> tuple[list[int], int] | None:
        """(pieces, outward side) of the innermost closed loop around the pattern
        axis with nothing inside it, if it is consistent with ring 0."""
        import cv2

        s = self.s
        found = []
        for cid, plist in self.curve_pieces.items():
            idx = np.nonzero(self.curve == cid)[0]
            q = self.uv[idx]
            c = q.mean(0)
            order = _closed_loop_order(q, s.closed_max_gap_deg)
            if order is None:
                continue
            radial = np.sign(np.sum((q - c) * self.normal[idx], 1))
            side = int(np.sign(radial.sum()))
            if side == 0 or np.mean(radial == side) < 0.9:
                continue
            # nothing inside: no centre of another curve within the loop
            others = (self.curve >= 0) & (self.curve != cid)
            if np.any(_inside(self.uv[others], q[order])):
                continue
            # ring 0 under this outward side, on every piece of the loop
            X, good = [], True
            for p in plist:
                r = self.choose(p, 0, side)
                if np.mean(r >= 0) < s.min_root_fraction:
                    good = False
                    break
                k = np.nonzero(r >= 0)[0]
                X.append(self.roots(p, 0)["P"][k, r[k]])
            if not good or sum(len(x) for x in X) < s.min_piece_samples:
                continue
            # the pattern axis, at the loop's height, lies inside the loop
            o, d = _light_ray(self.rig, np.asarray(self.spec.center, np.float64))
            Xm = np.concatenate(X).mean(0)
            ci = _to_camera(self.rig, (o + np.dot(Xm - o, d) * d)[None])[0]
            poly = q[order].astype(np.float32).reshape(-1, 1, 2)
            if cv2.pointPolygonTest(poly, (float(ci[0]), float(ci[1])), False) < 0:
                continue
            found.append((list(plist), side))
        if len(found) != 1:
            if len(found) > 1:
                log.info("single shot: %d candidate centre loops: none used", len(found))
            return None
        return found[0]

    # -- spreading

    def spread(self) -> None:
        heap: list = []
        seq = 0

        def push(a):
            nonlocal seq
            for link in self.links[a]:
                heapq.heappush(heap, (-link.pa.size, seq, a, link))
                seq += 1

        anchors = [(p, j, o, "plane") for p, j, o in self.plane_anchors()]
        c = self.centre_anchor()
        if c is not None:
            anchors += [(p, 0, c[1], "centre") for p in c[0]]
        # Anchors that contradict each other (same piece, or overlapping arcs of
        # one ring) are not used.
        bad = set()
        for x in range(len(anchors)):
            for y in range(x + 1, len(anchors)):
                px, jx, ox, _ = anchors[x]
                py, jy, oy, _ = anchors[y]
                if px == py and (jx, ox) != (jy, oy):
                    bad |= {x, y}
                elif px != py and jx == jy and np.intersect1d(self.bins(px, jx, ox), self.bins(py, jy, oy)).size > 2:
                    bad |= {x, y}
        for x, (p, j, o, kind) in enumerate(anchors):
            if x in bad or self.state[p] >= 0:
                continue
            self.assign(p, j, o, kind)
            self.stats["anchors_plane"] += kind == "plane"
            self.stats["anchors_centre"] = int(self.stats["anchors_centre"] or kind == "centre")
            push(p)
        while heap:
            _, _, a, link = heapq.heappop(heap)
            b = link.b
            if self.state[b] >= 0:
                continue
            pred = self.predict(a, link)
            if pred is None or self.overlaps(b, *pred) or not self.check(a, link, *pred):
                self.stats["links_rejected"] += 1
                continue
            self.assign(b, pred[0], pred[1], "link", a)
            self.stats["links_used"] += 1
            push(b)

    def verify(self) -> np.ndarray:
        """Pieces to drop: both ends of every link that passes the 3D test under
        the labels it predicts but disagrees with the labels given, and every piece
        labelled through them."""
        bad = np.zeros(self.n_pieces, bool)
        for a in range(self.n_pieces):
            if self.state[a] < 0:
                continue
            for link in self.links[a]:
                b = link.b
                if self.state[b] < 0:
                    continue
                pred = self.predict(a, link)
                if pred is None or pred == (int(self.state[b]), int(self.out[b])):
                    continue
                if self.check(a, link, *pred):
                    bad[a] = bad[b] = True
                    self.stats["conflicts"] += 1
        # The pieces of one curve are one ring unless the curve joins two at a
        # junction that the cuts missed: labelled pieces of a curve must agree.
        for plist in self.curve_pieces.values():
            lab = [p for p in plist if self.state[p] >= 0]
            if len({(int(self.state[p]), int(self.out[p])) for p in lab}) > 1:
                bad[lab] = True
                self.stats["conflicts"] += 1
        if bad.any():
            # everything labelled through a dropped piece goes too
            changed = True
            while changed:
                inherit = (self.parent >= 0) & ~bad
                inherit[inherit] = bad[self.parent[inherit]]
                changed = bool(inherit.any())
                bad |= inherit
        return bad


def _longest_run_deg(phi_sorted: np.ndarray, *, max_gap_deg: float) -> float:
    """Longest contiguous arc (degrees) covered by sorted angles (radians) whose
    neighbours lie at most ``max_gap_deg`` apart (the circle wraps at +-180)."""
    if phi_sorted.size < 2:
        return 0.0
    a = np.degrees(phi_sorted)
    cut = np.nonzero(np.diff(a) > max_gap_deg)[0]
    starts = np.concatenate([[0], cut + 1])
    ends = np.concatenate([cut, [a.size - 1]])
    lengths = a[ends] - a[starts]
    wrap = 360.0 - (a[-1] - a[0])
    if wrap <= max_gap_deg:
        if cut.size == 0:
            return 360.0
        lengths[0] += lengths[-1] + wrap
    return float(lengths.max())


def label_ring_lines(
    uv: np.ndarray,
    normal: np.ndarray,
    pixel: np.ndarray,
    smoothed: wp.array,
    *,
    contrast: np.ndarray | None = None,
    rig: Rig,
    patterns: PatternSpec,
    settings: SingleShotSettings = SingleShotSettings(),
) -> RingLabelling:
    """Give each line sample its ring index (or -1), by the rule of this module.

    Args:
        uv: (n, 2) sub-pixel line centres (camera px).
        normal: (n, 2) unit normals across the lines.
        pixel: (n,) linear pixel index of each centre.
        smoothed: (H, W) float32 Warp array, the smoothed frame
            (``RingLines.smoothed``); its device runs the root computations.
        contrast: (n,) line contrast of each centre (cuts curves where it
            steps); None: no cuts by contrast.
        rig: the calibrated rig.
        patterns: the ``rings`` pattern set.
        settings: stage settings.

    Returns:
        :class:`RingLabelling`.
    """
    if patterns.codec != "rings":
        raise ValueError(f"label_ring_lines: patterns must be the 'rings' codec, got {patterns.codec!r}")
    cam = rig.camera
    contrast = np.ones(len(uv)) if contrast is None else contrast
    pcs = build_pieces(uv, normal, pixel, contrast, cam.width, cam.height, settings=settings)
    piece, curve, nrm = pcs.piece, pcs.curve, pcs.normal
    n = piece.size
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    ring = np.full(n, -1, np.int32)
    root = np.full(n, -1, np.int8)
    phi = np.full(n, np.nan, np.float32)
    stats = {"pieces": 0, "pieces_labelled": 0, "pieces_dropped": 0, "samples_in_pieces": int(np.sum(piece >= 0)),
             "samples_labelled": 0, "samples_root_undecided": 0, "samples_root_inconsistent": 0}
    if n == 0 or piece.max() < 0:
        return RingLabelling(ring, root, phi, piece, curve, stats)
    max_gap = settings.max_gap_px or min(400.0, max(10.0, 3.0 * _plane_ring_spacing_px(rig, patterns)))
    device = smoothed.device
    nb, _, bump = link_lines(wp.array(uv.astype(np.float32), dtype=wp.vec2, device=device),
                             wp.array(nrm.astype(np.float32), dtype=wp.vec2, device=device),
                             wp.array(curve, dtype=wp.int32, device=device), image=smoothed,
                             pixel=wp.array(np.asarray(pixel, np.int32), dtype=wp.int32, device=device),
                             max_gap=max_gap, bump_contrast=settings.bump_contrast)
    lab = _Labeller(uv, nrm, piece, curve, nb.numpy(), bump.numpy(), rig, patterns, settings, device)
    lab.spread()
    bad = lab.verify()
    for p, idx in enumerate(lab.members):
        if lab.state[p] < 0 or bad[p]:
            continue
        j, o = int(lab.state[p]), int(lab.out[p])
        r = lab.choose(p, j, o)
        R = lab.roots(p, j)
        oo = R["o"]
        inconsistent = ~np.any(oo == o, axis=1)  # no root runs the piece's way: not on this ring
        # where the ray nearly grazes the ring's quadric its two meetings close up
        # and their orientations cannot be told apart: leave the root undecided
        close = np.all(oo != 0, axis=1) & (np.linalg.norm(R["P"][:, 0] - R["P"][:, 1], axis=1)
                                           < settings.min_root_separation_mm)
        r = np.where(close, -1, r)
        keep = ~inconsistent
        ring[idx[keep]] = j
        k = np.nonzero(keep & (r >= 0))[0]
        root[idx[k]] = r[k]
        phi[idx[k]] = lab.roots(p, j)["phi"][k, r[k]]
        stats["samples_root_inconsistent"] += int(inconsistent.sum())
        stats["samples_root_undecided"] += int(np.sum(keep & (r < 0)))
    labelled = (lab.state >= 0) & ~bad
    stats.update({"pieces": lab.n_pieces, "pieces_labelled": int(labelled.sum()),
                  "pieces_dropped": int(lab.n_pieces - labelled.sum()), "samples_labelled": int(np.sum(ring >= 0))})
    stats.update({k: v for k, v in lab.stats.items() if k != "pieces"})
    stats["curves"] = int(curve.max()) + 1
    return RingLabelling(ring, root, phi, piece, curve, stats)


# ----------------------------------------------------------------------------- the reconstruct hook


def extract_rings(frames: wp.array, scan, settings, threads: int):
    """``reconstruct`` hook for the ``rings`` codec: (Samples, stats) of one view.

    Args:
        frames: (1, H, W) uint8/uint16 Warp stack (the ``rings`` frame).
        scan: the :class:`~ringscan.pipeline.scan.Scan`.
        settings: ``ReconstructSettings``; its ``single_shot`` block when it has
            one, else :class:`SingleShotSettings` defaults.
        threads: CPU threads for the row-run kernels.

    Returns:
        (``reconstruct.Samples`` of the labelled samples in raster order, stats
        with pixels_decoded, samples, the labelling counts and times_s
        {"sample": line detection, "decode": labelling}). ``sector`` holds the
        sector (``SECTOR_BITS`` bits) of the root that the orientation rule
        chose, -1 where it does not decide; stats["sector_bits"] says so.
    """
    from .reconstruct import Samples

    spec = scan.patterns
    if spec.codec != "rings":
        raise ValueError(f"extract_rings: codec {spec.codec!r} is not 'rings'")
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.shape[0] < 1:
        raise ValueError("extract_rings: frames must be a (1, H, W) Warp array")
    ss = getattr(settings, "single_shot", None) or SingleShotSettings()
    dev = frames.device
    t0 = time.perf_counter()
    lines = detect_ring_lines(frames, frame=0, settings=ss.lines, threads=threads)
    d = lines.numpy()
    t1 = time.perf_counter()
    lab = label_ring_lines(d["uv"], d["normal"], d["pixel"], lines.smoothed, contrast=d["contrast"], rig=scan.rig,
                           patterns=spec, settings=ss)
    keep = np.nonzero(lab.ring >= 0)[0]
    ring = lab.ring[keep]
    n_sec = 2 ** SECTOR_BITS
    phi = lab.phi[keep].astype(np.float64)
    sector = np.where(np.isfinite(phi), np.floor((np.nan_to_num(phi) + np.pi) / (2 * np.pi) * n_sec), -1)
    sector = np.clip(sector, -1, n_sec - 1).astype(np.int32)
    rho = (spec.rho0 + spec.pitch * ring).astype(np.float32)
    smp = Samples(
        uv=wp.array(d["uv"][keep], dtype=wp.vec2, device=dev),
        rho=wp.array(rho, dtype=wp.float32, device=dev),
        ring=wp.array(ring, dtype=wp.int32, device=dev),
        sector=wp.array(sector, dtype=wp.int32, device=dev),
        confidence=wp.array(d["confidence"][keep], dtype=wp.float32, device=dev),
        pixel=wp.array(d["pixel"][keep], dtype=wp.int32, device=dev),
    )
    wp.synchronize_device(dev)
    t2 = time.perf_counter()
    stats = {"pixels_decoded": int(keep.size), "samples": int(keep.size), "line_samples": len(lines),
             "sector_bits": SECTOR_BITS, **lab.stats, "times_s": {"sample": t1 - t0, "decode": t2 - t1}}
    log.info("rings: %d line centres, %d pieces, %d labelled (%d dropped), %d samples", len(lines),
             lab.stats["pieces"], lab.stats["pieces_labelled"], lab.stats["pieces_dropped"], keep.size)
    return smp, stats
