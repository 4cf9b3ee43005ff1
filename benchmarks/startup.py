"""Start-up of a single ``ringscan reconstruct`` process of one view, in one run.

Runs, in turn, ``--rounds`` times each:

- ``every command``: the process as it was before the command line imported only the
  module of the command it runs (every sub-command's module imported to build the
  parser: SciPy's optimisers, pygame, the calibration code ...);
- ``last collection``: the process as it was before it ended without the garbage
  collector's last pass over every object (``kernels.process.skip_final_collection``
  made a no-op);
- ``reconstruct``: ``python -m ringscan.tools.cli reconstruct SCAN --out DIR`` as it is;

and prints the median wall time of each, the ratio, and the part of the process
before reconstruction starts (the wall time less the report's own seconds).

Usage::

    python benchmarks/startup.py SCAN [--rounds 5]

SCAN: a one-view scan folder (e.g. ``ringscan simulate --out SCAN``; full size is the
case the issue measured).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

EVERY = ("import sys, ringscan.tools.cli as c; c.build_parser(); "  # as before: every command's module
         "sys.exit(c.main(sys.argv[1:]))")
ONE = "import sys, ringscan.tools.cli as c; sys.exit(c.main(sys.argv[1:]))"
COLLECT = ("import sys, ringscan.kernels.process as r, ringscan.tools.cli as c; "  # as before: a last collection
           "r.skip_final_collection = lambda: None; sys.exit(c.main(sys.argv[1:]))")


def run(code: str, scan: str, out: Path) -> tuple[float, float]:
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, "reconstruct", scan, "--out", str(out), "--device", "cpu",
                    "--no-progress"], check=True, capture_output=True)
    wall = time.perf_counter() - t
    rep = json.loads((out / "report.json").read_text())
    return wall, float(rep["time_s"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scan")
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="ringscan_startup_"))
    try:
        run(ONE, a.scan, tmp / "warm")  # Warp's kernel cache filled, files in the page cache
        res = {"every command": [], "last collection": [], "reconstruct": []}
        for _ in range(a.rounds):
            for label, code in (("every command", EVERY), ("last collection", COLLECT), ("reconstruct", ONE)):
                res[label].append(run(code, a.scan, tmp / "out"))
        for label, r in res.items():
            wall = float(np.median([w for w, _ in r]))
            work = float(np.median([s for _, s in r]))
            print(f"{label:14s}: {wall:.2f} s a process (median of {a.rounds}); reconstruction's own time "
                  f"{work:.2f} s; start-up and exit {wall - work:.2f} s")
        for ref in ("every command", "last collection"):
            ratio = float(np.median([o[0] / e[0] for o, e in zip(res["reconstruct"], res[ref])]))
            print(f"reconstruct / {ref}: {ratio:.2f} (median of per-round ratios; {100 * (1 - ratio):.0f} % cut)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
