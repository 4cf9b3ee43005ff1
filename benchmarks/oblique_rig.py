"""The oblique projector rig, virtual: a bust in front of a wall under OpenCV's Gray code (issue 19).

The rig is ``../shared/data/rigs/oblique_projector.json`` (a real rig's calibration: a
1920x1280 camera, a 1280x800 projector with its principal point near the bottom edge,
about 0.9 m apart). The scene: the goat head of ../shared/data/models (or ``--model``)
scaled to 600 mm, stood up facing the rig, 2.7-3.2 m from the camera (the real
scan's object stood 2.4-3.3 m off), 0.3 m in front of a wall (the plane z = 500 mm),
where the camera's rays run nearly along the projector's cones of constant ring radius:
78 % of its lit pixels meet their cone at |cos| < 0.1 (on the real scan, 75 % of the
torso's). Moved 300 mm to the right (``PLACE``), the same bust has 2 % there. Steps,
each a ``ringscan`` command (printed, so any can be rerun by hand):

1. ``ringscan simulate --captures opencv-graycode``: the column/row Gray code of a
   1280x800 projector, as OpenCV's structured-light module writes it (44 frames),
   rendered by the virtual rig (defocus, noise, supersampling), plus the truth.
2. ``ringscan import --rig <the true rig> --projector 1280x800``: ringscan's sub-pixel
   decode into a ``decoded`` scan.
3. ``ringscan reconstruct`` (today: the rings-only cone model), with any extra
   arguments of ``--reconstruct-args``.

Then it measures, against the ground truth (the lit pixels of the object and of the
wall, the truth mesh), for each way of getting points:

- ``ringscan reconstruct``: the points of step 3;
- ``integer ray-ray``: the plain OpenCV way: integer column/row codes of the captures
  (``decode_graycode``), camera and projector rays through ``cv2.triangulatePoints``;
- ``decode ray-ray``: ringscan's own sub-pixel decode (the imported proj_u, proj_v
  frames), both coordinates, through ``cv2.triangulatePoints``;
- ``truth ray-ray``: the truth projector coordinates of each pixel, the same way (the
  floor set by the triangulation and the truth's pixel-centre convention, not by a decode).

With ``--codec gray-rings`` (or ``phase-rings``) it also simulates ringscan's own codec on
the same scene (``ringscan simulate`` without ``--captures``: a scan folder; rings centred
on the projector's principal point as the import's, or ``--ring-center``),
reconstructs it and prints its points' coverage (camera pixels with a point, and
``evaluate``'s footprint coverage, the measure for codecs that sample ring boundaries),
errors and its median's ratio to the integer decode's.

Printed per method: coverage (pixels with a point / lit pixels) on the object and on
the wall; median and p95 point-to-surface distance to the truth mesh on the object
(and the median on the wall); the median on the object pixels that both the
reconstruction and the other method keep. Also: the share of lit object pixels whose
camera ray meets its ring's cone at |cos| < 0.1 (between the ray and the cone's normal,
as ``reconstruct`` computes its incidence), the decode's error against the truth
projector coordinates, and the reconstruction's drops by reason.

Figures from the virtual rig share the reconstruction's geometry code (camera and
light models) and a perfectly known rig: they measure the decode and the
triangulation, not a calibration; a real rig adds calibration error on top.

    RINGSCAN_SHARED_DATA=/path/to/shared/data  (default ../shared/data)
    python benchmarks/oblique_rig.py [--work DIR] [--model PATH] [--device cpu]
    python benchmarks/oblique_rig.py --scan-dir DIR                  # reuse DIR's render (and import)
    python benchmarks/oblique_rig.py --scan-dir DIR --reconstruct-args "--settings S.json"
    python benchmarks/oblique_rig.py --scan-dir DIR --reconstructed RECON_DIR   # measure a reconstruction only
    python benchmarks/oblique_rig.py --scan-dir DIR --codec gray-rings      # + ringscan's own codec, same scene

A full-size run (1920x1280, 44 frames) takes 3.5 minutes on two CPU cores;
``--scale 0.5`` renders with the camera's K and size scaled by 0.5 (1 minute; the
import uses the scaled rig written next to the render). Then a camera pixel sees
about 1.5 projector pixels: the finest bit is below the camera's resolution and the
import places the pixels between the boundaries of 2-pixel blocks (docs/calibration.md, "A
projector finer than the camera"; measured 2026-12-07: decode ray-ray 0.097 mm object
median, 0.137 on the wall; the decode before that 0.103 and 0.168; integer 0.69): a smoke
run, not figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ringscan.pipeline.calibrate.capture_reader import read_capture
from ringscan.pipeline.calibrate.graycode import decode_graycode
from ringscan.pipeline.calibrate.importer import procam_pose, triangulate_codes
from ringscan.pipeline.evaluate.metrics import evaluate_view, point_distances
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import load_rig, save_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.geometry import camera_rays, projector_pixels
from ringscan.pipeline.simulate.opencv_graycode import CAPTURE, OBJECT_MIN_HEIGHT_MM, read_graycode_truth
from ringscan.pipeline.simulate.truth import load_truth

DATA = Path(os.environ.get("RINGSCAN_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
RIG = DATA / "rigs" / "oblique_projector.json"
MODEL = DATA / "models" / "odedstein_goathead.obj"
PROJECTOR = (1280, 800)
SIZE_MM = 600.0
POSE = "x:-90,y:90"            # Y-up model, facing -x in its own frame -> up +y, facing +z (the rig)
PLACE = (-50.0, 436.0, 1000.0)  # 2.7-3.2 m from the camera, across the band where its rays run along the cones
WALL_Z = 500.0                 # 0.27 m behind the object's back, inside the rig's volume (z 0..2137)
GRAZING_COS = 0.1


def run(cmd: list[str]) -> None:
    print("$ " + " ".join(shlex.quote(c) for c in cmd), flush=True)
    t = time.perf_counter()
    if subprocess.run(cmd).returncode != 0:
        raise SystemExit(f"oblique_rig: the command above failed: {cmd[1]}")
    print(f"  ({time.perf_counter() - t:.0f} s)", flush=True)


def scaled_rig(rig, s: float):
    """The rig with its camera's image scaled by s (K and size; pixel centres kept)."""
    c = rig.camera
    K = c.K.copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    cam = dataclasses.replace(c, K=K, width=int(round(c.width * s)), height=int(round(c.height * s)))
    return dataclasses.replace(rig, camera=cam)


def to_world(rig, Xc: np.ndarray) -> np.ndarray:
    c = rig.camera
    return (Xc - c.t) @ c.R


def ray_ray(rig, px: np.ndarray, proj: np.ndarray) -> np.ndarray:
    """World points of camera pixels px (n, 2) and projector pixels proj (n, 2), cv2.triangulatePoints."""
    R, T = procam_pose(rig)
    c, li = rig.camera, rig.light
    Xc = triangulate_codes(px, proj, cam_K=c.K, cam_dist=c.dist, proj_K=li.K, proj_dist=li.dist, R=R, T=T)
    return to_world(rig, Xc)


def grazing_map(rig, truth: dict, mask: np.ndarray, centre=None) -> np.ndarray:
    """(H, W) bool: ``mask`` pixels whose camera ray meets its ring's cone at |cos| < GRAZING_COS.

    The rings are centred on ``centre`` (projector px; default the principal point, as imported)."""
    yy, xx = np.nonzero(mask)
    _, d = camera_rays(rig, np.stack([xx, yy], 1).astype(np.float64))
    depth = truth["depth"][yy, xx].astype(np.float64)
    c = rig.camera
    # the centre ray's point: camera-frame Z = depth along the unit ray's z component
    dz = d @ c.R.T
    X = c.center + d * (depth / dz[:, 2])[:, None]
    centre = rig.light.K[:2, 2] if centre is None else np.asarray(centre, np.float64)

    def rho(P):
        return np.hypot(*(projector_pixels(rig, P) - centre).T)

    h = 0.5
    r0 = rho(X)
    g = np.stack([rho(X + h * e) - r0 for e in np.eye(3)], 1)
    cos = np.abs(np.einsum("ij,ij->i", g, d)) / np.maximum(np.linalg.norm(g, axis=1), 1e-12)
    out = np.zeros(mask.shape, bool)
    out[yy, xx] = cos < GRAZING_COS
    return out


def measure(name: str, px: np.ndarray, P: np.ndarray, truth: dict, mesh, keep_ref: np.ndarray | None) -> dict:
    """Coverage and error of points P (n, 3) at camera pixels px (n, 2) int."""
    ok = np.all(np.isfinite(P), axis=1)
    px, P = px[ok], P[ok]
    H, W = truth["lit"].shape
    inside = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
    px, P = px[inside], P[inside]
    lit, obj = truth["lit"], truth["object"]
    hit = np.isfinite(truth["depth"])
    lit_obj, lit_wall = lit & obj, lit & ~obj & hit
    has = np.zeros((H, W), bool)
    has[px[:, 1], px[:, 0]] = True
    on_obj = lit_obj[px[:, 1], px[:, 0]]
    on_wall = lit_wall[px[:, 1], px[:, 0]]
    d = point_distances(mesh, P[on_obj | on_wall])
    d_obj = d[on_obj[on_obj | on_wall]]
    d_wall = d[on_wall[on_obj | on_wall]]
    res = {"name": name, "points": int(len(P)),
           "cov_obj": float((has & lit_obj).sum() / max(1, lit_obj.sum())),
           "cov_wall": float((has & lit_wall).sum() / max(1, lit_wall.sum())),
           "med_obj": float(np.median(d_obj)) if d_obj.size else float("nan"),
           "p95_obj": float(np.percentile(d_obj, 95)) if d_obj.size else float("nan"),
           "med_wall": float(np.median(d_wall)) if d_wall.size else float("nan"),
           "has": has, "err_map": None}
    err = np.full((H, W), np.nan)
    opx = px[on_obj]
    err[opx[:, 1], opx[:, 0]] = d_obj   # one point per pixel for these methods
    res["err_map"] = err
    if keep_ref is not None:
        both = keep_ref & has & lit_obj
        res["med_both"] = float(np.nanmedian(err[both])) if both.any() else float("nan")
    return res


def scan_truth(render: Path) -> dict:
    """depth, lit and object masks of a simulated scan's first view (object: off the wall by 0.5 mm)."""
    scan = load_scan(render)
    t = load_truth(scan)
    view = scan.views[0].name
    depth, lit = t.depth(view), t.lit(view)
    H, W = depth.shape
    yy, xx = np.nonzero(np.isfinite(depth))
    _, d = camera_rays(scan.rig, np.stack([xx, yy], 1).astype(np.float64))
    c = scan.rig.camera
    z = (c.center + d * (depth[yy, xx] / (d @ c.R.T)[:, 2])[:, None])[:, 2]
    obj = np.zeros((H, W), bool)
    obj[yy, xx] = z > float(scan.extra["truth"].get("wall_z", 0.0)) + OBJECT_MIN_HEIGHT_MM
    return {"scan": scan, "view": view, "depth": depth, "lit": lit, "object": obj}


def ring_codec(codec: str, *, rs: str, work: Path, rig_path: Path, model: str, extra: list, dev: list, mesh,
               integer_median: float, centre, sim_extra: list = ()) -> None:
    """ringscan's own codec on the same scene: simulate (scan folder), reconstruct, measure."""
    sim_tag = "_".join(a.strip("-") for a in sim_extra)[:60]
    render = work / (f"render_{codec}" + (f"_{sim_tag}" if sim_tag else ""))
    if not (render / "scan.json").is_file():
        run([rs, "simulate", "--rig", str(rig_path), "--scene", model, "--size-mm", str(SIZE_MM), "--up", "y",
             "--pose", POSE, "--place=" + ",".join(f"{c:g}" for c in PLACE), "--wall", str(WALL_Z),
             "--codec", codec, "--center", f"{centre[0]:.4f}", f"{centre[1]:.4f}", "--no-progress", "--out",
             str(render), *dev, *sim_extra])
    else:
        print(f"reusing the render in {render}")
    tag = "_".join(a.strip("-").replace("/", "_") for a in extra)[:60]
    recon = work / (f"recon_{codec}" + (f"_{sim_tag}" if sim_tag else "") + (f"_{tag}" if tag else ""))
    run([rs, "reconstruct", str(render), "--out", str(recon), "--no-progress", *dev, *extra])
    truth = scan_truth(render)
    scan = truth["scan"]
    cl = read_ply(sorted(recon.glob("*.ply"))[0])
    px = np.stack([np.round(cl["u"]), np.round(cl["v"])], 1).astype(int)
    P = np.stack([cl["x"], cl["y"], cl["z"]], 1).astype(np.float64)
    r = measure(f"{codec} reconstruct", px, P, truth, mesh, None)
    ev = evaluate_view(scan, truth["view"], P[np.all(np.isfinite(P), 1)])
    lit_obj = truth["lit"] & truth["object"]
    graz = grazing_map(scan.rig, truth, lit_obj, centre=scan.patterns.center)
    rest = lit_obj & ~graz
    rep = json.loads((recon / "report.json").read_text())
    print(f"\n{codec} on the same scene ({len(scan.views[0].frames)} frames, rings centred on "
          f"{tuple(round(c, 1) for c in scan.patterns.center)}): {recon} {' '.join(extra)}")
    print("| method | points | object pixels with a point | object coverage (evaluate, footprint) | "
          "object median mm | object p95 mm | wall median mm | object median / integer ray-ray |")
    print("|---|---|---|---|---|---|---|---|")
    print(f"| {r['name']} | {r['points']} | {100 * r['cov_obj']:.1f} % | {100 * ev['coverage_object']:.1f} % | "
          f"{r['med_obj']:.4f} | {r['p95_obj']:.4f} | {r['med_wall']:.4f} | {r['med_obj'] / integer_median:.2f}x |")
    print(f"lit object pixels with |cos| < {GRAZING_COS} to their ring's cone: "
          f"{100 * graz.sum() / max(1, lit_obj.sum()):.1f} %; object pixels with a point there / elsewhere: "
          f"{100 * (r['has'] & graz).sum() / max(1, graz.sum()):.1f} % / "
          f"{100 * (r['has'] & rest).sum() / max(1, rest.sum()):.1f} %")
    print(f"reconstruct drops: {json.dumps(rep.get('totals', {}).get('dropped', {}))}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", default=None, help="work folder (default: a temporary one, removed)")
    ap.add_argument("--scan-dir", default=None,
                    help="reuse this work folder's render (render/) and import (imported/) when present")
    ap.add_argument("--reconstructed", default=None,
                    help="measure this `ringscan reconstruct` output folder instead of running reconstruct")
    ap.add_argument("--reconstruct-args", default="",
                    help='extra arguments for `ringscan reconstruct`, e.g. "--settings S.json"')
    ap.add_argument("--rig", default=str(RIG), help=f"the rig (default {RIG})")
    ap.add_argument("--model", default=str(MODEL), help=f"the object mesh (default {MODEL})")
    ap.add_argument("--scale", type=float, default=1.0, help="camera image scale (default 1: 1920x1280)")
    ap.add_argument("--codec", action="append", default=[], choices=("gray-rings", "phase-rings"),
                    help="also simulate ringscan's own codec on the same scene (scan folder) and measure it "
                         "(repeatable; its reconstruction gets --reconstruct-args too)")
    ap.add_argument("--ring-center", type=float, nargs=2, default=None, metavar=("CU", "CV"),
                    help="ring centre of --codec (default the projector's principal point, as the import uses)")
    ap.add_argument("--simulate-args", default="",
                    help='extra arguments of `ringscan simulate` for --codec, e.g. "--angle-steps 4 --sector-bits 8"')
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    if not Path(args.rig).is_file() or not Path(args.model).is_file():
        print(f"oblique_rig: rig {args.rig} or model {args.model} not found (../shared/data)", file=sys.stderr)
        return 2
    if not 0.1 <= args.scale <= 1.0:
        print(f"oblique_rig: --scale must be in [0.1, 1], got {args.scale}", file=sys.stderr)
        return 2
    tmp = None
    if args.scan_dir:
        work = Path(args.scan_dir)
    elif args.work:
        work = Path(args.work)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="oblique_rig_")
        work = Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    rs = "ringscan"
    exe = str(Path(sys.executable).with_name(rs))
    rs = exe if Path(exe).is_file() else rs
    render, imported = work / "render", work / "imported"
    dev = ["--device", args.device]

    rig_path = Path(args.rig)
    if args.scale != 1.0:
        rig_path = work / f"rig_scale_{args.scale:g}.json"
        if not rig_path.is_file():
            save_rig(rig_path, scaled_rig(load_rig(args.rig), args.scale))
    if not (render / "truth.json").is_file():
        run([rs, "simulate", "--rig", str(rig_path), "--scene", args.model, "--size-mm", str(SIZE_MM), "--up", "y",
             "--pose", POSE, "--place=" + ",".join(f"{c:g}" for c in PLACE), "--wall", str(WALL_Z),
             "--captures", "opencv-graycode", "--no-progress", "--out", str(render), *dev])
    else:
        print(f"reusing the render in {render}")
    if not (imported / "scan.json").is_file():
        run([rs, "import", str(render / CAPTURE), "--rig", str(rig_path), "--projector",
             f"{PROJECTOR[0]}x{PROJECTOR[1]}", "--out", str(imported)])
    else:
        print(f"reusing the import in {imported}")
    extra = shlex.split(args.reconstruct_args)
    if args.reconstructed:
        recon = Path(args.reconstructed)
    else:
        tag = "_".join(a.strip("-").replace("/", "_") for a in extra)[:60]
        recon = work / ("recon" + (f"_{tag}" if tag else ""))
        run([rs, "reconstruct", str(imported), "--out", str(recon), "--no-progress", *dev, *extra])

    rig = load_rig(rig_path)
    truth = read_graycode_truth(render)
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(truth["mesh"]))
    lit_obj = truth["lit"] & truth["object"]
    H, W = lit_obj.shape

    # the reconstruction
    plys = sorted(recon.glob("*.ply"))
    if not plys:
        print(f"oblique_rig: no PLY in {recon}", file=sys.stderr)
        return 1
    cl = read_ply(plys[0])
    px = np.stack([np.round(cl["u"]), np.round(cl["v"])], 1).astype(int)
    P = np.stack([cl["x"], cl["y"], cl["z"]], 1).astype(np.float64)
    rows = [measure("ringscan reconstruct", px, P, truth, mesh, None)]
    keep = rows[0]["has"]

    # plain integer decode, OpenCV-style
    dec = decode_graycode(read_capture(render / CAPTURE, projector=PROJECTOR))
    yy, xx = np.nonzero(dec.valid)
    ipx = np.stack([xx, yy], 1)
    rows.append(measure("integer ray-ray", ipx, ray_ray(rig, ipx, np.stack([dec.col[yy, xx], dec.row[yy, xx]], 1)
                                                        .astype(np.float64)), truth, mesh, keep))
    # ringscan's own sub-pixel decode, both coordinates
    fu = read_image(imported / CAPTURE / "proj_u.png").astype(np.float64)
    fv = read_image(imported / CAPTURE / "proj_v.png").astype(np.float64)
    good = (fu > 0) & (fv > 0)
    yy, xx = np.nonzero(good)
    uv = np.stack([fu[yy, xx], fv[yy, xx]], 1) / load_scan(imported).patterns.scale - 1.0
    dpx = np.stack([xx, yy], 1)
    rows.append(measure("decode ray-ray", dpx, ray_ray(rig, dpx, uv), truth, mesh, keep))
    # the truth projector coordinates
    tp = truth["proj"]
    tl = truth["lit"] & np.all(np.isfinite(tp), -1)
    yy, xx = np.nonzero(tl)
    tpx = np.stack([xx, yy], 1)
    rows.append(measure("truth ray-ray", tpx, ray_ray(rig, tpx, tp[yy, xx].astype(np.float64)), truth, mesh, keep))

    both = good & lit_obj
    du = np.abs(uv[:, 0] - tp[good][:, 0])[lit_obj[good]]
    dv = np.abs(uv[:, 1] - tp[good][:, 1])[lit_obj[good]]
    graz_map = grazing_map(rig, truth, lit_obj)
    graz = float(graz_map.sum() / max(1, lit_obj.sum()))
    rest = lit_obj & ~graz_map
    rep = json.loads((recon / "report.json").read_text()) if (recon / "report.json").is_file() else {}
    drops = rep.get("totals", {}).get("dropped", {})

    print(f"\noblique rig (virtual), {W}x{H} camera, {PROJECTOR[0]}x{PROJECTOR[1]} projector, OpenCV Gray code; "
          f"lit object pixels {int(lit_obj.sum())}, lit wall pixels {int((truth['lit'] & ~truth['object']).sum())}")
    print(f"reconstruction: {recon} {' '.join(extra)}")
    print("| method | points | object coverage | wall coverage | object median mm | object p95 mm | "
          "wall median mm | median on pixels both keep |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        mb = r.get("med_both")
        print(f"| {r['name']} | {r['points']} | {100 * r['cov_obj']:.1f} % | {100 * r['cov_wall']:.1f} % | "
              f"{r['med_obj']:.3f} | {r['p95_obj']:.3f} | {r['med_wall']:.3f} | "
              f"{'-' if mb is None else f'{mb:.3f}'} |")
    ref = rows[1]["med_obj"]
    print("\nobject median / integer ray-ray median: "
          + ", ".join(f"{r['name']} {r['med_obj'] / ref:.2f}x" for r in rows))
    print(f"lit object pixels with |cos| < {GRAZING_COS} between the camera ray and the ring cone: {100 * graz:.1f} %")
    print("object coverage where |cos| < 0.1 / elsewhere: " + ", ".join(
        f"{r['name']} {100 * (r['has'] & graz_map).sum() / max(1, graz_map.sum()):.1f} % / "
        f"{100 * (r['has'] & rest).sum() / max(1, rest.sum()):.1f} %" for r in rows))
    print(f"decode vs truth projector coordinates on {int(both.sum())} lit object pixels: |du| median "
          f"{np.median(du):.3f} px, p95 {np.percentile(du, 95):.3f}; |dv| median {np.median(dv):.3f} px, p95 "
          f"{np.percentile(dv, 95):.3f}")
    print(f"reconstruct drops: {json.dumps(drops)}")
    for codec in args.codec:
        ring_codec(codec, rs=rs, work=work, rig_path=rig_path, model=args.model, extra=extra, dev=dev, mesh=mesh,
                   sim_extra=shlex.split(args.simulate_args),
                   integer_median=ref, centre=args.ring_center or tuple(rig.light.K[:2, 2]))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
