"""pipeline.reconstruct.view.load_view_modules: the modules a view runs, imported up front (while its frames are
read), and only those."""

import os
import subprocess
import sys
import textwrap

PROBE = textwrap.dedent("""
    import dataclasses, sys
    from pathlib import Path
    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.formats.rig import default_rig
    from ringscan.pipeline.formats.scan import Scan
    from ringscan.pipeline.reconstruct.view import load_view_modules
    rig = default_rig()
    spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 16.0, "bits": 5})
    stereo = ("ringscan.kernels.stereo_rays", "ringscan.kernels.stereo_match", "ringscan.pipeline.reconstruct.stereo")
    load_view_modules(Scan(folder=Path("."), rig=rig, patterns=spec, views=()))
    one = [m in sys.modules for m in stereo] + ["ringscan.pipeline.codecs.gray_rings" in sys.modules]
    load_view_modules(Scan(folder=Path("."), rig=dataclasses.replace(rig, camera2=rig.camera), patterns=spec, views=()))
    print([*one, *[m in sys.modules for m in stereo]])
""")


def test_a_view_s_modules_are_its_codec_s_and_with_two_cameras_the_matcher_s():
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str([False, False, False, True, True, True, True])
