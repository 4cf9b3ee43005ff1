"""``ringscan view FILE [FILE ...] --out PNG``: offscreen render of clouds and meshes."""

from __future__ import annotations

from ringscan.pipeline.formats.atomic import check_output_file
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.fusion.workflow import load_truth_mesh
from ringscan.pipeline.preview.colour import colorize
from ringscan.pipeline.preview.render import ViewSettings, read_geometry, render_to_png


def add_parser(sub):
    p = sub.add_parser("view", help="render point clouds and meshes to a PNG (offscreen)",
                       description="Renders each FILE (a mesh when it has faces, else a point cloud) into one "
                                   "picture with Open3D's offscreen renderer (software point splats when it "
                                   "cannot start). With --truth the first file is coloured by its distance to "
                                   "the truth mesh and a colour bar is added.")
    p.add_argument("files", nargs="+", metavar="FILE", help="PLY/OBJ/STL mesh or point cloud files")
    p.add_argument("--out", required=True, metavar="PNG", help="output PNG")
    d = ViewSettings()
    p.add_argument("--width", type=int, default=d.width, help=f"image width (default {d.width})")
    p.add_argument("--height", type=int, default=d.height, help=f"image height (default {d.height})")
    p.add_argument("--azimuth", type=float, default=d.azimuth_deg,
                   help=f"view direction about z, degrees (default {d.azimuth_deg})")
    p.add_argument("--elevation", type=float, default=d.elevation_deg,
                   help=f"view direction above the x-y plane, degrees (default {d.elevation_deg})")
    p.add_argument("--point-size", type=float, default=d.point_size, help=f"point size in px (default {d.point_size})")
    p.add_argument("--renderer", choices=("auto", "open3d", "software"), default="auto",
                   help="auto: Open3D, or software when Open3D cannot start (default auto)")
    p.add_argument("--truth", default=None, metavar="MESH_OR_SCAN",
                   help="colour the first file by distance to this truth mesh, or to a simulated scan's truth "
                        "mesh (mm), with a colour bar")
    p.add_argument("--max-error", type=float, default=None, metavar="MM",
                   help="top of the --truth colour scale (default: 99th percentile)")
    return p


def run(args) -> int:
    import numpy as np
    import open3d as o3d

    out = check_output_file(args.out, extensions=(".png",), what="picture (--out)")
    geoms = [read_geometry(f) for f in args.files]
    bar = None
    if args.truth:
        truth = load_truth_mesh(args.truth)
        g = geoms[0]
        pts = np.asarray(g.vertices if hasattr(g, "triangles") else g.points, np.float32)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(truth))
        dist = scene.compute_distance(o3d.core.Tensor(pts)).numpy().astype(np.float64)
        vmax = args.max_error if args.max_error else max(float(np.quantile(dist, 0.99)), 1e-6)
        geoms[0] = colorize(g, dist, vmin=0.0, vmax=vmax, cmap="turbo")
        bar = {"vmin": 0.0, "vmax": vmax, "cmap": "turbo", "label": "dist (mm)"}
        print(f"distance to truth: mean {dist.mean():.4f} mm, median {np.median(dist):.4f} mm, "
              f"p95 {np.quantile(dist, 0.95):.4f} mm")
    s = ViewSettings(width=args.width, height=args.height, azimuth_deg=args.azimuth, elevation_deg=args.elevation,
                     point_size=args.point_size, renderer=args.renderer)
    with progress_step(f"rendering {out.name}", enabled=not args.no_progress):
        res = render_to_png(geoms, out, settings=s, colorbar_spec=bar)
    w, h = res.png_size
    print(f"wrote {args.out} ({w}x{h}, {res.renderer} renderer)")
    return 0
