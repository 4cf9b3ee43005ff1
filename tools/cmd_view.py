"""``ringscan view FILE [FILE ...] --out PNG``: offscreen render of clouds and meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ringscan.pipeline.evaluate.conditioning import ConditioningSettings
from ringscan.pipeline.evaluate.metrics import point_distances, truth_surface
from ringscan.pipeline.formats.atomic import check_output_file
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.fusion.workflow import load_truth_mesh
from ringscan.pipeline.preview.clouds import CLOUD_FIELDS, cloud_field, length_unit, own_camera, shade_cloud
from ringscan.pipeline.preview.colour import category_colours, colorize, readable_unit
from ringscan.pipeline.preview.render import ViewSettings, read_geometry, render_to_png, view_camera
from ringscan.tools.cli import UsageError, add_device_option, basic_options

CATEGORICAL = ("view", "ring")
"""Fields whose values name things (a view, a ring): one colour each and a legend, not a scale."""
MAX_CATEGORIES = 20
"""More distinct values than this (a scan of 60 rings) get a scale with whole-number ticks instead."""
FIXED_RANGE = {"confidence": (0.0, 1.0)}
"""Fields with a range of their own: the colours mean the same from one picture to the next."""

NOT_DECODED = "no point (not decoded)"
"""The key of the hatched pixels of a view seen from its own camera: where it decoded nothing (a board's
dark squares, a shadow), which plain would read as white surface."""

FLOOR_MM = 0.5
"""--truth SCAN: points within this height of the reference plane are the floor, reported apart
(the same split as evaluate's object coverage)."""


def add_parser(sub):
    p = sub.add_parser("view", help="render point clouds and meshes to a PNG (offscreen)",
                       description="Renders each FILE (a mesh when it has faces, else a point cloud) into one "
                                   "picture with Open3D's offscreen renderer (software point splats when it "
                                   "cannot start). Point clouds without normals get estimated ones, so they are "
                                   "shaded. A single view's PLY from `reconstruct` is seen from the camera that "
                                   "took it (its report.json holds the rig), so it looks like the camera's photo; "
                                   "--azimuth/--elevation or --camera orbit frame everything from outside instead. "
                                   "--color-by colours the first file by a field, with a colour bar; with --truth "
                                   "it is coloured by its distance to the truth. --conditioning draws a rig's "
                                   "conditioning map instead of FILEs; --residuals a view's residual map.")
    p.add_argument("files", nargs="*", metavar="FILE", help="PLY/OBJ/STL mesh or point cloud files")
    p.add_argument("--out", required=True, metavar="PNG", help="output PNG (or SVG with --conditioning)")
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
    r = p.add_argument_group("residual map (instead of FILEs)")
    r.add_argument("--residuals", default=None, metavar="VIEW_PLY",
                   help="a view's PLY from `ringscan reconstruct`: each point's residual (two cameras: RMS "
                        "reprojection px; one camera: the projector-side residual) at its camera-1 pixel, with "
                        "the view's calibration check from the report.json beside it")
    add_device_option(p)
    d = ViewSettings()
    p.add_argument("--width", type=int, default=d.width, help=f"image width (default {d.width})")
    p.add_argument("--height", type=int, default=None,
                   help=f"image height (default {d.height}; with the view's own camera, its aspect ratio)")
    p.add_argument("--camera", choices=("auto", "own", "orbit"), default="auto",
                   help="own: the camera that took a view's PLY; orbit: --azimuth/--elevation around the "
                        "objects; auto: own for a single view's PLY, else orbit (default auto)")
    p.add_argument("--azimuth", type=float, default=None,
                   help=f"orbit camera: view direction about z, degrees (default {d.azimuth_deg})")
    p.add_argument("--elevation", type=float, default=None,
                   help=f"orbit camera: view direction above the x-y plane, degrees (default {d.elevation_deg})")
    p.add_argument("--point-size", type=float, default=d.point_size, help=f"point size in px (default {d.point_size})")
    p.add_argument("--renderer", choices=("auto", "open3d", "software"), default="auto",
                   help="auto: Open3D, or software when Open3D cannot start (default auto)")
    p.add_argument("--color-by", choices=("none", *CLOUD_FIELDS, "error"), default=None,
                   help="colour the first file by this field, with a colour bar: height (z, mm), a PLY property "
                        "(confidence, rho, ring, view), or error (distance to --truth, mm; the default with "
                        "--truth); default none")
    p.add_argument("--cmap", default="turbo", choices=("turbo", "viridis", "inferno", "jet"),
                   help="colour map of --color-by (default turbo)")
    p.add_argument("--truth", default=None, metavar="MESH_OR_SCAN",
                   help="a truth mesh, or a simulated scan folder (its object placed at the view's table angle, "
                        "with its floor): colour the first file by distance to it (mm); with a scan the floor "
                        "points are reported apart")
    p.add_argument("--no-scale-bar", action="store_true",
                   help="no scale bar (a round number of mm, true at the points' median depth, lower left)")
    p.add_argument("--max-error", type=float, default=None, metavar="MM",
                   help="top of the error colour scale (default: 99th percentile)")
    basic_options(p, "--truth", "--color-by", "--max-error", "--conditioning", "--residuals")
    return p


def run_conditioning(args) -> int:
    import json
    import os

    from ringscan.pipeline.codecs import DEFAULT_CODEC
    from ringscan.pipeline.evaluate.conditioning import (MAX_MAP_PIXELS, compute_conditioning, map_step_needed,
                                                         plot_conditioning)
    from ringscan.pipeline.formats.patterns import default_patterns
    from ringscan.pipeline.formats.rig import load_rig

    out = check_output_file(args.out, extensions=(".png", ".svg"), what="picture (--out)")
    if args.step < 1:
        raise UsageError(f"--step {args.step}: expected a whole number >= 1")
    if not (args.sigma_rho > 0 and args.sigma_tan > 0):
        raise UsageError("--sigma-rho, --sigma-tan: expected standard deviations > 0 (projector px)")
    src = args.conditioning
    why = ""
    if os.path.isdir(src):
        scan = load_scan(src, check_files=False)
        rig, spec = scan.rig, scan.patterns
        if not spec.layout.projectable:  # imported: projector columns and rows, no rings to map
            why = (f"{src} was decoded on import (codec '{spec.codec}': projector columns and rows, no rings); "
                   "the map is of a ring codec: give its rig file for the default gray-rings patterns")
    else:
        rig = load_rig(src)
        size = (rig.light.width, rig.light.height) if hasattr(rig.light, "width") else (1024, 768)
        spec = default_patterns(DEFAULT_CODEC, width=size[0], height=size[1], source=src)
    need = map_step_needed(rig.camera.width, rig.camera.height)
    if args.step < need:  # before: a 65536x65536 camera asked for 64 GiB
        raise UsageError(f"--step {args.step}: the map of the {rig.camera.width}x{rig.camera.height} camera of {src} "
                         f"would evaluate more than {MAX_MAP_PIXELS} pixels (~1.5 GB); give --step {need} or more")
    settings = ConditioningSettings(plane_z=args.plane_z, step=args.step, sigma_rho_px=args.sigma_rho,
                                    sigma_tan_px=args.sigma_tan)
    with progress_step("conditioning map", enabled=not args.no_progress):
        cmap = compute_conditioning(rig, center=spec.center, rho_range=(spec.rho0, spec.rho_max),
                                    sector_bits=spec.sector_bits, settings=settings, device=args.device)
        plot_conditioning(cmap, out, title=f"{src}: plane z = {cmap.plane_z:g} mm", empty_why=why)
    if why and not cmap.lit.any():
        print(f"no panel has a value: {why}")
    print(json.dumps(cmap.summary()))
    print(f"wrote {args.out}")
    return 0


def run_residuals(args) -> int:
    import json

    from ringscan.pipeline.evaluate.residuals import plot_residuals, residual_map
    from ringscan.pipeline.formats.atomic import read_json
    from ringscan.pipeline.formats.errors import FormatError
    from ringscan.pipeline.formats.ply import read_ply

    out = check_output_file(args.out, extensions=(".png", ".svg"), what="picture (--out)")
    src = Path(args.residuals)
    fields = read_ply(src)
    width = height = None
    check = None
    unit = "px"
    rep_path = src.parent / "report.json"
    if rep_path.is_file():
        rep = read_json(rep_path)
        cam = (rep.get("rig") or {}).get("camera") or {}
        width, height = cam.get("width"), cam.get("height")
        view = next((v for v in rep.get("views", []) if v.get("name") == src.stem), {})
        check = view.get("calibration_check")
        if view.get("rays", "camera-projector") == "camera-projector" and view.get("constraint") == "rings":
            unit = "sectors"
    if not (isinstance(width, int) and isinstance(height, int)):
        if "u" not in fields or "v" not in fields or fields["u"].size == 0:
            raise FormatError(src, "no points with camera pixels (u, v): not a view's PLY from ringscan reconstruct")
        width, height = int(np.ceil(fields["u"].max())) + 1, int(np.ceil(fields["v"].max())) + 1
    try:
        rmap = residual_map(fields, width=width, height=height, check=check)
    except ValueError as e:
        raise FormatError(src, str(e)) from None
    plot_residuals(rmap, out, title=str(src), unit=unit)
    print(json.dumps(rmap.summary))
    print(f"wrote {args.out}")
    return 0


def _truth_distances(args, g, cam):
    """Distance of each point of ``g`` to the truth, and a mask of the floor's points (or None)."""
    pts = np.asarray(g.vertices if hasattr(g, "triangles") else g.points, np.float64)
    if Path(args.truth).is_dir():
        scan = load_scan(args.truth, check_files=False)
        mesh = truth_surface(scan, cam.turntable_deg if cam is not None else 0.0)
        zp = float(scan.extra["truth"].get("reference_plane_z", 0.0))
        floor = np.abs(pts[:, 2] - zp) <= FLOOR_MM if scan.extra["truth"].get("reference_plane", True) else None
        return point_distances(mesh, pts), floor
    return point_distances(load_truth_mesh(args.truth), pts), None


def run(args) -> int:
    if args.conditioning and args.residuals:
        raise UsageError("give --conditioning or --residuals, not both")
    if args.conditioning:
        if args.files:
            raise UsageError(f"give either FILEs ({args.files[0]}) or --conditioning, not both")
        return run_conditioning(args)
    if args.residuals:
        if args.files:
            raise UsageError(f"give either FILEs ({args.files[0]}) or --residuals, not both")
        return run_residuals(args)
    if not args.files:
        raise UsageError("give FILEs to render, --conditioning SCAN_OR_RIG or --residuals VIEW_PLY")
    out = check_output_file(args.out, extensions=(".png",), what="picture (--out)")
    field = args.color_by or ("error" if args.truth else "none")
    if field == "error" and not args.truth:
        raise UsageError("--color-by error needs --truth MESH_OR_SCAN")
    orbit_asked = args.azimuth is not None or args.elevation is not None
    if args.camera == "own" and orbit_asked:
        raise UsageError("--azimuth/--elevation frame the orbit camera, not --camera own")
    geoms = [read_geometry(f) for f in args.files]
    cam = None
    if args.camera == "own" or (args.camera == "auto" and not orbit_asked and len(args.files) == 1):
        cam = own_camera(args.files[0])
        if cam is None and args.camera == "own":
            raise UsageError(f"--camera own: {args.files[0]} is not a view's PLY with a report.json beside it")
        if cam is not None and hasattr(geoms[0], "triangles"):
            cam = None
    d = ViewSettings()
    height = args.height or (round(args.width * cam.height / cam.width) if cam is not None else d.height)
    s = ViewSettings(width=args.width, height=height,
                     azimuth_deg=d.azimuth_deg if args.azimuth is None else args.azimuth,
                     elevation_deg=d.elevation_deg if args.elevation is None else args.elevation,
                     point_size=args.point_size, renderer=args.renderer)
    camera = cam.scaled(s.width, s.height) if cam is not None else view_camera(geoms, settings=s)
    eye = -camera[1][:3, :3].T @ camera[1][:3, 3]
    for g in geoms:
        if not hasattr(g, "triangles"):
            shade_cloud(g, towards=eye)  # normals face the camera: lit where it looks
    bar = None
    if field == "error":
        bar = _colour_by_error(args, geoms, cam)
    elif field != "none":
        bar = _colour_by_field(args, geoms, field)
    with progress_step(f"rendering {out.name}", enabled=not args.no_progress):
        res = render_to_png(geoms, out, settings=s, camera=camera, colorbar_spec=bar,
                            scale_bar=not args.no_scale_bar, length_unit=length_unit(args.files[0]),
                            empty_label=NOT_DECODED if cam is not None else None)
    w, h = res.png_size
    seen = f", seen from {cam.view}'s camera" if cam is not None else ""
    sb = f", scale bar {res.scale_bar_label}" if res.scale_bar_mm else ""
    print(f"wrote {args.out} ({w}x{h}, {res.renderer} renderer{seen}{sb})")
    return 0


def _colour_by_error(args, geoms: list, cam) -> dict:
    """Colour the first geometry by its distance to ``--truth`` and print the distances' figures
    (the object's and the reference plane's apart where the truth has a floor); returns the colour bar."""
    g = geoms[0]
    dist, floor = _truth_distances(args, g, cam)
    obj = dist if floor is None else dist[~floor]
    vmax = args.max_error if args.max_error else max(float(np.quantile(obj if len(obj) else dist, 0.99)), 1e-6)
    geoms[0] = colorize(g, dist, vmin=0.0, vmax=vmax, cmap=args.cmap)
    unit, k = readable_unit(vmax, "mm")  # 0..0.004 mm reads 0..4 um
    bar = {"vmin": 0.0, "vmax": vmax * k, "cmap": args.cmap, "label": f"dist ({unit})"}
    if floor is None:
        print(f"distance to truth: mean {dist.mean():.4f} mm, median {np.median(dist):.4f} mm, "
              f"p95 {np.quantile(dist, 0.95):.4f} mm")
    else:
        stats = (f"mean {obj.mean():.4f} mm, median {np.median(obj):.4f} mm, p95 {np.quantile(obj, 0.95):.4f} mm"
                 if len(obj) else "no point")
        fl = dist[floor]
        print(f"distance to truth, object ({len(obj)} points): {stats}; floor ({int(floor.sum())} points within "
              f"{FLOOR_MM} mm of the reference plane): " + (f"mean {fl.mean():.4f} mm" if len(fl) else "none"))
    return bar


def _colour_by_field(args, geoms: list, field: str) -> dict:
    """Colour the first geometry by one of its per-point fields: one colour per value with a legend where
    there are few (views, rings), else a colour map; returns the colour bar."""
    g = geoms[0]
    vals = cloud_field(args.files[0], field, g) if not hasattr(g, "triangles") else None
    if vals is None:
        if field != "height":
            raise UsageError(f"--color-by {field}: {args.files[0]} is a mesh; a mesh has only height")
        vals = np.asarray(g.vertices)[:, 2].astype(np.float64)
    fin = vals[np.isfinite(vals)]
    kinds = np.unique(fin) if field in CATEGORICAL else np.zeros(MAX_CATEGORIES + 1)
    if len(kinds) <= MAX_CATEGORIES:  # one colour a view (or ring), named in a legend
        rgb, ok = category_colours(len(kinds)), np.isfinite(vals)
        colours = np.full((len(vals), 3), 0.5)  # no value: grey
        if len(kinds):
            colours[ok] = rgb[np.searchsorted(kinds, vals[ok])]
        geoms[0] = painted(g, colours)
        bar = {"label": field, "categories": [(f"{field} {v:g}", c) for v, c in zip(kinds, rgb)]}
    else:
        unit = length_unit(args.files[0])
        lo, hi = (float(np.quantile(fin, 0.01)), float(np.quantile(fin, 0.99))) if len(fin) else (0.0, 1.0)
        lo, hi = FIXED_RANGE.get(field, (lo, hi))
        geoms[0] = colorize(g, vals, vmin=lo, vmax=hi, cmap=args.cmap)
        bar = {"vmin": lo, "vmax": max(hi, lo + 1e-9), "cmap": args.cmap,
               "label": {"height": f"z ({unit})", "rho": "rho (px)"}.get(field, field)}
    return bar


def painted(geom, rgb: np.ndarray):
    """A copy of a cloud (or mesh) with these (N, 3) colours, 0..1."""
    import open3d as o3d

    colours = o3d.utility.Vector3dVector(np.ascontiguousarray(rgb, dtype=np.float64))
    if hasattr(geom, "triangles"):
        out = o3d.geometry.TriangleMesh(geom)
        out.vertex_colors = colours
    else:
        out = o3d.geometry.PointCloud(geom)
        out.colors = colours
    return out
