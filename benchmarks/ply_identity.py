"""Byte-identity of ringscan's outputs across a change that must not change behaviour (issue 36's
restructuring): every codec and constraint, one and two cameras, simulated on a small rig (the
default rig's geometry, a 480x384 camera) and reconstructed through the command line; prints the
SHA-256 of every PLY (and of the frames' and truth's files, so a changed renderer shows apart from a
changed reconstruction).

    python benchmarks/ply_identity.py --save before.json      # on the commit before the change
    python benchmarks/ply_identity.py --check before.json     # after: exit 1 when any file differs

About 2-3 minutes on two cores. Times and clocks are not hashed: report.json files carry them."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CASES = {
    # name: (the rig's light, simulate options, reconstruct options); simulate None: OpenCV's Gray
    # code captures decoded by `ringscan import`
    "gray-rings": ("parallel", ["--codec", "gray-rings"], []),
    "gray-rings-rings": ("parallel", ["--codec", "gray-rings"], ["--constraint", "rings"]),
    "gray-rings-angle": ("parallel", ["--codec", "gray-rings"], ["--constraint", "angle"]),
    "gray-rings-no-angle": ("parallel", ["--codec", "gray-rings", "--angle-steps", "0"], []),
    "phase-rings": ("parallel", ["--codec", "phase-rings"], []),
    "rings": ("parallel", ["--codec", "rings"], []),
    "gamma-1": ("parallel", ["--codec", "gray-rings", "--gamma", "1.0"], []),
    "perspective": ("perspective", ["--codec", "gray-rings"], []),
    "two-camera": ("parallel", ["--codec", "gray-rings", "--camera2"], []),
    "import": ("perspective", None, []),
}
HASHED = (".ply",)


def small_rig_file(path: Path, light_model: str) -> None:
    from ringscan.pipeline.formats.rig import save_rig
    from ringscan.pipeline.formats.rig import default_rig

    rig = default_rig(light_model=light_model)
    cam = rig.camera
    s = 480 / cam.width
    K = cam.K.copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 2], K[1, 2] = (480 - 1) / 2, (384 - 1) / 2
    save_rig(path, dataclasses.replace(rig, camera=dataclasses.replace(cam, width=480, height=384, K=K)))


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run(cmd: list[str]) -> None:
    res = subprocess.run([sys.executable, "-m", "ringscan.tools.cli", *cmd], capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"ply_identity: `ringscan {' '.join(cmd)}` failed: {res.stderr.strip()[-400:]}")


def fingerprints(work: Path) -> dict[str, str]:
    rigs = {m: work / f"rig_{m}.json" for m in ("parallel", "perspective")}
    for m, p in rigs.items():
        small_rig_file(p, m)
    out: dict[str, str] = {}
    for name, (light, sim, rec) in CASES.items():
        scan, recon = work / name / "scan", work / name / "recon"
        common = ["--rig", str(rigs[light]), "--scene", "sphere", "--no-progress", "--device", "cpu"]
        if sim is None:
            cap = work / name / "captures"
            run(["simulate", "--captures", "opencv-graycode", "--out", str(cap), *common])
            run(["import", str(cap / "capture_0"), "--rig", str(cap / "rig.json"), "--projector", "1024x768",
                 "--out", str(scan), "--no-progress"])
        else:
            run(["simulate", "--out", str(scan), "--views", "1", *common, *sim])
        run(["reconstruct", str(scan), "--out", str(recon), "--no-progress", "--device", "cpu", *rec])
        for root, tag in ((scan, "scan"), (recon, "recon")):
            for p in sorted(root.rglob("*")):
                if p.is_file() and (p.suffix in HASHED or (tag == "scan" and p.suffix in (".png", ".tiff"))):
                    out[f"{name}/{tag}/{p.relative_to(root).as_posix()}"] = sha(p)
        print(f"{name}: {sum(k.startswith(name + '/') for k in out)} files", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--save", type=Path, help="write the fingerprints to this JSON file")
    g.add_argument("--check", type=Path, help="compare against fingerprints saved before")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ringscan-identity-") as tmp:
        now = fingerprints(Path(tmp))
    if args.save:
        args.save.write_text(json.dumps(now, indent=1, sort_keys=True))
        print(f"{len(now)} files fingerprinted -> {args.save}")
        return 0
    before = json.loads(args.check.read_text())
    changed = sorted(k for k in before.keys() | now.keys() if before.get(k) != now.get(k))
    for k in changed:
        print(f"DIFFERS {k}: {'missing now' if k not in now else 'new' if k not in before else 'other bytes'}")
    print(f"{len(now)} files, {len(changed)} differ")
    return 1 if changed else 0


if __name__ == "__main__":
    sys.exit(main())
