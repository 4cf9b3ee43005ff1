"""OpenCV's own structured-light sample pipeline (``structured_light`` module, its
``cap_pattern`` / ``pointcloud`` sample) on a two-camera Gray-code capture: the reference
``benchmarks/real_capture.py`` measures ringscan against (issue 33, ``peer_speed``).

What the sample does, step for step: read the capture's frames (the list file's ``cam1`` and
``cam2`` nodes: patterns, then white, then black), read the calibration with
``cv2.FileStorage``, ``stereoRectify`` + ``initUndistortRectifyMap`` + ``remap`` (nearest),
``GrayCodePattern.decode`` (white threshold 5, black threshold 40; ``DECODE_3D_UNDERWORLD``)
and ``reprojectImageTo3D``. Where the OpenCV build lacks ``cv2.structured_light`` (it is in
opencv-contrib-python-headless, the project's dependency) the decode is a NumPy
re-implementation of the same steps, and :data:`DECODER` says so.

Imports only OpenCV and NumPy, so that run as its own process it starts as OpenCV's sample would::

    python benchmarks/opencv_graycode_sample.py SRC --projector 768x576

(SRC: a folder with ``capture_0.yml`` and ``calibrationParameters.yml``, as ``ringscan simulate
--captures opencv-graycode`` writes it). Prints one JSON line: seconds per stage and the pixels
with a disparity.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

WHITE_THRESHOLD, BLACK_THRESHOLD = 5, 40
"""The sample's thresholds (8-bit levels)."""
DECODER = ("cv2.structured_light.GrayCodePattern.decode" if hasattr(cv2, "structured_light") else
           "cv2.structured_light ABSENT in this build: a NumPy re-implementation of its decode")


def read_list(src: Path) -> dict[int, list[Path]]:
    """Each camera's frame paths of ``src/capture_0.yml`` (patterns, white, black)."""
    fs = cv2.FileStorage(str(src / "capture_0.yml"), cv2.FILE_STORAGE_READ)
    out = {}
    for c in (1, 2):
        node = fs.getNode(f"cam{c}")
        out[c] = [src / node.at(i).string() for i in range(node.size())]
    fs.release()
    return out


def read_calibration(path: Path) -> dict:
    """The sample's calibration file as the sample reads it: each camera's intrinsics and distortion, and
    camera 2's pose (``R``, ``T``, or ``RT_cam1_2_cam2`` as in OpenCV's test data)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    out = {}
    for c in (1, 2):
        out[f"cam{c}_K"] = fs.getNode(f"cam{c}_intrinsics").mat()
        out[f"cam{c}_dist"] = fs.getNode(f"cam{c}_distorsion").mat()
    if not fs.getNode("R").empty():
        out["R"], out["T"] = fs.getNode("R").mat(), fs.getNode("T").mat().reshape(3)
    else:
        rt = fs.getNode("RT_cam1_2_cam2").mat()
        out["R"], out["T"] = rt[:3, :3].copy(), rt[:3, 3].copy()
    fs.release()
    return out


def numpy_graycode_decode(pats, blacks, whites, proj: tuple[int, int]) -> np.ndarray:
    """OpenCV's GrayCodePattern.decode (DECODE_3D_UNDERWORLD) re-implemented in NumPy: the disparity map of
    camera 1 (its column minus the mean column of camera 2's pixels of the same projector pixel; 0 where none)."""
    pw, ph = proj
    cb, rb = int(np.ceil(np.log2(pw))), int(np.ceil(np.log2(ph)))
    codes = []
    for cam in range(2):
        p = pats[cam]
        lit = (whites[cam].astype(np.int16) - blacks[cam]) > BLACK_THRESHOLD
        ok = lit.copy()

        def bits(first, n):
            g = np.zeros(p[0].shape, np.int32)
            for k in range(n):
                a, b = p[first + 2 * k].astype(np.int16), p[first + 2 * k + 1].astype(np.int16)
                ok[np.abs(a - b) < WHITE_THRESHOLD] = False
                g = (g << 1) | (a > b)
            shift = 1
            while shift < n:
                g ^= g >> shift
                shift <<= 1
            return g

        x, y = bits(0, cb), bits(2 * cb, rb)
        ok &= (x < pw) & (y < ph)
        codes.append(np.where(ok, y * pw + x, -1))
    n = pw * ph
    c2 = codes[1].ravel()
    m2 = c2 >= 0
    cols2 = np.tile(np.arange(pats[1][0].shape[1]), pats[1][0].shape[0])[m2]
    cnt = np.bincount(c2[m2], minlength=n)
    sx = np.bincount(c2[m2], cols2, minlength=n)
    c1 = codes[0]
    disp = np.zeros(c1.shape, np.float64)
    hit = (c1 >= 0) & (cnt[np.maximum(c1, 0)] > 0)
    cols1 = np.broadcast_to(np.arange(c1.shape[1])[None, :], c1.shape)
    disp[hit] = cols1[hit] - sx[c1[hit]] / cnt[c1[hit]]
    return disp


def opencv_sample(src: Path, proj: tuple[int, int]) -> tuple[dict, int]:
    """OpenCV's structured-light sample pipeline on the capture: (seconds per stage, pixels with a disparity)."""
    times = {}
    t = time.perf_counter()
    lists = read_list(src)
    imgs = {c: [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in lists[c]] for c in (1, 2)}
    times["read"] = time.perf_counter() - t
    t = time.perf_counter()
    cal = read_calibration(src / "calibrationParameters.yml")
    h, w = imgs[1][0].shape
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(cal["cam1_K"], cal["cam1_dist"], cal["cam2_K"], cal["cam2_dist"],
                                                (w, h), cal["R"], cal["T"].reshape(3, 1), flags=0, alpha=-1)
    maps = {1: cv2.initUndistortRectifyMap(cal["cam1_K"], cal["cam1_dist"], R1, P1, (w, h), cv2.CV_32FC1),
            2: cv2.initUndistortRectifyMap(cal["cam2_K"], cal["cam2_dist"], R2, P2, (w, h), cv2.CV_32FC1)}
    rect = {c: [cv2.remap(im, *maps[c], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) for im in imgs[c]]
            for c in (1, 2)}
    times["rectify"] = time.perf_counter() - t
    t = time.perf_counter()
    pats = [rect[c][:-2] for c in (1, 2)]
    whites = [rect[c][-2] for c in (1, 2)]
    blacks = [rect[c][-1] for c in (1, 2)]
    if hasattr(cv2, "structured_light"):
        gc = cv2.structured_light.GrayCodePattern.create(proj[0], proj[1])
        gc.setWhiteThreshold(WHITE_THRESHOLD)
        gc.setBlackThreshold(BLACK_THRESHOLD)
        ok, disp = gc.decode(pats, blackImages=blacks, whiteImages=whites,
                             flags=cv2.structured_light.DECODE_3D_UNDERWORLD)
    else:
        disp = numpy_graycode_decode(pats, blacks, whites, proj)
    times["decode"] = time.perf_counter() - t
    t = time.perf_counter()
    cloud = cv2.reprojectImageTo3D(disp.astype(np.float32), Q, handleMissingValues=True, ddepth=-1)
    mask = disp > 0
    _ = cloud[mask]
    times["reproject"] = time.perf_counter() - t
    return times, int(mask.sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", help="the capture folder (capture_0.yml, calibrationParameters.yml)")
    ap.add_argument("--projector", required=True, help="projector WxH (px)")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.projector.lower().split("x"))
    times, pixels = opencv_sample(Path(args.src), (w, h))
    print(json.dumps({"times_s": times, "pixels": pixels, "decoder": DECODER}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
