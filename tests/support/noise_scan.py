"""A scan whose frames are seeded noise, for the tests of what happens to a scan's files (packing them into
stores and back, buffers, the pack command): every frame is known and differs from every other."""

import numpy as np

from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.rig import default_rig, parse_rig, rig_to_dict
from ringscan.pipeline.formats.scan import Scan, View, save_scan

SPEC = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0, "pitch": 4.0,
        "bits": 3, "sector_bits": 2}
W, H = 40, 30
"""The frames' size (pixels): small, nothing here is reconstructed."""


def noise_scan(folder, *, dtype=np.uint8, views=2, ext="png"):
    """Write a scan of ``views`` views in ``folder`` whose frames are seeded noise (W x H, ``dtype``, ``ext``
    files) on the default rig and :data:`SPEC`; return every frame as written, by (view index, frame name)."""
    d = rig_to_dict(default_rig())
    d["camera"].update(width=W, height=H)
    spec = parse_patterns(SPEC)
    rng = np.random.default_rng(3)
    hi = np.iinfo(dtype).max
    truth, vs = {}, []
    for k in range(views):
        frames = {}
        for n in frame_names(spec):
            img = rng.integers(0, hi + 1, size=(H, W), dtype=np.int64).astype(dtype)
            write_image(folder / f"view_{k}" / f"{n}.{ext}", img)
            frames[n] = f"view_{k}/{n}.{ext}"
            truth[(k, n)] = img
        vs.append(View(f"view_{k}", 10.0 * k, frames))
    save_scan(Scan(folder=folder, rig=parse_rig(d), patterns=spec, views=tuple(vs)))
    return truth
