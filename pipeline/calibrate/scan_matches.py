"""Calibration from a scan's own matches (``calibrate refine``, ``calibrate projector-from-scan``): the scan
with another rig file in place of its own, every view's matches gathered and subsampled, the extrinsics they
refine, and the two cameras' matches triangulated into the world frame.

The two-camera matching itself is reconstruct's (``ringscan.pipeline.reconstruct.stereo.match_view``), which
this stage may not import: :func:`gather_matches` takes it as ``match_view``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.projector_fit import decoded_pairs
from ringscan.pipeline.calibrate.rig_refine import (
    Refinement,
    refine_procam_rig,
    refine_stereo_rig,
    relative_pose,
    reprojection_errors,
    triangulate_pair,
)
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.progress import progress_bar
from ringscan.pipeline.formats.rig import Camera, PerspectiveLight, Rig, load_rig
from ringscan.pipeline.formats.scan import Scan, View, load_scan

__all__ = ["OPENCV_EXTENSIONS", "load_scan_with_rig", "gather_matches", "refine_rig_from_matches",
           "two_camera_points"]

OPENCV_EXTENSIONS = (".yml", ".yaml", ".xml")
"""What an OpenCV FileStorage file ends in (OpenCV picks the format from it)."""


def load_scan_with_rig(scan_path, *, rig_path=None, view_names=None) -> tuple[Scan, list[View]]:
    """The scan, with the rig file ``rig_path`` in place of its own (same cameras' image sizes), and the views
    to use (``view_names``, in that order without repeats; None: every view).

    Raises:
        FormatError: naming the rig file: an OpenCV file, other cameras than the scan's; naming the scan:
            no view of a name given.
    """
    if rig_path and Path(rig_path).suffix.lower() in OPENCV_EXTENSIONS:
        raise FormatError(rig_path, "an OpenCV FileStorage file; --rig takes a ringscan rig (JSON): import the "
                                    "calibration first (docs/calibration.md)")
    scan = load_scan(scan_path)
    if rig_path:
        rig = load_rig(rig_path)
        own = scan.rig
        for what, a, b in (("camera", rig.camera, own.camera), ("camera2", rig.camera2, own.camera2)):
            if (a is None) != (b is None):
                has = "two cameras" if rig.camera2 is not None else "one camera"
                raise FormatError(rig_path, f"has {has}, the scan {scan_path} "
                                            f"{'two cameras' if own.camera2 is not None else 'one camera'}")
            if a is not None and (a.width, a.height) != (b.width, b.height):
                raise FormatError(rig_path, f"{what} is {a.width}x{a.height}, the scan's frames are "
                                            f"{b.width}x{b.height}")
        scan = dataclasses.replace(scan, rig=rig)
    views = list(scan.views)
    if view_names:
        names = {v.name: v for v in views}
        missing = [n for n in view_names if n not in names]
        if missing:
            raise FormatError(scan.path, f"no view {missing[0]!r} (views: {', '.join(sorted(names))})")
        views = [names[n] for n in dict.fromkeys(view_names)]
    return scan, views


def gather_matches(scan: Scan, views, *, need: str, max_matches: int, match_view: Callable, progress: bool = True,
                   on_view: Callable[[str, int], None] | None = None):
    """Matches of every view, subsampled (a seeded random subset) to ``max_matches`` over all views:
    (uv1, uv2 or None, proj, sigmas or None).

    Args:
        need: "cameras" (a two-camera scan's matches) or "projector" (camera-projector pairs: a two-camera
            scan's, or an imported one-camera scan's decoded pixels).
        match_view: ``match_view(scan, view) -> (uv1, uv2, proj, sigmas or None)`` of a two-camera view;
            sigmas: (n, 5) predicted standard deviations of uv1, uv2 (px), proj (projector px, the mean of its
            two axes) and proj along u_p and v_p.
        on_view: called with each view's name and its number of matches.

    Raises:
        FormatError: naming the scan: ``need`` "cameras" and a view with one camera's frames.
    """
    two = [v for v in views if v.camera2 is not None]
    if need == "cameras" and len(two) < len(views):
        one = next(v for v in views if v.camera2 is None)
        raise FormatError(scan.path, f"view {one.name} has one camera's frames; matching cameras needs both")
    per = max(1, max_matches // max(1, len(views)))
    u1s, u2s, ps, ss = [], [], [], []
    for v in progress_bar(views, desc="matching", unit="view", disable=not progress, leave=False):
        if v.camera2 is not None:
            u1, u2, pr, sg = match_view(scan, v)
        else:
            u1, pr = decoded_pairs(scan, v, max_pairs=per)
            u2 = sg = None
        if u1.shape[0] > per:
            pick = np.sort(np.random.default_rng(len(u1s)).choice(u1.shape[0], per, replace=False))
            u1, pr = u1[pick], pr[pick]
            u2 = None if u2 is None else u2[pick]
            sg = None if sg is None else sg[pick]
        if on_view is not None:
            on_view(v.name, u1.shape[0])
        u1s.append(u1)
        ps.append(pr)
        if u2 is not None:
            u2s.append(u2)
        if sg is not None:
            ss.append(sg)
    uv1, proj = np.concatenate(u1s), np.concatenate(ps)
    uv2 = np.concatenate(u2s) if len(u2s) == len(u1s) else None
    sig = np.concatenate(ss) if len(ss) == len(u1s) else None
    return uv1, uv2, proj, sig


def refine_rig_from_matches(rig: Rig, uv1, uv2, proj, sigmas, *, pair: str, baseline_mm: float | None = None,
                            two_view: bool = False) -> tuple[Rig, Refinement]:
    """The rig with camera 2 (``pair`` "cameras") or the projector (``pair`` "projector") re-estimated against
    camera 1 from the matches of :func:`gather_matches`. On a two-camera rig the third device (the calibrated
    projector, or camera 2) joins the adjustment with its pose held, unless ``two_view``; camera 2 only where
    every view has its matches (a note says when it was left out)."""
    sig = sigmas
    if pair == "cameras":
        use_light = isinstance(rig.light, PerspectiveLight) and not two_view
        return refine_stereo_rig(rig, uv1, uv2, baseline_mm=baseline_mm,
                                 sigma1=None if sig is None else sig[:, 0],
                                 sigma2=None if sig is None else sig[:, 1],
                                 uv_light=proj if use_light else None,
                                 sigma_light=None if sig is None or not use_light else sig[:, 2])
    # a two-camera rig's camera 2 (pose held) joins as the third device where every view has its matches
    use_cam2 = rig.camera2 is not None and uv2 is not None and not two_view
    new, ref = refine_procam_rig(rig, uv1, proj, baseline_mm=baseline_mm,
                                 uv_camera2=uv2 if use_cam2 else None,
                                 sigma_cam=None if sig is None or not use_cam2 else sig[:, 0],
                                 sigma_proj=None if sig is None or not use_cam2 else sig[:, 2],
                                 sigma_camera2=None if sig is None or not use_cam2 else sig[:, 1])
    if rig.camera2 is not None and uv2 is None and not two_view:
        ref.notes.append("camera 2 was left out of the adjustment: a view has one camera's frames")
    return new, ref


def two_camera_points(camera1: Camera, camera2: Camera, uv1, uv2, *, max_error_px: float = 3.0):
    """The two cameras' matches triangulated into the world frame with the rig's poses.

    Returns:
        (points_world of the kept matches (m, 3), keep (n,) bool: in front of both cameras and reprojected
        within ``max_error_px``, err (n,) the reprojection errors (px) of every match).
    """
    R, t = relative_pose(camera1, camera2)
    n1 = cv2.undistortPoints(uv1.reshape(-1, 1, 2), camera1.K, camera1.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(uv2.reshape(-1, 1, 2), camera2.K, camera2.dist).reshape(-1, 2)
    err, front = reprojection_errors(R, t, camera1, camera2, uv1, uv2, n1, n2)
    keep = front & (err <= max_error_px)
    Xc = triangulate_pair(R, t, n1[keep], n2[keep])
    return (Xc - camera1.t) @ camera1.R, keep, err
