"""``ringscan sweep --scene S --out DIR``: error and coverage against the number of rings."""

from __future__ import annotations

from ringscan.pipeline.evaluate.sweep import SweepSettings, run_sweep
from ringscan.pipeline.formats.atomic import check_output_folder
from ringscan.pipeline.formats.rig import load_rig
from ringscan.pipeline.simulate.scenes import SCENES
from ringscan.pipeline.simulate.virtual_rig import RenderSettings
from ringscan.tools.cli import UsageError, add_device_option, basic_options


def _int_list(text: str) -> tuple[int, ...]:
    """'3:8' (inclusive range) or '3,5,7'."""
    try:
        if ":" in text:
            a, b = (int(x) for x in text.split(":"))
            if b < a:
                raise ValueError
            return tuple(range(a, b + 1))
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise UsageError(f"--bits: expected a range like 3:8 or a list like 3,5,7, got {text!r}") from None


def _float_list(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise UsageError(f"--targets: expected numbers like 0.5,0.1, got {text!r}") from None


def add_parser(sub):
    d = SweepSettings()
    r = RenderSettings()
    p = sub.add_parser("sweep", help="error and coverage against the number of rings (the minimum ring count)",
                       description="Simulate the scene on the virtual rig with gray-rings patterns of 2**bits - 1 "
                                   "rings over one annulus (and a dense phase-rings run), reconstruct each, "
                                   "interpolate the surface between the rings and write sweep.csv, sweep.json and "
                                   "sweep.png and sweep.svg (surface error and coverage against the number of rings, "
                                   "with the targets and the least coverage as dashed lines) into --out.")
    p.add_argument("--scene", default="sphere",
                   help=f"{'|'.join(SCENES)} or the path of an OBJ/PLY/STL mesh (default sphere)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--bits", default=f"{min(d.bits)}:{max(d.bits)}",
                   help="band bits per run: a range 3:8 or a list 3,5,7 (2**bits - 1 rings each; default 3:8)")
    p.add_argument("--rho0", type=float, default=d.rho0, help=f"inner radius, projector px (default {d.rho0:g})")
    p.add_argument("--radius", type=float, default=d.radius,
                   help=f"outer radius of the coded annulus, projector px (default {d.radius:g}); "
                        "pitch = (radius - rho0) / 2**bits")
    p.add_argument("--sector-bits", type=int, default=d.sector_bits, help=f"sector bits (default {d.sector_bits})")
    p.add_argument("--no-dense", action="store_true", help="leave out the dense phase-rings run")
    p.add_argument("--dense-pitch", type=float, default=d.dense_pitch,
                   help=f"fringe pitch of the dense run, projector px (default {d.dense_pitch:g})")
    p.add_argument("--targets", default=",".join(f"{t:g}" for t in d.targets_mm),
                   help="surface-error targets in mm for the minimum ring count (default 0.5,0.2,0.1,0.05)")
    p.add_argument("--min-coverage", type=float, default=d.min_coverage,
                   help=f"least coverage for a run to meet a target (default {d.min_coverage:g})")
    p.add_argument("--rig", default=None, help="rig file (default: the built-in virtual rig)")
    p.add_argument("--size-mm", type=float, default=80.0, help="longest side of the object in mm (default 80)")
    p.add_argument("--up", choices=("auto", "y", "z"), default="auto", help="up axis of a mesh file (default auto)")
    p.add_argument("--noise", type=float, default=r.noise, help=f"camera noise, grey levels (default {r.noise:g})")
    p.add_argument("--defocus", type=float, default=r.defocus_px,
                   help=f"projector blur sigma, px (default {r.defocus_px:g})")
    p.add_argument("--keep-scans", action="store_true", help="keep each run's scan under OUT/scans")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_device_option(p)
    basic_options(p, "--scene", "--bits", "--sector-bits", "--rig", "--size-mm")
    return p


def run(args) -> int:
    check_output_folder(args.out, what="sweep's output folder (--out)")
    settings = SweepSettings(bits=_int_list(args.bits), rho0=args.rho0, radius=args.radius,
                             sector_bits=args.sector_bits, dense=not args.no_dense, dense_pitch=args.dense_pitch,
                             targets_mm=_float_list(args.targets), min_coverage=args.min_coverage)
    render = RenderSettings(noise=args.noise, defocus_px=args.defocus)
    rig = load_rig(args.rig) if args.rig else None
    res = run_sweep(args.out, scene=args.scene, rig=rig, settings=settings, render=render, device=args.device,
                    keep_scans=args.keep_scans, progress=not args.no_progress, size_mm=args.size_mm, up=args.up)

    def f(x, fmt):
        return "-" if x is None else format(x, fmt)

    print(f"{'codec':<12}{'rings':>6}{'pitch':>7}{'on obj':>7}{'surf med':>10}{'surf p95':>10}{'cover':>7}"
          f"{'pt med':>9}{'pt >1mm':>8}")
    for r in res["runs"]:
        print(f"{r['codec']:<12}{f(r['rings'], 'd'):>6}{r['pitch']:>7.3g}{f(r['rings_on_object'], 'd'):>7}"
              f"{f(r['surface_median_mm'], '.4f'):>10}{f(r['surface_p95_mm'], '.4f'):>10}{r['coverage'] * 100:>6.1f}%"
              f"{f(r['point_median_mm'], '.4f'):>9}{f(r['point_frac_over_1mm'] and r['point_frac_over_1mm'] * 100, '.2f'):>7}%")
    for t, n in res["min_rings"].items():
        print(f"surface p95 <= {t} mm with coverage >= {settings.min_coverage:.0%}: "
              + (f"{n} rings" if n else "not reached in this sweep"))
    print(f"{args.out}/sweep.csv, sweep.json, sweep.png, sweep.svg ({res['time_s']:.0f} s)")
    return 0
