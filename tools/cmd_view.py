"""``ringscan view FILE [FILE ...] --out PNG``: offscreen render of clouds and meshes."""

from __future__ import annotations

from ringscan.pipeline.evaluate.conditioning import ConditioningSettings
from ringscan.pipeline.formats.atomic import check_output_file
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.meshes import read_mesh
from ringscan.pipeline.preview.colour import colorize
from ringscan.pipeline.preview.render import ViewSettings, read_geometry, render_to_png
from ringscan.tools.cli import add_device_option


def add_parser(sub):
    p = sub.add_parser("view", help="render point clouds and meshes to a PNG (offscreen)",
                       description="Renders each FILE (a mesh when it has faces, else a point cloud) into one "
                                   "picture with Open3D's offscreen renderer (software point splats when it "
                                   "cannot start). With --truth the first file is coloured by its distance to "
                                   "the truth mesh and a colour bar is added.")
    p.add_argument("files", nargs="*", metavar="FILE", help="PLY/OBJ/STL mesh or point cloud files")
    p.add_argument("--out", required=True, metavar="PNG", help="output PNG (SVG too with --conditioning)")
    c = p.add_argument_group("conditioning map (instead of FILEs)")
    c.add_argument("--conditioning", default=None, metavar="SCAN_OR_RIG",
                   help="per camera pixel, the predicted depth sigma of rings alone, the angle alone and both, "
                        "for a scan folder's rig and patterns, or a rig file (default gray-rings patterns): "
                        "where a rig is blind, before scanning")
    cd = ConditioningSettings()
    c.add_argument("--plane-z", type=float, default=None, metavar="MM",
                   help="world z of the plane the camera rays meet (default: the middle of the working volume)")
    c.add_argument("--step", type=int, default=cd.step, help=f"camera pixels between evaluated pixels (default {cd.step})")
    c.add_argument("--sigma-rho", type=float, default=cd.sigma_rho_px, metavar="PX",
                   help=f"standard deviation of the ring coordinate, projector px (default {cd.sigma_rho_px:g})")
    c.add_argument("--sigma-tan", type=float, default=cd.sigma_tan_px, metavar="PX",
                   help=f"standard deviation of the angle's tangential position, projector px (default {cd.sigma_tan_px:g})")
    add_device_option(p)
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
    p.add_argument("--truth", default=None, metavar="MESH",
                   help="colour the first file by distance to this mesh (mm), with a colour bar")
    p.add_argument("--max-error", type=float, default=None, metavar="MM",
                   help="top of the --truth colour scale (default: 99th percentile)")
    return p


def run_conditioning(args) -> int:
    import json
    import os

    from ringscan.pipeline.evaluate.conditioning import compute_conditioning, plot_conditioning
    from ringscan.pipeline.formats.patterns import default_patterns
    from ringscan.pipeline.formats.rig import load_rig
    from ringscan.pipeline.formats.scan import load_scan

    out = check_output_file(args.out, extensions=(".png", ".svg"), what="picture (--out)")
    src = args.conditioning
    if os.path.isdir(src):
        scan = load_scan(src, check_files=False)
        rig, spec = scan.rig, scan.patterns
    else:
        rig = load_rig(src)
        size = (rig.light.width, rig.light.height) if hasattr(rig.light, "width") else (1024, 768)
        spec = default_patterns("gray-rings", width=size[0], height=size[1], source=src)
    settings = ConditioningSettings(plane_z=args.plane_z, step=args.step, sigma_rho_px=args.sigma_rho,
                                    sigma_tan_px=args.sigma_tan)
    cmap = compute_conditioning(rig, center=spec.center, rho_range=(spec.rho0, spec.rho_max),
                                sector_bits=spec.sector_bits, settings=settings, device=args.device)
    plot_conditioning(cmap, out, title=f"{src}: plane z = {cmap.plane_z:g} mm")
    print(json.dumps(cmap.summary()))
    print(f"wrote {args.out}")
    return 0


def run(args) -> int:
    if args.conditioning:
        if args.files:
            raise FormatError(args.files[0], "give either FILEs or --conditioning, not both")
        return run_conditioning(args)
    if not args.files:
        raise FormatError(None, "view: give FILEs to render, or --conditioning SCAN_OR_RIG")
    import numpy as np
    import open3d as o3d

    out = check_output_file(args.out, extensions=(".png",), what="picture (--out)")
    geoms = [read_geometry(f) for f in args.files]
    bar = None
    if args.truth:
        truth = read_mesh(args.truth)
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
    res = render_to_png(geoms, out, settings=s, colorbar_spec=bar)
    print(f"wrote {args.out} ({args.width}x{args.height}, {res.renderer} renderer)")
    return 0
