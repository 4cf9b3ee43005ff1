"""Run the command blocks of README.md and docs/*.md as written, so they cannot rot.

    python benchmarks/run_doc_blocks.py                # every block that can run here (~60 min on 2 loaded cores)
    python benchmarks/run_doc_blocks.py --pip          # also README's install block (a fresh venv: needs PyPI)
    python benchmarks/run_doc_blocks.py --only suite   # only those the test suite runs too
    python benchmarks/run_doc_blocks.py --keep DIR     # keep the scratch folders in DIR
    python benchmarks/run_doc_blocks.py --match TEXT   # only the blocks holding TEXT

Every fenced ``sh``/``bash``/``python`` block of README.md and docs/*.md (:data:`DOCS`) is listed
in :data:`BLOCKS` with where it runs:

- ``suite``: cheap enough for the test suite (``tests/tools/test_doc_blocks.py`` and
  ``tests/tools/test_docs_commands.py`` run it as written; the test named in the entry);
- ``script``: runs here, as written, but too slow for the suite (tens of seconds to minutes
  on a 2-core machine) or it needs the package index; this script runs it;
- ``no``: cannot run without hardware or your own photos, or is not a program (an excerpt of the
  source); the reason says which, and names the block or test that does the same instead.

A usage synopsis (``ringscan fuse RECON --out OUT [--watertight]``: placeholders in capitals,
``[options]``, ``a|b``) is not a command block: it stands in an untagged fence.

A block that is in no list, or a list entry whose block is gone or changed,
fails ``tests/tools/test_doc_blocks.py``: a new block must be classified.

A shell block runs in ``bash -e -o pipefail`` with this Python's ``bin`` folder first on
``PATH`` (so ``ringscan``, ``python`` and ``pip`` are this environment's), in a scratch
folder ``work/`` whose sibling ``shared`` is the repository's ``../shared`` (the docs name
``../shared/data/...``); ``--device`` is not added (CUDA when present, as a user gets).
A python block runs with this Python in the same folder. Inputs a block expects from
an earlier step are made by the entry's ``setup`` (named in the entry), never faked:
e.g. README's Python snippet runs on a tiny simulated scan in the demo's layout, docs/api.md's
on the demo itself (``ringscan demo --out out/demo``: the shipped Spot mesh). Blocks of one
page with the same ``share`` run in one scratch folder, in page order: a later block reads
what an earlier one wrote, as a reader following the page has it.
Output: one line per block: ran (seconds) / FAILED (the last lines of its output) /
not run (why).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", *(f"docs/{p.name}" for p in sorted((ROOT / "docs").glob("*.md"))))
"""The pages whose blocks are listed here: README.md and every page of docs/."""
LANGS = ("sh", "bash", "python")
"""Fence languages of command blocks (an untagged block is output or a file, not commands)."""


@dataclass(frozen=True)
class Block:
    doc: str
    """The file (relative to the repository)."""
    match: str
    """Text found in this block alone (its identity; a changed block must still contain it)."""
    where: str
    """``suite``, ``script`` or ``no`` (module docstring)."""
    reason: str = ""
    """Why not in the suite (``script``) or not at all (``no``); for ``suite``: the test that runs it."""
    setup: str = ""
    """Name of the function below that makes the block's inputs in the scratch folder."""
    drop_lines: dict = field(default_factory=dict)
    """Lines left out when run (a substring of the line -> why): lines that need hardware."""
    cwd: str = "work"
    """``work`` (the scratch folder), ``copy`` (a copy of the source tree: the install block) or ``repo``
    (the repository itself: the make block)."""
    quotes: tuple = ()
    """Figures the doc quotes from this block's output: templates with ``{}`` where a number stands
    (``tests/support/printed.py``); each printed figure must agree with the doc's within ``quote_rtol``
    of its value plus half a unit of the doc's last decimal."""
    quote_rtol: float = 0.0
    """How far a quoted figure may move from machine to machine, relative (the reason in the entry)."""
    share: str = ""
    """Blocks of one page with the same ``share`` run in one scratch folder, in page order (module docstring)."""


BLOCKS = [
    # README.md
    Block("README.md", "make demo    #", "script",
          "`make demo` is the main job at full size (~90 s; it writes out/demo/) and `make test` is the test "
          "suite itself (CI's own command, .ci/run): neither can run inside the suite. This script runs the "
          "block in the repository, as README says, `make test` only with --make-test", cwd="repo"),
    Block("README.md", "pip install .                 #", "script",
          "installs ringscan and its dependencies from the package index into a fresh virtual environment "
          "(network, minutes); run with --pip", cwd="copy"),
    Block("README.md", "report = reconstruct_scan(\"out/demo/scan\"", "suite",
          "tests/tools/test_doc_blocks.py::test_readme_python_block_runs_as_written", setup="demo_scan"),
    # docs/batch.md
    Block("docs/batch.md", "--backend ray --address ray-head:6379", "no",
          "needs a Ray cluster (its head at ray-head:6379); tests/pipeline/batch/test_ray_backend.py runs the same "
          "batch on a local Ray cluster (the same bytes as the local workers, a killed worker, a killed batch)"),
    Block("docs/batch.md", "ringscan batch s3://scans/2026-12 --out s3://results/2026-12", "no",
          "needs an S3 bucket and its credentials; tests/pipeline/batch/test_object_storage.py runs the same "
          "batch and reconstruct commands against a local S3 server (moto)"),
    # docs/calibration.md
    Block("docs/calibration.md", "--board 9x7 --square 30 --charuco DICT_5X5_100", "no",
          "needs your photos of a ChArUco board through a wide-angle lens (shots/: the shared captures show a plain "
          "chessboard); tests/pipeline/calibrate/test_camera.py fits the rational and thin-prism models to "
          "rendered views of a known lens"),
    Block("docs/calibration.md", "ringscan calibrate camera shots/*.png --board 9x7 --square 75", "script",
          "~25 s (board detection in three 1280x1024 photos, twice); `shots/` are your photos: here the white "
          "frames of the shared procam captures, the same board", setup="shots_and_rig"),
    Block("docs/calibration.md", "ringscan calibrate procam ../shared/data/procam/capture_{1,2,3}", "script",
          "~30 s (the real captures' board corners and Gray code); the same fit with the same inputs is checked "
          "in tests/tools/test_cmd_calibrate.py (test_procam_a_repeated_capture_is_left_out) and "
          "tests/pipeline/calibrate/test_procam_real.py", setup="shared"),
    Block("docs/calibration.md", "ringscan import ../shared/data/procam/capture_{1,2,3}", "script",
          "~50 s (decoding three real captures of 42 frames, reconstructing 2.7 million points)",
          setup="shared_procam_rig"),
    Block("docs/calibration.md", "--levels 0 32 64 96 128 160 192 224 255 --rig rig.json", "no",
          "needs your projector's grey ramp photographed (ramp/*.png) and your rig; the block after the next "
          "does the same on the virtual rig's ramp and runs in the suite"),
    Block("docs/calibration.md", "--levels 0 32 64 96 128 160 192 224 255 --rig ramp_rig.json", "suite",
          "tests/tools/test_docs_commands.py::test_calibration_md_grey_ramp_runs_as_written (after the python "
          "block that makes ramp/ and ramp_rig.json)", setup="ramp"),
    Block("docs/calibration.md", "vr = VirtualRig(rig, \"plane\")", "suite",
          "tests/tools/test_docs_commands.py::test_calibration_md_grey_ramp_runs_as_written"),
    Block("docs/calibration.md", "ringscan patterns --codec phase-rings --rig rig.json --out pat", "suite",
          "tests/tools/test_doc_blocks.py::test_calibration_precompensated_patterns_block_runs_as_written",
          setup="default_rig",
          drop_lines={"ringscan capture ": "needs a camera, a projector and a turntable (the `...` are their "
                                           "ports: docs/hardware.md)"}),
    Block("docs/calibration.md", "ringscan calibrate pose board_on_plane.png", "no",
          "needs your rig: photos of a board (shots/, board_on_plane.png) and captures of the bare plane and a "
          "plate (cal/z0, cal/z40); the next block does the same on the virtual rig and runs in the suite"),
    Block("docs/calibration.md", "ringscan simulate --scene plate:40 --out cal/z40", "script",
          "~20 s (two full-size 1280x1024 scans and the light's fit); the suite covers the command on small "
          "scans (tests/tools/test_cmd_calibrate_light.py, tests/pipeline/calibrate/test_light.py). The fit the "
          "page quotes is checked here: the virtual rig's float32 renders may move its last digits on another "
          "CPU (1e-3 of a value at most)",
          quotes=("parallel light: pitch {} mm/px, axis pixel ({}, {}), tilt {} deg from z, roll {} deg; "
                  "ring RMS {} px",), quote_rtol=1e-3),
    Block("docs/calibration.md", "ringscan calibrate turntable scans/board", "no",
          "needs your rig: a scan folder or photos of a board on the table (scans/board, tt/*.png); the next "
          "block does the same on the virtual rig"),
    Block("docs/calibration.md", "ringscan import data/images_list.yml --rig data/calibrationParameters.yml", "no",
          "needs your captures from OpenCV's structured-light sample (data/: not in ../shared); the same commands "
          "run on virtual captures in OpenCV's layout in tests/pipeline/calibrate/test_import_opencv_sample.py "
          "and benchmarks/opencv_sample_virtual.py"),
    Block("docs/calibration.md", "ringscan calibrate stereo --cam1 left/*.png --cam2 right/*.png", "no",
          "needs your two cameras' photos of a board (left/, right/); the same command runs on rendered ChArUco "
          "pairs of a known rig in tests/tools/test_cmd_calibrate_stereo_boards.py"),
    Block("docs/calibration.md", "ringscan calibrate refine scan --out rig_refined.json", "script",
          "minutes (a two-camera scan rendered at full size, both cameras decoded and matched); `scan` is your "
          "two-camera scan: here the virtual rig's (`ringscan simulate --camera2 --light perspective`)",
          setup="stereo_scan"),
    Block("docs/calibration.md", "ringscan calibrate projector-from-scan scan --rig rig_refined.json", "script",
          "as the block before (it refines the rig first, as the page does)", setup="stereo_scan_refined"),
    Block("docs/calibration.md", "ringscan simulate --scene chessboard --views 8", "script",
          "~60 s (eight 1280x1024 views rendered, then the axis fit)"),
    # docs/accuracy.md
    Block("docs/accuracy.md", "--light perspective --out scans/spot_cone", "script",
          "a full-size scan of Spot (38 frames of 1280x1024) rendered, reconstructed and evaluated: ~40 s"),
    # docs/api.md: on the demo's own scan (the shipped Spot mesh), as the page says
    Block("docs/api.md", 'scan = ringscan.load_scan("out/demo/scan")\nprint(scan.patterns.codec', "script",
          "needs the demo's scan (`ringscan demo --out out/demo`, ~2 min: the setup runs it once for the page)",
          setup="demo", share="api"),
    Block("docs/api.md", 'ringscan.simulate("out/api/cube"', "script",
          "two full-size views of a cube rendered (~20 s)", share="api"),
    Block("docs/api.md", 'views=["view_000", "view_001"]', "script",
          "two views of the demo's scan reconstructed (~30 s)", setup="demo", share="api"),
    Block("docs/api.md", 'triangulate={"constraint": "rings"}', "script",
          "a view of the demo's scan reconstructed (~15 s)", setup="demo", share="api"),
    Block("docs/api.md", "fused, report = ringscan.fuse(views", "script",
          "the demo's six views reconstructed and fused (~1 min)", setup="demo", share="api"),
    Block("docs/api.md", "mesh = ringscan.mesh(fused, poisson_depth=8)", "script",
          "the demo's scan reconstructed, fused and meshed twice (~1.5 min)", setup="demo", share="api"),
    Block("docs/api.md", "figures = ringscan.evaluate(views, scan)", "script",
          "the demo's scan reconstructed, fused, meshed and evaluated (~1.5 min)", setup="demo", share="api"),
    # docs/architecture.md
    Block("docs/architecture.md", "class DecodedLayout(PatternLayout):", "no",
          "not a program: an excerpt of three source files (formats/patterns.py, codecs/decoded.py, "
          "codecs/registry.py) showing where a codec's parts live; the suite imports and runs the real ones "
          "(tests/pipeline/codecs)"),
    # docs/demo.md
    Block("docs/demo.md", ".venv/bin/ringscan demo --out out/demo", "script",
          "the demo at full size (~2 min), run in the repository's environment as the page says", cwd="repo"),
    Block("docs/demo.md", 'mesh = o3d.io.read_triangle_mesh("out/demo/model/mesh.ply")', "script",
          "needs the demo's output (`ringscan demo --out out/demo`, ~2 min)", setup="demo",
          drop_lines={"draw_geometries": "opens a window: needs a display"}),
    # docs/dense.md
    Block("docs/dense.md", "--pitch 8 --bits 6 --sector-bits 6 --out scans/spot_phase", "script",
          "a full-size phase-rings scan of Spot, a sweep of ring counts (a scan each) and the dense benchmark: "
          "minutes"),
    Block("docs/dense.md", "--angle-steps 4 --sector-bits 9 --out scans/spot_angle", "script",
          "a full-size scan of Spot reconstructed twice and its conditioning map: ~1.5 min"),
    # docs/fusion.md: on the demo's output (out/demo), as the page says
    Block("docs/fusion.md", "ringscan view out/demo/recon/view_000.ply --out v0.png", "script",
          "needs the demo's output (`ringscan demo --out out/demo`, ~2 min: the setup runs it once for the page)",
          setup="demo", share="fusion"),
    Block("docs/fusion.md", "fuse_and_mesh(\"out/demo/recon\"", "script",
          "the demo's six views fused and meshed (~1 min)", setup="demo", share="fusion"),
    Block("docs/fusion.md", "palette = np.array(", "script",
          "the demo's six views fused and rendered (~1 min)", setup="demo", share="fusion"),
    Block("docs/fusion.md", "scene = o3d.t.geometry.RaycastingScene()", "script",
          "the demo's six views fused, meshed and compared with the truth (~1 min)", setup="demo", share="fusion"),
    Block("docs/fusion.md", "ringscan simulate --scene spot --views 8 --pose $p", "script",
          "four poses of eight full-size views each rendered, reconstructed and fused: ~10 min"),
    Block("docs/fusion.md", "ringscan fuse $W/recon_0", "no",
          "needs the work folder of benchmarks/multipose_accuracy.py (`W`: its --keep folder, ~15 min); the block "
          "above does the same from scratch"),
    # docs/hardware.md
    Block("docs/hardware.md", "--views 8 --out scan --virtual sphere", "script",
          "eight full-size views captured from the emulated turntable and projector (the real drivers, "
          "rendered grabs): ~2 min", setup="rig_and_patterns"),
    Block("docs/hardware.md", "ringscan calibrate latency --projector display:1", "no",
          "needs a projector on a second display, a camera and a turntable on /dev/ttyUSB0; the block above "
          "runs the same capture on emulated devices"),
    Block("docs/hardware.md", "SerialProjector(\"/dev/ttyACM0\"", "no",
          "needs the real turntable, projector and camera on their ports; tests/hardware runs capture_scan on "
          "the emulated ones"),
    Block("docs/hardware.md", 'tt.inject("error", on="G1", code=33)', "suite",
          "tests/tools/test_doc_blocks.py::test_hardware_fault_injection_block_runs_as_written"),
    # docs/measurements.md (generated by benchmarks/measurements.py; its output fences are untagged)
    Block("docs/measurements.md", "python benchmarks/measurements.py --check", "suite",
          "tests/benchmarks/test_measurements.py::test_the_pages_check_block_runs_as_written", cwd="repo"),
    # docs/reconstruction.md
    Block("docs/reconstruction.md", "ringscan simulate --camera2 --scene sphere --out scans/sphere2", "script",
          "a two-camera full-size scan rendered and matched: ~1 min"),
    # docs/single_shot.md
    Block("docs/single_shot.md", "ringscan simulate --scene sphere --codec rings --out scan9", "script",
          "a full-size one-frame scan rendered, reconstructed and evaluated: ~20 s (Warp and Open3D start-up)"),
    Block("docs/single_shot.md", "--count 30 --pitch 12 --out sphere_30", "script",
          "three full-size one-frame scans rendered, one reconstructed: ~30 s"),
    # docs/virtual_rig.md
    Block("docs/virtual_rig.md", "ringscan simulate --scene sphere --out scans/sphere", "script",
          "two full-size scans rendered (one of four views), one reconstructed: ~2 min. The `all` line the page "
          "quotes (points, median mm) is checked here: the float32 renders and the root choice may move the "
          "count and the median's last digit on another CPU (5 % of each)",
          quotes=("all {} {}",), quote_rtol=0.05),
    Block("docs/virtual_rig.md", 'simulate_scan("scans/cube", scene="cube"', "script",
          "four full-size views of a cube rendered: ~40 s"),
    Block("docs/virtual_rig.md", "--rig ../shared/data/rigs/oblique_projector.json", "script",
          "a 1920x1080 scan of a bust in front of a wall: ~1 min; the rig and the bust are real data in "
          "../shared (not shipped: the page says where they come from)", setup="shared", share="oblique"),
    Block("docs/virtual_rig.md", "ringscan import scans/oblique/capture_0", "script",
          "the block above's captures decoded and reconstructed: ~1 min", setup="shared", share="oblique"),
    Block("docs/virtual_rig.md", "--renderer mitsuba --out scans/sphere_mi", "script",
          "a full-size Mitsuba scan: ~2 min",
          drop_lines={"pip install": "installs into this environment (README's install block covers installing; "
                                     "the test extra holds mitsuba already)"}),
    Block("docs/virtual_rig.md", "from ringscan.pipeline.simulate.mitsuba_render import MitsubaRig", "script",
          "a full-size Mitsuba scan of a cube and two frames: ~2 min"),
]


# ----------------------------------------------------------------------------- blocks of a file


def command_blocks(path: Path) -> list[tuple[int, str, str]]:
    """The fenced command blocks of a Markdown file: (first line number, language, text)."""
    out, lang, start, lines = [], None, 0, []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if s.startswith("```"):
            if lang is None:
                lang, start, lines = s[3:].strip() or "-", n + 1, []
            else:
                if lang in LANGS:
                    out.append((start, lang, "\n".join(lines) + "\n"))
                lang = None
        elif lang is not None:
            lines.append(line)
    return out


def untagged_commands(path: Path) -> list[int]:
    """Line numbers of ``ringscan``/``make``/``pip`` command lines inside untagged or other blocks
    (a command block without ``sh``: it would escape the list)."""
    bad, lang = [], None
    for n, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if s.startswith("```"):
            lang = (s[3:].strip() or "-") if lang is None else None
        elif (lang is not None and lang not in LANGS and re.match(r"(\$ )?(ringscan|make|pip) ", s)
              and not is_synopsis(s)):
            bad.append(n)
    return bad


def is_synopsis(line: str) -> bool:
    """A usage line, not a command: ``[options]``, ``a|b``, ``...`` or a placeholder in capitals
    (``ROOT``, ``SCAN_OR_ROOT``, ``P.json``) before its comment."""
    cmd = line.split(" #")[0]
    return (any(c in cmd for c in ("[", "|", "...")) or re.search(r"(?:^|[\s=/])[A-Z][A-Z0-9_]*(?:\.\w+)?(?=[\s/]|$)", cmd) is not None)


def classify() -> list[tuple[Block, int, str, str]]:
    """Every command block of :data:`DOCS` with its entry: (entry, line, language, text).

    Raises:
        ValueError: a block with no entry or several, an entry that matches no block.
    """
    out, used = [], set()
    for doc in DOCS:
        for line, lang, text in command_blocks(ROOT / doc):
            hits = [b for b in BLOCKS if b.doc == doc and b.match in text]
            if len(hits) != 1:
                raise ValueError(f"{doc}:{line}: a {lang} block with {len(hits)} entries in "
                                 f"benchmarks/run_doc_blocks.py BLOCKS (want 1): {text.strip()[:80]!r}")
            out.append((hits[0], line, lang, text))
            used.add(id(hits[0]))
        bad = untagged_commands(ROOT / doc)
        if bad:
            raise ValueError(f"{doc}:{bad[0]}: a command line in a block without the sh language tag")
    twice = [(b, line) for b, line, _, _ in out if sum(b is c for c, *_ in out) > 1]
    if twice:
        raise ValueError(f"{twice[0][0].doc}:{twice[0][1]}: the entry {twice[0][0].match!r} matches more than one "
                         "block (make its match text longer)")
    gone = [b for b in BLOCKS if id(b) not in used]
    if gone:
        raise ValueError(f"{gone[0].doc}: no block contains {gone[0].match!r} any more")
    return out


# ----------------------------------------------------------------------------- inputs (setup)


def _shared(work: Path) -> None:
    """``work/../shared`` -> the repository's ``../shared`` (the docs name ``../shared/data/...``)."""
    link = work.parent / "shared"
    if not link.exists():
        link.symlink_to((ROOT.parent / "shared").resolve(), target_is_directory=True)


def setup_shared(work: Path) -> None:
    _shared(work)


def setup_shared_procam_rig(work: Path) -> None:
    """The shared captures and the rig that the block before (§3) writes."""
    _shared(work)
    run_bash("ringscan calibrate procam ../shared/data/procam/capture_{1,2,3} --board 9x7 --square 75 "
             "--projector 1024x768 --layout opencv-graycode --out rig.json", work, check=True)


def setup_shots_and_rig(work: Path) -> None:
    """``shots/``: the shared captures' white frames (photos of the 9x7 board); ``rig.json`` for the
    second line (a rig whose camera it updates: the default rig's, 1280x1024 as these photos)."""
    _shared(work)
    (work / "shots").mkdir(exist_ok=True)
    for i in (1, 2, 3):
        shutil.copyfile(work.parent / "shared" / "data" / "procam" / f"capture_{i}" / "graycode_40.png",
                        work / "shots" / f"capture_{i}.png")
    setup_default_rig(work)


def setup_ramp(work: Path) -> None:
    """``ramp/*.png`` and ``ramp_rig.json``: the section's own Python block (the virtual rig's grey ramp), as written."""
    (text,) = [t for b, _, _, t in classify() if b.match == 'vr = VirtualRig(rig, "plane")']
    subprocess.run([sys.executable, "-c", text], cwd=work, env=_env(), check=True, capture_output=True)


def setup_default_rig(work: Path) -> None:
    from ringscan.pipeline.formats.rig import default_rig, save_rig

    save_rig(work / "rig.json", default_rig())


def setup_stereo_scan(work: Path) -> None:
    """``scan``: a two-camera scan of the virtual rig with a perspective projector (docs/virtual_rig.md)."""
    run_bash("ringscan simulate --camera2 --light perspective --out scan --no-progress", work, env=_env(),
             check=True)


def setup_stereo_scan_refined(work: Path) -> None:
    setup_stereo_scan(work)
    run_bash("ringscan calibrate refine scan --out rig_refined.json", work, env=_env(), check=True)


def setup_demo(work: Path) -> None:
    """``out/demo``: the demo itself (``ringscan demo --out out/demo``: the shipped Spot mesh on the virtual
    turntable, reconstructed, fused and meshed), once for the blocks that share the folder."""
    if (work / "out" / "demo" / "model").is_dir():
        return
    made = work.parent.parent / "demo_output"  # one demo for the run: the pages' folders get a copy
    if not (made / "out" / "demo" / "model").is_dir():
        made.mkdir(parents=True, exist_ok=True)
        run_bash("ringscan demo --out out/demo", made, check=True)
    shutil.copytree(made / "out", work / "out", dirs_exist_ok=True)


def setup_rig_and_patterns(work: Path) -> None:
    """``rig.json`` (the default rig) and ``patterns.json`` (the default patterns): what a reader has after
    docs/hardware.md's set-up (`ringscan patterns`)."""
    setup_default_rig(work)
    run_bash("ringscan patterns --out pats && cp pats/patterns.json patterns.json", work, check=True)


def setup_demo_scan(work: Path) -> None:
    """``out/demo/scan`` as `ringscan demo` lays it out (a scan folder with ``view_000``), at the size of
    the tests' tiny scan (160x128 camera, one view): the snippet's own steps run on it unchanged."""
    sys.path.insert(0, str(ROOT))
    from tests.support.tiny_scan import simulate_tiny_scan

    simulate_tiny_scan(work / "out" / "demo" / "scan")


# ----------------------------------------------------------------------------- running


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def run_bash(text: str, cwd: Path, *, env: dict | None = None, check: bool = False, timeout: float = 3600):
    return subprocess.run(["bash", "-e", "-o", "pipefail", "-c", text], cwd=cwd, env=env or _env(),
                          capture_output=True, text=True, check=check, timeout=timeout)


def runnable_text(block: Block, text: str) -> str:
    """The block without its dropped lines (and their continuations)."""
    joined = re.sub(r"\\\n", "", text).splitlines()
    return "\n".join(ln for ln in joined if not any(k in ln for k in block.drop_lines)) + "\n"


def run_block(block: Block, lang: str, text: str, work: Path, *, env: dict | None = None,
              timeout: float = 3600) -> subprocess.CompletedProcess:
    """Run one block as written in ``work`` (made first by its setup)."""
    work.mkdir(parents=True, exist_ok=True)
    if block.setup:
        globals()[f"setup_{block.setup}"](work)
    text = runnable_text(block, text)
    if lang == "python":
        return subprocess.run([sys.executable, "-c", text], cwd=work, env=env or _env(), capture_output=True,
                              text=True, timeout=timeout)
    return run_bash(text, work, env=env, timeout=timeout)


def check_quotes(block: Block, output: str) -> None:
    """The figures the doc quotes from this block are the ones it printed (AssertionError naming one that
    is not)."""
    sys.path.insert(0, str(ROOT))
    from tests.support.printed import assert_figures_as_quoted

    doc = (ROOT / block.doc).read_text()  # a quote may wrap: the templates match any run of whitespace
    for template in block.quotes:
        assert_figures_as_quoted(output, doc, template, rtol=block.quote_rtol, why=block.reason)


def _source_copy(dest: Path) -> Path:
    """The tracked files of the repository (what a user gets in a release archive)."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    for rel in filter(None, files.decode().split("\0")):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=("suite", "script", "all"), default="all", help="which blocks to run")
    ap.add_argument("--pip", action="store_true", help="also run README's install block (a fresh venv; PyPI)")
    ap.add_argument("--make-test", action="store_true", help="let README's make block run `make test` too")
    ap.add_argument("--keep", metavar="DIR", help="make the scratch folders in DIR and keep them")
    ap.add_argument("--match", metavar="TEXT", help="only the blocks whose text holds TEXT")
    args = ap.parse_args(argv)
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="doc_blocks_"))
    failed = 0
    try:
        for i, (block, line, lang, text) in enumerate(classify()):
            name = f"{block.doc}:{line}"
            if args.match and args.match not in text:
                continue
            if block.where == "no" or (args.only != "all" and block.where != args.only):
                print(f"{name}: not run ({block.where}: {block.reason})")
                continue
            env = None
            work = base / (f"share_{Path(block.doc).stem}_{block.share}" if block.share else f"block_{i:02d}") / "work"
            if block.cwd == "copy":  # the install block: a fresh venv, a copy of the tree (pip wheel writes dist/)
                if not args.pip:
                    print(f"{name}: not run (needs --pip: {block.reason})")
                    continue
                work = _source_copy(base / f"block_{i:02d}" / "src")
                venv = base / f"block_{i:02d}" / "venv"
                subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
                env = dict(os.environ, PATH=f"{venv / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}",
                           VIRTUAL_ENV=str(venv))
            elif block.cwd == "repo":
                work = ROOT
                if not args.make_test and any(ln.startswith("make test") for ln in text.splitlines()):
                    print(f"{name}: `make test` left out (the suite itself; --make-test runs it)")
                    text = "\n".join(ln for ln in text.splitlines() if not ln.startswith("make test")) + "\n"
            for key, why in block.drop_lines.items():
                print(f"{name}: a line with {key.strip()!r} left out: {why}")
            t = time.perf_counter()
            r = run_block(block, lang, text, work, env=env)
            dt = time.perf_counter() - t
            if r.returncode == 0 and block.quotes:
                try:
                    check_quotes(block, r.stdout)
                except AssertionError as e:
                    r = subprocess.CompletedProcess(r.args, 1, r.stdout, f"{r.stderr}\nthe doc's figures: {e}")
            if r.returncode == 0:
                print(f"{name}: ran in {dt:.1f} s ({block.where})")
            else:
                failed += 1
                tail = "\n    ".join((r.stdout + r.stderr).strip().splitlines()[-8:])
                print(f"{name}: FAILED (exit {r.returncode}, {dt:.1f} s)\n    {tail}")
    finally:
        if not args.keep:
            shutil.rmtree(base, ignore_errors=True)
    print(f"{failed} block(s) failed" if failed else "every block that can run here ran")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
