"""How flat is the board? Real captures (../shared/data/procam) reconstructed two ways.

1. Calibrates the rig from capture_1..3 (``ringscan calibrate procam``'s library
   code), or reads ``--rig``.
2. The ringscan way: ``import_captures`` (sub-pixel projector positions) and
   ``reconstruct_view``, once per constraint (``--constraints``, default
   ``rings both``): rings = each camera ray meets the cone of its rho around the
   projector's principal point, the polar angle picks the root (the paper's
   model); both = the full projector coordinate, each direction weighted by its
   predicted standard deviation.
3. The plain OpenCV way: integer column/row codes decoded with NumPy, camera and
   projector rays triangulated with ``cv2.triangulatePoints`` (same calibration).

For each capture, the points whose camera pixel lies inside the board's outer
corners are fitted with a plane (least squares); printed: points, RMS residual,
median |residual|, share within 1 and 3 units, and the ring/plain RMS ratio. Also
where the cone is ill-conditioned: the triangulation's drops by reason on the board
and in the whole image, and the median incidence |cos| per image quadrant.

    python benchmarks/procam_plane.py [--data ../shared/data/procam] [--rig RIG.json] [--out DIR]
        [--constraints rings both]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.board import Board
from ringscan.pipeline.calibrate.capture_reader import read_capture
from ringscan.pipeline.calibrate.graycode import GrayCodeSettings, decode_graycode
from ringscan.pipeline.calibrate.importer import ImportSettings, import_captures, procam_pose, triangulate_codes
from ringscan.pipeline.calibrate.procam import calibrate_procam, capture_corners, depth_range, procam_rig
from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.formats.rig import load_rig
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import reconstruct_view

PROJECTOR = (1024, 768)
BOARD = Board(9, 7, 75.0)


def plane_stats(P: np.ndarray, sigma: np.ndarray | None = None, center: np.ndarray | None = None) -> dict:
    """The plane fit's residuals; with each point's ``sigma`` (along its camera ray from ``center``) also
    the residual along the ray over sigma: its median (a Gaussian: 0.67) and share beyond 3 (0.3 %)."""
    c = P.mean(0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    r = (P - c) @ vt[2]
    a = np.abs(r)
    out = {"n": len(P), "rms": float(np.sqrt(np.mean(r ** 2))), "median": float(np.median(a)),
           "within1": float(np.mean(a <= 1.0)), "within3": float(np.mean(a <= 3.0))}
    if sigma is not None:
        ray = (P - center) / np.linalg.norm(P - center, axis=1, keepdims=True)
        z = a / np.maximum(np.abs(ray @ vt[2]), 1e-6) / np.asarray(sigma, np.float64)  # along the ray
        out.update(z_median=float(np.median(z)), beyond_3=float(np.mean(z > 3)))
    return out


def board_mask(corners: np.ndarray, shape) -> np.ndarray:
    g = corners.reshape(BOARD.rows, BOARD.cols, 2)
    quad = np.array([g[0, 0], g[0, -1], g[-1, -1], g[-1, 0]], np.float32)
    m = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(m, np.round(quad).astype(np.int32), 1)
    return m.astype(bool)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "procam"))
    ap.add_argument("--rig", default=None, help="a ringscan rig (default: calibrate from the captures)")
    ap.add_argument("--out", default=None, help="keep the imported scan here")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--constraints", nargs="+", default=["rings", "both"], choices=["rings", "angle", "both"],
                    help="triangulation constraints to compare (default: rings both)")
    ap.add_argument("--min-contrast", type=float, default=GrayCodeSettings.min_contrast,
                    help="the import's least white - black (8-bit levels; default the import's); "
                         "the plain decode keeps its own default")
    args = ap.parse_args(argv)
    data = Path(args.data)
    caps = [data / f"capture_{i}" for i in (1, 2, 3)]
    if not all(c.is_dir() for c in caps):
        print(f"procam captures not found under {data}", file=sys.stderr)
        return 2
    corners, masks = {}, {}
    cc = []
    for c in caps:
        cap = read_capture(c, projector=PROJECTOR)
        x = capture_corners(cap, board=BOARD, name=c.name)
        cc.append(x)
        corners[c.name] = x.camera_view.corners
        masks[c.name] = board_mask(x.camera_view.corners, cap.white.shape)
    if args.rig:
        rig = load_rig(args.rig)
        print(f"rig: {args.rig}")
    else:
        res = calibrate_procam(cc, board=BOARD, camera_size=(1280, 1024), projector_size=PROJECTOR)
        rig = procam_rig(cam_K=res.camera.K, cam_dist=res.camera.dist, cam_size=(1280, 1024), proj_K=res.projector.K,
                         proj_dist=res.projector.dist, proj_size=PROJECTOR, R=res.R, T=res.T,
                         z_range=depth_range(res.depths))
        print(f"calibrated from capture_1..3: camera fx {res.camera.K[0, 0]:.1f} RMS {res.camera.rms:.3f} px; "
              f"projector fx {res.projector.K[0, 0]:.1f} RMS {res.projector.rms:.3f} px; "
              f"stereo RMS {res.stereo_rms:.3f} px")
    R, T = procam_pose(rig)
    cam, li = rig.camera, rig.light
    tmp = tempfile.TemporaryDirectory()
    out = Path(args.out) if args.out else Path(tmp.name) / "scan"
    scan, stats = import_captures(caps, out=out, rig=rig, projector=PROJECTOR,
                                  settings=ImportSettings(graycode=GrayCodeSettings(min_contrast=args.min_contrast)))
    print(f"import min_contrast {args.min_contrast:g}")
    print(f"\n{'capture':10} {'method':6} {'points':>8} {'rms':>6} {'median':>7} {'<=1':>6} {'<=3':>6}   ratio")
    ratios = []
    for view, c in zip(scan.views, caps):
        m = masks[c.name]
        dec = decode_graycode(read_capture(c, projector=PROJECTOR))
        sel = dec.valid & m
        yy, xx = np.nonzero(sel)
        X = triangulate_codes(np.stack([xx, yy], 1), np.stack([dec.col[sel], dec.row[sel]], 1), cam_K=cam.K,
                              cam_dist=cam.dist, proj_K=li.K, proj_dist=li.dist, R=R, T=T)
        plain = plane_stats(X[np.all(np.isfinite(X), 1)])
        for k in args.constraints:
            settings = ReconstructSettings(triangulate=TriangulateSettings(constraint=k))
            cloud = reconstruct_view(scan, view, settings=settings, device=args.device)
            uv = np.round(cloud.uv).astype(int)
            on = m[uv[:, 1], uv[:, 0]]
            ring = plane_stats(cloud.points[on].astype(np.float64), cloud.sigma[on],
                               np.asarray(cam.center, np.float64))
            ratio = ring["rms"] / plain["rms"]
            ratios.append((c.name, k, ratio))
            print(f"{c.name:10} {k:6} {ring['n']:8d} {ring['rms']:6.3f} {ring['median']:7.3f} "
                  f"{100 * ring['within1']:5.1f}% {100 * ring['within3']:5.1f}%   {ratio:.2f}   "
                  f"median sigma {np.median(cloud.sigma[on]):.3f}, median |e|/sigma {ring['z_median']:.2f}, "
                  f"{100 * ring['beyond_3']:.1f} % beyond 3 sigma")
            st = cloud.stats
            print(f"{'':10} drops (whole image): { {a: b for a, b in st['dropped'].items() if b} }; sub-pixel share "
                  f"{100 * stats[c.name]['subpixel_share']:.0f} %")
        s_ = plain
        print(f"{c.name:10} {'plain':6} {s_['n']:8d} {s_['rms']:6.3f} {s_['median']:7.3f} {100 * s_['within1']:5.1f}% "
              f"{100 * s_['within3']:5.1f}%")
    print("\nringscan/plain plane RMS: " + ", ".join(f"{c} {k} {r:.2f}" for c, k, r in ratios))
    return 0


if __name__ == "__main__":
    sys.exit(main())
