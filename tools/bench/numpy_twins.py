"""Plain vectorised NumPy versions of the decode, sampling and triangulation
stages, for ``ringscan bench`` (the reference each Warp timing is divided by) and
for tests that cross-check the kernels. They follow the kernels' rules exactly
(same thresholds, same root choice) but are written the way a careful NumPy user
would: whole-image array operations, no Python loops over pixels.
"""

from __future__ import annotations

import math

import numpy as np

from ringscan.kernels.settings import PhaseSettings
from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.formats.rig import ParallelLight, Rig
from ringscan.pipeline.geometry import undistort_normalized

__all__ = ["decode_numpy", "sample_numpy", "triangulate_numpy", "phase_numpy", "smooth_numpy", "points_numpy"]


def _gray_to_binary(g: np.ndarray, bits: int) -> np.ndarray:
    k = g.copy()
    shift = 1
    while shift < bits:
        k ^= k >> shift
        shift <<= 1
    return k


def decode_numpy(frames: np.ndarray, *, bits: int, sector_bits: int = 0, min_contrast: float = 12.0,
                 bit_margin: float = 0.12) -> dict:
    """NumPy twin of ``kernels.ring_labels.decode_gray_rings``."""
    f = frames.astype(np.float32)
    scale = 257.0 if frames.dtype == np.uint16 else 1.0
    c = f[0] - f[1]
    d = f[2:2 + 2 * bits:2] - f[3:3 + 2 * bits:2]
    weights = (1 << np.arange(bits - 1, -1, -1)).astype(np.int32)[:, None, None]
    code = ((d > 0).astype(np.int32) * weights).sum(0, dtype=np.int32)
    weak = ((np.abs(d) < bit_margin * c).astype(np.int32) * weights).sum(0, dtype=np.int32)
    ok = c >= min_contrast * scale
    band = np.where(ok & (weak == 0), _gray_to_binary(code, bits), -1).astype(np.int32)
    sector = np.full(c.shape, -1, np.int32)
    if sector_bits:
        base = 2 + 2 * bits
        ds = f[base:base + 2 * sector_bits:2] - f[base + 1:base + 1 + 2 * sector_bits:2]
        sw = (1 << np.arange(sector_bits - 1, -1, -1)).astype(np.int32)[:, None, None]
        sg = ((ds > 0).astype(np.int32) * sw).sum(0, dtype=np.int32)
        strong = np.all(np.abs(ds) >= bit_margin * c, axis=0)
        sector = np.where(ok & strong, _gray_to_binary(sg, sector_bits), -1).astype(np.int32)
    return {"code": code, "weak": weak, "band": band, "sector": sector, "contrast": c, "d": d}


def sample_numpy(frames: np.ndarray, dec: dict, *, bits: int, min_contrast: float = 12.0,
                 min_slope: float = 0.3) -> dict:
    """NumPy twin of ``kernels.ring_sampling.sample_gray_rings`` (same order)."""
    scale = 257.0 if frames.dtype == np.uint16 else 1.0
    code, weak, c, d, sector = dec["code"], dec["weak"], dec["contrast"], dec["d"], dec["sector"]
    h, w = code.shape
    k = _gray_to_binary(code, bits)
    out = []
    for axis in (1, 0):  # +x pairs, then +y pairs
        if axis == 1:
            P = (slice(None), slice(0, w - 1))
            Q = (slice(None), slice(1, w))
        else:
            P = (slice(0, h - 1), slice(None))
            Q = (slice(1, h), slice(None))
        x = code[P] ^ code[Q]
        single = (x > 0) & ((x & (x - 1)) == 0)
        m = np.where(single, x, 0)
        ok = single & ((c[P] >= min_contrast * scale) & (c[Q] >= min_contrast * scale))
        ok &= ((weak[P] | weak[Q]) & ~m) == 0
        ok &= np.abs(k[P] - k[Q]) == 1
        lsb = np.zeros_like(x)
        lsb[ok] = np.log2(m[ok]).astype(np.int32)
        b = bits - 1 - lsb
        yy, xx = np.nonzero(ok)
        bb = b[yy, xx]
        y2, x2 = (yy, xx + 1) if axis == 1 else (yy + 1, xx)
        dp = d[bb, yy, xx]
        dq = d[bb, y2, x2]
        slope = dp - dq
        cm = 0.5 * (c[yy, xx] + c[y2, x2])
        keep = np.abs(slope) >= min_slope * cm
        # gradient across the pair (central differences, clamped at the border)
        if axis == 1:
            a = (d[bb, np.minimum(yy + 1, h - 1), xx] - d[bb, np.maximum(yy - 1, 0), xx]) * 0.5
            bq = (d[bb, np.minimum(y2 + 1, h - 1), x2] - d[bb, np.maximum(y2 - 1, 0), x2]) * 0.5
            across = 0.5 * a + 0.5 * bq
            keep &= ~(np.abs(across) > np.abs(slope))
        else:
            a = (d[bb, yy, np.minimum(xx + 1, w - 1)] - d[bb, yy, np.maximum(xx - 1, 0)]) * 0.5
            bq = (d[bb, y2, np.minimum(x2 + 1, w - 1)] - d[bb, y2, np.maximum(x2 - 1, 0)]) * 0.5
            across = 0.5 * a + 0.5 * bq
            keep &= ~(np.abs(across) >= np.abs(slope))
        yy, xx, y2, x2 = yy[keep], xx[keep], y2[keep], x2[keep]
        f = (dp[keep] / slope[keep]).astype(np.float32)
        uv = np.stack([xx + (f if axis == 1 else 0), yy + (f if axis == 0 else 0)], -1).astype(np.float32)
        ring = np.maximum(k[yy, xx], k[y2, x2])
        s = np.where(sector[yy, xx] >= 0, sector[yy, xx], sector[y2, x2])
        conf = np.minimum(np.abs(slope[keep]) / cm[keep], 1.0).astype(np.float32)
        out.append((yy * w + xx, 0 if axis == 1 else 1, uv, ring, s, conf))
    pix = np.concatenate([o[0] for o in out])
    order = np.lexsort((np.concatenate([np.full(len(o[0]), o[1]) for o in out]), pix))
    return {"pixel": pix[order].astype(np.int32), "uv": np.concatenate([o[2] for o in out])[order],
            "ring": np.concatenate([o[3] for o in out])[order].astype(np.int32),
            "sector": np.concatenate([o[4] for o in out])[order].astype(np.int32),
            "confidence": np.concatenate([o[5] for o in out])[order]}


def triangulate_numpy(uv: np.ndarray, rho: np.ndarray, sector: np.ndarray, rig: Rig, *, center, sector_bits: int,
                      settings: TriangulateSettings = TriangulateSettings()) -> tuple[np.ndarray, np.ndarray]:
    """NumPy twin of ``kernels.triangulation.triangulate_rings`` for the parallel
    light (the default rig), the ring constraint alone (of ``settings``: ``sector_tolerance``,
    ``sector_margin``, ``min_incidence_cos``). Returns (points (n, 3), status (n,))."""
    sector_tolerance = settings.sector_tolerance
    sector_margin = settings.sector_margin
    min_incidence_cos = settings.min_incidence_cos
    li = rig.light
    if not isinstance(li, ParallelLight):
        raise ValueError("triangulate_numpy: only the parallel light model")
    cam = rig.camera
    x, y = undistort_normalized(cam, uv[:, 0], uv[:, 1])
    dcam = np.stack([x, y, np.ones_like(x)], -1)
    d = dcam @ cam.R  # R^T d
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    C = cam.center
    P0 = li.R @ C + li.t
    D = d @ li.R.T
    s = li.pixel_pitch_mm
    a0 = P0[0] / s + li.axis_px[0] - center[0]
    b0 = P0[1] / s + li.axis_px[1] - center[1]
    a1, b1 = D[:, 0] / s, D[:, 1] / s
    r2 = rho.astype(np.float64) ** 2
    A = a1 * a1 + b1 * b1
    B = 2 * (a0 * a1 + b0 * b1)
    Cc = a0 * a0 + b0 * b0 - r2
    disc = B * B - 4 * A * Cc
    status = np.zeros(len(uv), np.int32)
    status[disc < 0] = 1
    sq = np.sqrt(np.maximum(disc, 0))
    q = -0.5 * (B + np.where(B >= 0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = q / A, np.where(q != 0, Cc / q, q / A)
    t1, t2 = np.minimum(ta, tb), np.maximum(ta, tb)
    X1 = C + d * t1[:, None]
    X2 = C + d * t2[:, None]
    vol = rig.volume

    def inside(X, t):
        r = np.hypot(X[:, 0], X[:, 1])
        return (t > 0) & (X[:, 2] >= vol.z_min) & (X[:, 2] <= vol.z_max) & (r <= vol.r_max)

    ok1, ok2 = inside(X1, t1), inside(X2, t2)
    status[(status == 0) & ~ok1 & ~ok2] = 2
    X = np.where(ok1[:, None], X1, X2)
    if sector_bits:
        n = 2 ** sector_bits
        width = 2 * math.pi / n

        def resid(Xr):
            XL = Xr @ li.R.T + li.t
            phi = np.arctan2(XL[:, 1] / s + li.axis_px[1] - center[1], XL[:, 0] / s + li.axis_px[0] - center[0])
            dphi = phi - ((sector + 0.5) * width - math.pi)
            dphi -= 2 * math.pi * np.floor((dphi + math.pi) / (2 * math.pi))
            return np.maximum(np.abs(dphi) / width - 0.5, 0)

        has = sector >= 0
        e1 = np.where(ok1, resid(X1), 1e9)
        e2 = np.where(ok2, resid(X2), 1e9)
        amb = has & ok1 & ok2 & (np.abs(e1 - e2) < sector_margin)
        pick2 = has & (e2 < e1)
        res = np.where(pick2, e2, e1)
        X = np.where(pick2[:, None], X2, np.where(has[:, None], X1, X))
        live = status == 0
        status[live & amb] = 3
        status[live & ~amb & has & (res > sector_tolerance)] = 4
        status[live & ~has & ok1 & ok2] = 3
    else:
        status[(status == 0) & ok1 & ok2] = 3
    # incidence on the cylinder: its normal is radial in the light's x-y plane
    XL = X @ li.R.T + li.t
    g = np.stack([XL[:, 0] / s + li.axis_px[0] - center[0], XL[:, 1] / s + li.axis_px[1] - center[1],
                  np.zeros(len(X))], -1) @ li.R
    with np.errstate(invalid="ignore", divide="ignore"):
        cosi = np.abs(np.sum(g * d, axis=1)) / np.linalg.norm(g, axis=1)
    status[(status == 0) & ~(cosi >= min_incidence_cos)] = 5
    return X, status


def _ctz(k: np.ndarray) -> np.ndarray:
    """Trailing zeros of k > 0 (vectorised); 0 where k <= 0."""
    k = np.asarray(k, np.int64)
    low = k & -k
    return np.where(k > 0, np.log2(np.maximum(low, 1)).astype(np.int64), 0)


def phase_numpy(frames: np.ndarray, dec: dict, *, bits: int, sector_bits: int, steps: int, lut: np.ndarray,
                wlut: np.ndarray, light_gamma: float = 1.0, settings: PhaseSettings = PhaseSettings()) -> dict:
    """NumPy twin of ``kernels.phase.decode_phase`` (same rules).

    ``dec`` is the band decode as ``tools.numpy_twins.decode_numpy`` returns it
    (``code``, ``weak``, ``contrast``). Returns ``t``, ``modulation``, ``status``.

    Size: the NumPy twin of decode_phase, with its arguments (less threads), and it takes phase_unwrap_kernel's
    steps in the kernel's order (the weighted fit, its solution by Cramer's rule, the band code's edges, the
    unwrapping), vectorised over the pixels, so that tests/kernels/test_phase.py can compare their results.
    """
    s = settings
    scale = 257.0 if frames.dtype == np.uint16 else 1.0
    h, w = frames.shape[1:]
    phase0 = 2 + 2 * bits + 2 * sector_bits
    c = dec["contrast"].astype(np.float32)
    status = np.zeros((h, w), np.int32)
    t = np.zeros((h, w), np.float32)
    mod = np.zeros((h, w), np.float32)
    lw = lut[frames[0]]
    lb = lut[frames[1]]
    span = lw - lb
    dark = (c < s.min_contrast * scale) | (span <= 0)
    status[dark] = 1
    live = ~dark
    idx = np.nonzero(live)
    raw = frames[phase0:phase0 + steps][:, idx[0], idx[1]]
    val = lut[raw]
    wt = wlut[raw]
    lb_l, span_l = lb[idx], span[idx]
    normalise = light_gamma != 1.0
    if normalise:
        ig = np.float32(1.0 / light_gamma)
        u = np.clip((val - lb_l) / span_l, 1e-6, 1.0)
        val = u ** ig
        g = ig * u ** (ig - 1.0) / span_l
        wt = wt / (g * g)
    dl = 2.0 * np.pi * np.arange(steps) / steps
    cn = np.cos(dl).astype(np.float32)[:, None]
    sn = np.sin(dl).astype(np.float32)[:, None]
    s0, sc, ss = wt.sum(0), (wt * cn).sum(0), (wt * sn).sum(0)
    scc, scs, sss = (wt * cn * cn).sum(0), (wt * cn * sn).sum(0), (wt * sn * sn).sum(0)
    r0, rc, rs = (wt * val).sum(0), (wt * cn * val).sum(0), (wt * sn * val).sum(0)
    # Solve the symmetric 3x3 system by its adjugate (Cramer).
    a11, a12, a13, a22, a23, a33 = s0, sc, ss, scc, scs, sss
    c11 = a22 * a33 - a23 * a23
    c12 = a13 * a23 - a12 * a33
    c13 = a12 * a23 - a13 * a22
    c22 = a11 * a33 - a13 * a13
    c23 = a12 * a13 - a11 * a23
    c33 = a11 * a22 - a12 * a12
    det = a11 * c11 + a12 * c12 + a13 * c13
    good = det > 1e-9 * s0 * s0 * s0
    with np.errstate(divide="ignore", invalid="ignore"):
        bc = (c12 * r0 + c22 * rc + c23 * rs) / det
        bs = (c13 * r0 + c23 * rc + c33 * rs) / det
    amp = np.sqrt(bc * bc + bs * bs)
    q = 2.0 * amp if normalise else 2.0 * amp / span_l
    q = np.where(good, q, 0.0).astype(np.float32)
    f = np.arctan2(bs, bc) / (2.0 * np.pi)
    f = f - np.floor(f)
    st = np.zeros(q.shape, np.int32)
    st[~good] = 3
    st[good & (q < s.min_modulation)] = 3
    code = dec["code"][idx].astype(np.int64)
    wk = dec["weak"][idx].astype(np.int64)
    kk = code.copy()
    shift = 1
    while shift < bits:
        kk ^= kk >> shift
        shift <<= 1
    nb = 1 << bits
    has_lo = (kk >= 1) & (kk < nb)
    has_hi = (kk + 1 >= 1) & (kk + 1 < nb)
    m_lo = np.where(has_lo, 1 << _ctz(kk), 0)
    m_hi = np.where(has_hi, 1 << _ctz(kk + 1), 0)
    bad_code = (wk != 0) & (wk != m_lo) & (wk != m_hi)
    st[(st == 0) & bad_code] = 2
    d = frames[2:2 + 2 * bits:2][:, idx[0], idx[1]].astype(np.float32) - frames[3:3 + 2 * bits:2][:, idx[0], idx[1]]
    cl = c[idx]
    ar = np.arange(kk.size)
    b_lo = np.clip(bits - 1 - _ctz(kk), 0, bits - 1)
    b_hi = np.clip(bits - 1 - _ctz(kk + 1), 0, bits - 1)
    e_lo = np.where(has_lo, np.abs(d[b_lo, ar]) / cl, 2.0)
    e_hi = np.where(has_hi, np.abs(d[b_hi, ar]) / cl, 2.0)
    near = np.minimum(e_lo, e_hi) < s.edge_ratio
    edge = np.where(near, np.where(e_lo <= e_hi, kk, kk + 1), -1)
    tb = np.where(near, edge, kk + 0.5)
    # round half away from zero, as wp.round does
    x = tb - f
    tt = np.sign(x) * np.floor(np.abs(x) + 0.5) + f
    emask = np.where(edge == kk, m_lo, m_hi)
    strong = near & ((wk & emask) == 0)
    slip = strong & (((edge == kk) & (tt < edge - s.slip_tolerance)) | ((edge == kk + 1) & (tt > edge + s.slip_tolerance)))
    st[(st == 0) & slip] = 4
    status[idx] = st
    mod[idx] = np.where(good, q, 0.0)
    t[idx] = np.where(st == 0, tt, 0.0)
    return {"t": t, "modulation": mod, "status": status}


def smooth_numpy(ph: dict, sector: np.ndarray, *, settings: PhaseSettings = PhaseSettings()) -> dict:
    """NumPy twin of ``kernels.phase.smooth_phase`` called without ``rho0``/``pitch`` (no
    ring-curvature correction): ``t``, ``status``, ``sector``, ``modulation``."""
    s = settings
    t, status = ph["t"], ph["status"]
    h, w = t.shape
    r = int(s.smooth_radius)
    ok = status == 0
    P = max(r, 2)
    tp = np.pad(t, P)
    okp = np.pad(ok, P)
    acc = t.astype(np.float32).copy()
    cnt = np.ones((h, w), np.float32)
    pairs = np.zeros((h, w), np.int32)
    seen = np.zeros((h, w), np.int32)
    for dy in range(0, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx <= 0:
                continue
            sa = (slice(P + dy, P + dy + h), slice(P + dx, P + dx + w))
            sb = (slice(P - dy, P - dy + h), slice(P - dx, P - dx + w))
            oa, ob = okp[sa], okp[sb]
            seen += oa | ob
            ta, tb = tp[sa], tp[sb]
            agree = oa & ob & (np.abs(np.float32(0.5) * (ta + tb) - t) <= np.float32(s.smooth_tolerance))
            acc += np.where(agree, ta + tb, np.float32(0))
            cnt += 2 * agree
            pairs += agree
    out_status = status.copy()
    if r > 0:
        out_status[ok & (seen > 0) & (pairs < s.min_pairs)] = 5
    out_t = np.where(ok, acc / cnt, t).astype(np.float32)
    sec = sector.copy()
    fill = ok & (sector < 0)
    sp = np.pad(sector, P, constant_values=-1)
    offs = sorted(((dy * dy + dx * dx, dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)))
    todo = fill.copy()
    for _, dy, dx in offs:
        cand = sp[P + dy:P + dy + h, P + dx:P + dx + w]
        take = todo & (cand >= 0)
        sec[take] = cand[take]
        todo &= ~take
    return {"t": out_t, "status": out_status, "sector": sec, "modulation": ph["modulation"]}


def points_numpy(sm: dict, *, rho0: float, pitch: float) -> dict:
    """NumPy twin of ``kernels.phase.compact_phase_points`` (raster order)."""
    h, w = sm["t"].shape
    pix = np.flatnonzero(sm["status"].ravel() == 0).astype(np.int32)
    y, x = np.divmod(pix, w)
    return {"pixel": pix, "uv": np.stack([x, y], -1).astype(np.float32),
            "rho": (np.float32(rho0) + np.float32(pitch) * sm["t"].ravel()[pix]).astype(np.float32),
            "sector": sm["sector"].ravel()[pix].astype(np.int32),
            "confidence": np.clip(sm["modulation"].ravel()[pix], 0.0, 1.0).astype(np.float32)}
