"""``ringscan mesh CLOUD.ply --out MESH.{ply,obj,stl}``: mesh a point cloud."""

from __future__ import annotations

from ringscan.pipeline.formats.atomic import check_no_overwrite, check_output_file
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.meshes import MESH_FORMATS, read_cloud, write_mesh
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.fusion.mesh import (
    MAX_COORDINATE_MM,
    MIN_MESH_POINTS,
    MeshSettings,
    drop_unusable_points,
    orient_normals,
)
from ringscan.pipeline.fusion.meshing import mesh_cloud
from ringscan.tools.cli import basic_options
from ringscan.tools.cmd_fuse import WATERTIGHT_COST


def add_parser(sub):
    p = sub.add_parser("mesh", help="mesh a point cloud (Poisson or TSDF) into PLY, OBJ or STL",
                       description="CLOUD is a point cloud file (e.g. fused.ply of `ringscan fuse`). Normals are "
                                   "used when present, else estimated and oriented outward. The output format "
                                   "follows the extension of --out.")
    p.add_argument("cloud", metavar="CLOUD", help="point cloud file (PLY, PCD, XYZ, ...)")
    p.add_argument("--out", required=True, metavar="MESH", help="output mesh: .ply, .obj or .stl")
    p.add_argument("--method", choices=("poisson", "tsdf"), default="poisson", help="meshing method (default poisson)")
    p.add_argument("--watertight", action="store_true",
                   help=f"closed manifold mesh (checked with is_watertight); {WATERTIGHT_COST}")
    p.add_argument("--poisson-depth", type=int, default=None, metavar="N",
                   help=f"Poisson octree depth (default {MeshSettings.poisson_depth})")
    p.add_argument("--density-quantile", type=float, default=None, metavar="Q",
                   help=f"trim Poisson vertices below this density quantile (default {MeshSettings.density_quantile})")
    p.add_argument("--tsdf-voxel", type=float, default=None, metavar="MM",
                   help=f"TSDF voxel size (default {MeshSettings.tsdf_voxel_mm})")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="CPU threads for Poisson (default 1: the same bytes from run to run; 0 = every core, "
                        "faster, last bits vary; docs/fusion.md)")
    basic_options(p, "--method", "--watertight", "--poisson-depth")
    return p


def run(args) -> int:
    out = check_output_file(args.out, extensions=MESH_FORMATS, what="mesh file (--out)")
    check_no_overwrite([out], [args.cloud])
    kw = {"method": args.method, "watertight": args.watertight}
    if args.watertight:
        print(f"--watertight: {WATERTIGHT_COST}", flush=True)
    if args.poisson_depth is not None:
        kw["poisson_depth"] = args.poisson_depth
    if args.density_quantile is not None:
        kw["density_quantile"] = args.density_quantile
    if args.tsdf_voxel is not None:
        kw["tsdf_voxel_mm"] = args.tsdf_voxel
    if args.threads is not None:
        kw["threads"] = args.threads
    settings = MeshSettings(**kw)
    cloud = read_cloud(args.cloud)
    n_in = len(cloud.points)
    cloud, dropped = drop_unusable_points(cloud)
    if dropped["non_finite"] or dropped["out_of_range"]:
        print(f"dropped {dropped['non_finite']} of {n_in} points with a NaN or infinite coordinate or normal, and "
              f"{dropped['out_of_range']} beyond +-{MAX_COORDINATE_MM:g} mm")
    if len(cloud.points) < MIN_MESH_POINTS:
        raise FormatError(args.cloud, f"{len(cloud.points)} usable points (of {n_in}): too few to mesh "
                                      f"(need at least {MIN_MESH_POINTS})")
    try:
        if not cloud.has_normals():
            orient_normals(cloud)
        with progress_step(f"{settings.method} meshing {len(cloud.points)} points", enabled=not args.no_progress):
            res = mesh_cloud(cloud, settings=settings)
    except ValueError as e:
        raise FormatError(args.cloud, str(e)) from None
    if len(res.mesh.triangles) == 0:
        raise FormatError(args.cloud, f"meshing its {len(cloud.points)} points gave no surface (too few or too "
                                      f"scattered for {res.method})")
    write_mesh(out, res.mesh)
    wt = "" if res.watertight is None else f", watertight {res.watertight}"
    print(f"{res.method} mesh: {res.info['vertices']} vertices, {res.info['triangles']} triangles{wt}; wrote {out}")
    if args.watertight and not res.watertight:
        print("warning: the mesh is not watertight")
        return 1
    return 0
