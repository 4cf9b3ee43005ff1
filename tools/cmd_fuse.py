"""``ringscan fuse SCAN_OR_RECON [SCAN_OR_RECON ...] --out DIR``: fused cloud, mesh, preview and report.

Several sources are scans of one object in several poses (flip and rescan): the
first is the reference pose, the others are aligned to it and merged."""

from __future__ import annotations

from ringscan.pipeline.formats.atomic import check_output_folder
from ringscan.pipeline.formats.meshes import MESH_FORMATS
from ringscan.pipeline.fusion.mesh import MeshSettings
from ringscan.pipeline.fusion.poses import PoseSettings
from ringscan.pipeline.fusion.turntable import FuseSettings
from ringscan.pipeline.fusion.workflow import fuse_and_mesh
from ringscan.tools.cli import UsageError, add_device_option, basic_options


WATERTIGHT_COST = ("closing the surface where no view looked takes several times an open mesh's time "
                   "(~6x on the demo)")
"""Said before a watertight mesh starts (and in --help): the wait is the option's, not a hang."""


def add_parser(sub):
    p = sub.add_parser("fuse", help="fuse turntable views into one cloud and mesh it",
                       description="SCAN_OR_RECON is a reconstruction folder (report.json + one PLY per view) or a "
                                   "scan folder (reconstructed first into DIR/recon). Writes DIR/fused.ply, "
                                   "DIR/mesh.<ext>, DIR/preview.png and DIR/fuse_report.json (per-view residuals "
                                   "and the resolved settings). Several sources are scans of the same object in "
                                   "several poses (flip and rescan): each is fused on its own, the others are "
                                   "aligned to the first (FPFH + RANSAC, then ICP) and merged in its object frame; "
                                   "fuse_report.json then has a per-pose section (transform, fitness, inlier RMSE). "
                                   "A pose that fails to align is an error naming it.")
    p.add_argument("source", metavar="SCAN_OR_RECON", nargs="+",
                   help="reconstruction folder or scan folder; more than one: further poses of the object")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--method", choices=("poisson", "tsdf"), default="poisson", help="meshing method (default poisson)")
    p.add_argument("--watertight", action="store_true",
                   help=f"closed manifold mesh (checked with is_watertight); {WATERTIGHT_COST}")
    p.add_argument("--formats", default="ply", metavar="LIST",
                   help="mesh formats, comma-separated from ply,obj,stl (default ply)")
    p.add_argument("--voxel", default=None, metavar="MM",
                   help=f"voxel size of the fused cloud, > 0; 'none' keeps every point of every view "
                        f"(default {FuseSettings.voxel_mm})")
    p.add_argument("--ground-clip", default=None, metavar="MM",
                   help=f"drop points below this world z; 'none' keeps all (default {FuseSettings.ground_clip_mm})")
    p.add_argument("--no-refine", action="store_true", help="trust the turntable axis: no ICP / pose graph")
    p.add_argument("--poisson-depth", type=int, default=None, metavar="N",
                   help=f"Poisson octree depth (default {MeshSettings.poisson_depth})")
    p.add_argument("--tsdf-voxel", type=float, default=None, metavar="MM",
                   help=f"TSDF voxel size (default {MeshSettings.tsdf_voxel_mm})")
    p.add_argument("--truth", default=None, metavar="MESH_OR_SCAN",
                   help="measure the mesh against this truth mesh (or a simulated scan's truth)")
    p.add_argument("--min-pose-fitness", type=float, default=None, metavar="F",
                   help=f"several poses: a pose whose ICP fitness against the first is below this fails "
                        f"(default {PoseSettings.min_fitness})")
    p.add_argument("--max-pose-rmse", type=float, default=None, metavar="MM",
                   help=f"several poses: a pose whose ICP inlier RMSE is above this fails "
                        f"(default {PoseSettings.max_rmse_mm})")
    p.add_argument("--no-pose-graph", action="store_true",
                   help="several poses: align each pose to the first only (no pose graph across poses)")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="CPU threads for Open3D's ICP, RANSAC and Poisson (default 1: the same bytes from run to "
                        "run; 0 = every core, faster, last bits vary; docs/fusion.md)")
    p.add_argument("--no-preview", action="store_true", help="do not render preview.png")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_device_option(p)
    basic_options(p, "--method", "--watertight", "--formats", "--truth")
    return p


def parse_formats(text: str) -> tuple[str, ...]:
    fmts = tuple("." + f.strip().lower().lstrip(".") for f in text.split(",") if f.strip())
    bad = [f for f in fmts if f not in MESH_FORMATS]
    if not fmts or bad:
        raise UsageError(f"--formats: expected some of ply, obj, stl, got {text!r}")
    return fmts


def parse_voxel(text: str) -> float:
    """--voxel: a finite number of mm > 0, or 'none' (0.0: keep every point)."""
    if text.strip().lower() == "none":
        return 0.0
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (0 < v < float("inf")):
        raise UsageError(f"--voxel: expected a finite number of mm > 0 (or 'none' to keep every point), got {text!r}")
    return v


def run(args) -> int:
    check_output_folder(args.out, what="output folder (--out)")
    voxel = None if args.voxel is None else parse_voxel(args.voxel)
    fkw = {}
    if voxel is not None:
        fkw["voxel_mm"] = voxel
    if args.ground_clip is not None:
        if args.ground_clip.lower() == "none":
            fkw["ground_clip_mm"] = None
        else:
            try:
                fkw["ground_clip_mm"] = float(args.ground_clip)
            except ValueError:
                raise UsageError(f"--ground-clip: expected a number of mm or 'none', "
                                 f"got {args.ground_clip!r}") from None
    if args.no_refine:
        fkw["refine"] = False
    mkw = {"method": args.method, "watertight": args.watertight}
    if args.watertight:
        print(f"--watertight: {WATERTIGHT_COST}", flush=True)
    if args.poisson_depth is not None:
        mkw["poisson_depth"] = args.poisson_depth
    if args.tsdf_voxel is not None:
        mkw["tsdf_voxel_mm"] = args.tsdf_voxel
    pkw = {}
    if voxel is not None:
        pkw["voxel_mm"] = voxel
    if args.min_pose_fitness is not None:
        pkw["min_fitness"] = args.min_pose_fitness
    if args.max_pose_rmse is not None:
        pkw["max_rmse_mm"] = args.max_pose_rmse
    if args.no_pose_graph:
        pkw["pose_graph"] = False
    if args.threads is not None:
        fkw["threads"] = mkw["threads"] = pkw["threads"] = args.threads
    sources = args.source[0] if len(args.source) == 1 else list(args.source)
    rep = fuse_and_mesh(sources, args.out, fuse_settings=FuseSettings(**fkw), mesh_settings=MeshSettings(**mkw),
                        formats=parse_formats(args.formats), preview=not args.no_preview, truth=args.truth,
                        device=args.device, progress=not args.no_progress, pose_settings=PoseSettings(**pkw),
                        preview_scale_bar=True)  # preview.png carries its scale, as the demo's does
    if "poses" in rep["fusion"]:
        # fitness / p2pl: against all other poses; fit ref: against the first alone;
        # o3d rmse: Open3D's point-to-point inlier RMSE (reported, not checked).
        print(f"{'#':<3}{'pose':<30}{'points':>8}{'fitness':>9}{'fit ref':>9}{'p2pl mm':>9}{'o3d rmse':>9}"
              f"{'rot deg':>9}{'trans mm':>10}  aligned with")
        for k, ps in enumerate(rep["fusion"]["poses"]):
            print(f"{k:<3}{ps['name'][-30:]:<30}{ps['points']:>8}{ps['fitness']:>9.3f}{ps['fitness_to_reference']:>9.3f}"
                  f"{ps['plane_rmse_mm']:>9.4f}{ps['inlier_rmse_mm']:>9.4f}{ps['rotation_deg']:>9.2f}"
                  f"{ps['translation_mm']:>10.2f}  {'-' if k == 0 else ps['aligned_with'][-30:]}")
    pose_index = {ps["name"]: k for k, ps in enumerate(rep["fusion"].get("poses", []))}
    print(f"{'view':<12}{'deg':>7}{'points':>9}{'kept':>9}{'fit before':>11}{'rms before':>11}{'fit':>7}"
          f"{'rms mm':>8}{'corr mm':>9}{'corr deg':>9}")
    for v in rep["fusion"]["views"]:
        name = f"{pose_index[v['pose']]}:{v['name']}" if "pose" in v else v["name"]
        print(f"{name:<12}{v['turntable_deg']:>7.1f}{v['points_in']:>9}{v['points_kept']:>9}"
              f"{v['fitness_before']:>11.3f}{v['rmse_before_mm']:>11.4f}{v['fitness']:>7.3f}{v['rmse_mm']:>8.4f}"
              f"{v['correction_mm']:>9.3f}{v['correction_deg']:>9.3f}"
              + ("  angle kept (not fixed by the overlap)" if v.get("angle_held") else ""))
    m = rep["mesh"]
    wt = "" if m["watertight"] is None else f", watertight {m['watertight']}"
    print(f"fused {rep['fusion']['points']} points; {m['method']} mesh {m['vertices']} vertices, "
          f"{m['triangles']} triangles{wt}; {rep['seconds']['total']:.1f} s")
    if "truth" in rep:
        t = rep["truth"]
        print(f"vs truth: mesh->truth {t['mesh_to_truth_mean']:.4f} mm, truth->mesh {t['truth_to_mesh_mean']:.4f} mm, "
              f"{100 * t['truth_within']:.2f}% of truth within {t['within_mm']} mm")
    outs = rep["outputs"]
    files = [outs["cloud"], *outs["meshes"], *([outs["preview"]] if "preview" in outs else []), "fuse_report.json"]
    print(f"wrote {args.out}/: {', '.join(files)}"
          + (f" (preview.png: scale bar {outs['preview_scale_bar_mm']:g} mm)" if outs.get("preview_scale_bar_mm") else ""))
    if outs.get("removed"):
        print(f"removed {', '.join(outs['removed'])}: left in {args.out}/ by an earlier run, not asked for this time")
    if args.watertight and not m["watertight"]:
        print("warning: the mesh is not watertight (see fuse_report.json mesh checks)")
        return 1
    return 0
