"""A small two-camera scan for tests: the virtual rig renders the same scene twice,
once from each camera, and the two one-camera scans are put together into one
two-camera scan folder (camera 2's frames under ``<view>/cam2/``); the ground
truth is camera 1's."""

from __future__ import annotations

import dataclasses
import math
import shutil

import cv2
import numpy as np

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import UncalibratedLight, default_rig, look_at
from ringscan.pipeline.formats.scan import View, load_scan, save_scan
from ringscan.pipeline.geometry import project_points
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.truth import load_truth
from ringscan.pipeline.simulate.virtual_rig import RenderSettings
from tests.support.shared_renders import shared_render

PROJ = {"width": 1024, "height": 768, "center": [511.5, 383.5]}
ANGLE_PATTERNS = {"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 16.0, "bits": 5, "sector_bits": 6,
                  "angle_steps": 4, "angle_period": 12.0}


def two_camera_rig(*, turn_deg: float = 70.0):
    """The default rig with a 320x256 camera 1 and a camera 2 turned by ``turn_deg``
    about the light axis (same distance and tilt)."""
    rig = default_rig()
    K = np.array([[650.0, 0, 159.5], [0, 650.0, 127.5], [0, 0, 1]])
    c1 = dataclasses.replace(rig.camera, width=320, height=256, K=K)
    a = math.radians(turn_deg)
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
    target = np.array([0.0, 0.0, 25.0])
    eye2 = Rz @ c1.center
    R2, t2 = look_at(eye2, target, up_hint=Rz @ np.array([1.0, 0.0, 0.0]))
    c2 = dataclasses.replace(c1, R=R2, t=t2, dist=np.array([-0.01, 0.02, 0.0, 0.0, 0.0]))
    return dataclasses.replace(rig, camera=c1, camera2=c2)


def simulate_two_camera_scan(folder, *, patterns=None, rig=None, uncalibrated: bool = False,
                             turntable_deg=(0.0,), seed: int = 0):
    """Write a two-camera scan of a 80 mm sphere into ``folder``; returns it loaded
    (``seed``: the renderings' noise, camera 1's ``seed``, camera 2's ``seed + 7``). Rendered once per
    test session for the same arguments (tests/support/shared_renders.py); each call gets its own copy."""
    rig = two_camera_rig() if rig is None else rig
    patterns = ANGLE_PATTERNS if patterns is None else patterns
    turntable_deg = tuple(float(a) for a in turntable_deg)
    shared_render(folder, "two_camera", (patterns, rig, uncalibrated, turntable_deg, seed),
                  lambda dst: _render_two_camera_scan(dst, patterns, rig, uncalibrated, turntable_deg, seed))
    return load_scan(folder)


def _render_two_camera_scan(folder, patterns, rig, uncalibrated, turntable_deg, seed):
    spec = parse_patterns(patterns)
    one = dataclasses.replace(rig, camera2=None)
    scan1 = simulate_scan(folder, scene="sphere", rig=one, patterns=spec, turntable_deg=turntable_deg,
                          progress=False, settings=RenderSettings(seed=seed))
    tmp = folder.parent / (folder.name + "_camera2")
    scan2 = simulate_scan(tmp, scene="sphere", rig=dataclasses.replace(one, camera=rig.camera2), patterns=spec,
                          turntable_deg=turntable_deg, progress=False, settings=RenderSettings(seed=7 + seed))
    views = []
    for v1, v2 in zip(scan1.views, scan2.views):
        frames2 = {}
        for name, rel in v2.frames.items():
            dst = f"{v1.name}/cam2/{name}.png"
            (folder / dst).parent.mkdir(parents=True, exist_ok=True)
            shutil.move(tmp / rel, folder / dst)
            frames2[name] = dst
        views.append(dataclasses.replace(v1, camera2=View(name=v1.name, turntable_deg=v1.turntable_deg,
                                                          frames=frames2)))
    shutil.rmtree(tmp)
    full = rig if not uncalibrated else dataclasses.replace(
        rig, light=UncalibratedLight(width=rig.light.width, height=rig.light.height, gamma=rig.light.gamma))
    save_scan(dataclasses.replace(scan1, rig=full, rig_ref=None, views=tuple(views)))


def _decoded_maps(rig, depth, lit, *, integer: bool):
    """(proj_u, proj_v) float maps of one camera from its truth depth (NaN: not decoded)."""
    from ringscan.pipeline.geometry import projector_pixels, undistort_normalized

    c = rig.camera
    h, w = depth.shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = undistort_normalized(c, uu.ravel(), vv.ravel())
    z = depth.ravel().astype(np.float64)
    Xc = np.stack([x * z, y * z, z], 1)
    X = (Xc - c.t) @ c.R  # R^T (X_c - t)
    ok = np.isfinite(X).all(1) & lit.ravel()
    p = np.full((h * w, 2), np.nan)
    p[ok] = projector_pixels(rig, X[ok])
    if integer:
        p = np.round(p)  # the projector pixel a Gray code names (as OpenCV decodes it)
    inside = (p[:, 0] >= 0) & (p[:, 0] <= rig.light.width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= rig.light.height - 1)
    p[~inside] = np.nan
    return p[:, 0].reshape(h, w), p[:, 1].reshape(h, w)


def simulate_decoded_two_camera_scan(folder, *, integer: bool = True):
    """A ``decoded`` two-camera scan (every pixel's projector coordinate, as an
    imported Gray code gives it: integer codes by default) of the 80 mm sphere,
    made from the virtual rig's truth depth of each camera; returns it loaded. Made once per test
    session for each ``integer`` (tests/support/shared_renders.py); each call gets its own copy."""
    shared_render(folder, "decoded_two_camera", bool(integer),
                  lambda dst: _render_decoded_two_camera_scan(dst, integer=integer))
    return load_scan(folder)


def _render_decoded_two_camera_scan(folder, *, integer: bool):
    from ringscan.pipeline.formats.images import write_image
    from ringscan.pipeline.formats.patterns import DECODED_SCALE
    from ringscan.pipeline.simulate.truth import load_truth

    rig = two_camera_rig()
    cheap = parse_patterns({"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 16.0, "bits": 1, "sector_bits": 0,
                            "angle_steps": 0})
    one = dataclasses.replace(rig, camera2=None)
    scan1 = simulate_scan(folder, scene="sphere", rig=one, patterns=cheap, progress=False)
    tmp = folder.parent / (folder.name + "_camera2")
    rig2 = dataclasses.replace(one, camera=rig.camera2)
    scan2 = simulate_scan(tmp, scene="sphere", rig=rig2, patterns=cheap, progress=False)
    frames = {}
    for key, scan, r in (("1", scan1, one), ("2", scan2, rig2)):
        t = load_truth(scan)
        u, v = _decoded_maps(r, t.depth("view_000"), t.lit("view_000"), integer=integer)
        sub = "view_000" if key == "1" else "view_000/cam2"
        (folder / sub).mkdir(parents=True, exist_ok=True)
        names = {}
        for name, img in (("proj_u", u), ("proj_v", v)):
            q = np.where(np.isfinite(img), np.round((np.nan_to_num(img) + 1.0) * DECODED_SCALE), 0)
            write_image(folder / sub / f"{name}.png", q.astype(np.uint16))
            names[name] = f"{sub}/{name}.png"
        write_image(folder / sub / "contrast.png", np.full(u.shape, 200 * 257, np.uint16))
        names["contrast"] = f"{sub}/contrast.png"
        frames[key] = names
    shutil.rmtree(tmp)
    for rel in scan1.views[0].frames.values():  # the cheap pattern's frames: not part of the decoded scan
        (folder / rel).unlink()
    spec = parse_patterns({"codec": "decoded", **PROJ, "rho0": 0.0, "pitch": 1.0, "sector_bits": 8})
    v1 = scan1.views[0]
    view = View(name=v1.name, turntable_deg=v1.turntable_deg, frames=frames["1"],
                camera2=View(name=v1.name, turntable_deg=v1.turntable_deg, frames=frames["2"]))
    save_scan(dataclasses.replace(scan1, rig=rig, rig_ref=None, patterns=spec, views=(view,)))


def true_uv2(scan, m):
    """(keep, uv2): where camera 1's truth depth (bilinear at uv1) is known, the point seen there projected
    into camera 2."""
    rig = scan.rig
    depth = load_truth(scan).depth("view_000")
    u, v = m.uv1[:, 0], m.uv1[:, 1]
    i0, j0 = np.floor(v).astype(int), np.floor(u).astype(int)
    fy, fx = v - i0, u - j0
    z = (depth[i0, j0] * (1 - fx) * (1 - fy) + depth[i0, j0 + 1] * fx * (1 - fy)
         + depth[i0 + 1, j0] * (1 - fx) * fy + depth[i0 + 1, j0 + 1] * fx * fy)
    keep = np.isfinite(z)
    c = rig.camera
    x = cv2.undistortPoints(m.uv1[keep].reshape(-1, 1, 2), c.K, c.dist)[:, 0]
    X = ((np.c_[x, np.ones(len(x))] * z[keep, None]) - c.t) @ c.R  # R^T (X_c - t)
    return keep, project_points(X, rig.camera2.R, rig.camera2.t, rig.camera2.K, rig.camera2.dist)
