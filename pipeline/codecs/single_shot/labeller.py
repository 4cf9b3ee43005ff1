"""The paper's single-shot ``rings`` codec: find the ring lines, label each with its
ring index, hand the samples to triangulation.

Line centres (``kernels.ring_lines``) are chained into curves and cut into smooth
pieces; each piece's index comes from its orientation, the anchors (reference
plane, ring 0), nesting across clean gaps and a final consistency check against the
rig; a piece whose index is not certain is dropped and counted, never guessed. The
rule and why: docs/design.md §10; the full statement and its limits:
docs/single_shot.md.
"""

from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.ring_links import link_lines, ring_roots
from ringscan.pipeline.codecs.single_shot.pieces import _closed_loop_order, _inside, build_pieces
from ringscan.pipeline.codecs.single_shot.settings import PHI_BINS, TUNING, RingLabelling, SingleShotSettings
from ringscan.pipeline.formats.patterns import PatternSpec
from ringscan.pipeline.formats.rig import Rig
from ringscan.pipeline.geometry import (
    camera_model_for,
    camera_pixels,
    camera_rays,
    light_directions,
    light_model_for,
    light_ray,
    plane_point,
    projector_offset,
)

log = logging.getLogger(__name__)


__all__ = ["orientation_sign", "label_ring_lines"]


# ----------------------------------------------------------------------------- rig geometry (NumPy)


def orientation_sign(rig: Rig, spec: PatternSpec) -> int:
    """Sign of the Jacobian d(camera px) / d(projector px) on the reference plane
    at the pattern centre: the same on every surface that faces both the light
    and the camera (both see it from its front)."""
    c = np.asarray(spec.center, np.float64)
    q = camera_pixels(rig, np.stack([plane_point(rig, c + e) for e in ((0, 0), (1, 0), (0, 1))]))
    det = np.linalg.det(np.stack([q[1] - q[0], q[2] - q[0]], 1))
    if not np.isfinite(det) or det == 0:
        raise ValueError("orientation_sign: the camera does not see the reference plane at the pattern centre")
    return 1 if det > 0 else -1


def _pitch_mm(rig: Rig, spec: PatternSpec) -> float:
    """One ring pitch at the object (mm), on the reference plane at the centre."""
    c = np.asarray(spec.center, np.float64)
    a = plane_point(rig, c)
    b = plane_point(rig, c + np.array([spec.pitch, 0.0]))
    return float(np.linalg.norm(b - a))


def _plane_ring_spacing_px(rig: Rig, spec: PatternSpec) -> float:
    """Widest image spacing (camera px) between neighbouring rings on the reference plane."""
    radii = spec.ring_radii()
    r = float(np.median(radii))
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    c = np.asarray(spec.center, np.float64)
    pts = []
    for rr in (r, r + spec.pitch):
        pts.append(np.stack([plane_point(rig, c + rr * np.array([math.cos(a), math.sin(a)])) for a in ang]))
    q0, q1 = camera_pixels(rig, pts[0]), camera_pixels(rig, pts[1])
    return float(np.max(np.linalg.norm(q1 - q0, axis=1)))


# ----------------------------------------------------------------------------- pieces


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
        """Keep the line samples, their pieces and links, and the rig, pattern set, settings and device the
        labelling reads.

        Size: the samples' per-sample arrays (uv, normal, piece, curve, neighbour, bump) come from three places
        (label_ring_lines's input, build_pieces, link_lines) and are kept as they are, plus the rig, pattern
        set, settings and device.
        """
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
        self.rejected = np.zeros(self.n_pieces, bool)  # a link into the piece was tried and failed its test
        self.plane_like = np.zeros(self.n_pieces, bool)  # most of its rays meet z = 0 on a ring's circle
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
                if grp.size >= TUNING.min_link_pairs:
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
        if link.bumps > TUNING.max_bump_fraction:
            return False
        ja, oa = int(self.state[a]), int(self.out[a])
        if np.mean(self.choose(b, jb, ob) >= 0) < TUNING.min_root_fraction:
            return False
        ra = self.choose(a, ja, oa, pa)
        rb = self.choose(b, jb, ob, pb)
        use = (ra >= 0) & (rb >= 0)
        if use.sum() < max(TUNING.min_link_pairs, TUNING.min_pass_fraction * use.size):
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
        L = light_directions(self.rig, Xa)
        n = n * np.where(np.sum(n * L, 1) < 0, -1.0, 1.0)[:, None]
        V = self.cam_center - 0.5 * (Xa + Xb)
        V /= np.linalg.norm(V, axis=1, keepdims=True)
        ok = ((nl > 0) & (np.sum(n * V, 1) >= s.min_view_cos) & (np.sum(n * L, 1) >= s.min_light_cos)
              & (np.linalg.norm(D, axis=1) <= TUNING.max_step_pitches * self.pitch_mm))
        return ok.sum() >= max(TUNING.min_link_pairs, TUNING.min_pass_fraction * use.size)

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
            C, d = camera_rays(self.rig, self.uv[idx])
            ok = d[:, 2] < -1e-6
            if ok.sum() < s.min_piece_samples:
                continue
            t = -C[2] / np.where(ok, d[:, 2], -1.0)
            X = C + t[:, None] * d
            off = projector_offset(self.rig, X, self.spec.center)
            rho = np.hypot(off[:, 0], off[:, 1])
            j = np.argmin(np.abs(rho[:, None] - self.radii[None]), 1)
            near = ok & (np.abs(rho - self.radii[j]) <= TUNING.plane_tolerance_px)
            self.plane_like[p] = near.sum() >= 0.5 * idx.size
            if near.sum() < s.min_piece_samples:
                continue
            jj = int(np.bincount(j[near]).argmax())
            on = near & (j == jj)
            phi = np.sort(np.arctan2(off[on, 1], off[on, 0]))
            if _longest_run_deg(phi, max_gap_deg=2.0) < TUNING.plane_min_arc_deg:
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
            order = _closed_loop_order(q, TUNING.closed_max_gap_deg)
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
                if np.mean(r >= 0) < TUNING.min_root_fraction:
                    good = False
                    break
                k = np.nonzero(r >= 0)[0]
                X.append(self.roots(p, 0)["P"][k, r[k]])
            if not good or sum(len(x) for x in X) < s.min_piece_samples:
                continue
            # the pattern axis, at the loop's height, lies inside the loop
            o, d = light_ray(self.rig, np.asarray(self.spec.center, np.float64))
            Xm = np.concatenate(X).mean(0)
            ci = camera_pixels(self.rig, (o + np.dot(Xm - o, d) * d)[None])[0]
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
                self.rejected[b] = True
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

    Size: the stage's one public entry point: over a third of its length is its signature, its documentation and
    the stats dictionary's initial counts; the labelling itself is _Labeller's (spread, verify, choose), and the
    loop here writes each labelled piece's samples and counts them.
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
             "samples_labelled": 0, "samples_root_undecided": 0, "samples_root_inconsistent": 0,
             "pieces_dropped_by_reason": {"unreached": 0, "link_rejected": 0, "conflict": 0},
             "samples_labelled_off_plane": 0, "pieces_off_plane_dropped": 0}
    if n == 0 or piece.max() < 0:
        return RingLabelling(ring, root, phi, piece, curve, stats)
    max_gap = settings.max_gap_px or min(400.0, max(10.0, 3.0 * _plane_ring_spacing_px(rig, patterns)))
    device = smoothed.device
    nb, gap, bump = link_lines(wp.array(uv.astype(np.float32), dtype=wp.vec2, device=device),
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
                                           < TUNING.min_root_separation_mm)
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
    stats.update(_dropped_report(lab, bad, ring, settings))
    nb = nb.numpy()
    gap = np.where(nb >= 0, gap.numpy(), 0.0).astype(np.float32)
    return RingLabelling(ring, root, phi, piece, curve, stats, gap, nb.astype(np.int32), nrm.astype(np.float32))


def _dropped_report(lab: _Labeller, bad: np.ndarray, ring: np.ndarray, settings: SingleShotSettings) -> dict:
    """Why pieces were dropped, and whether anything off the reference plane got
    a label: ``pieces_dropped_by_reason`` ({"unreached": no anchor and no link led
    to it, "link_rejected": the links into it failed the 3D test, "conflict":
    dropped by the consistency step}), ``samples_labelled_off_plane`` (labelled
    samples whose root lies more than ``off_plane_mm`` above z = 0; a sample whose
    root is undecided counts by its lower meeting), ``pieces_off_plane_dropped``
    and, when pieces off the plane were dropped and no sample off it got a label,
    ``object_unlabelled``: one sentence for the user."""
    reasons = {"unreached": 0, "link_rejected": 0, "conflict": 0}
    off_dropped = off_samples = 0
    labelled_off = 0
    for p, idx in enumerate(lab.members):
        if lab.state[p] >= 0 and not bad[p]:
            j = int(lab.state[p])
            r = lab.choose(p, j, int(lab.out[p]))
            P = lab.roots(p, j)["P"]
            z = np.where(r >= 0, P[np.arange(idx.size), np.maximum(r, 0), 2], P[:, :, 2].min(1))
            labelled_off += int(np.sum((ring[idx] >= 0) & (z > settings.off_plane_mm)))
            continue
        why = "conflict" if bad[p] else "link_rejected" if lab.rejected[p] else "unreached"
        reasons[why] += 1
        if not lab.plane_like[p]:
            off_dropped += 1
            off_samples += idx.size
    out = {"pieces_dropped_by_reason": reasons, "samples_labelled_off_plane": labelled_off,
           "pieces_off_plane_dropped": off_dropped}
    if off_dropped and labelled_off == 0:
        why = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in reasons.items() if n)
        hint = []
        if lab.stats["anchors_centre"] == 0:
            hint.append("no centre anchor: ring 0 was not seen as one closed loop around the pattern centre (hidden, "
                        "shadowed, crossed by another line, or too small in the image: a larger rho0 helps)")
        if reasons["link_rejected"]:
            hint.append("the links from the rings on the plane failed the 3D test (the object's silhouette lies "
                        "between them)")
        out["object_unlabelled"] = (f"no line off the reference plane got a ring label: {off_dropped} piece(s) off the "
                                    f"plane ({off_samples} line centres) dropped ({why})"
                                    + (": " + "; ".join(hint) if hint else ""))
    return out


# ----------------------------------------------------------------------------- the reconstruct hook


