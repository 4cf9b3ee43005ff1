"""Reconstruction while capturing: each captured view is reconstructed on a
background thread while the next one is captured (``ringscan capture --reconstruct``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from ringscan.kernels import resolve_device
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.scan import Scan, View
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)

__all__ = ["LiveReconstructor"]


class LiveReconstructor:
    """Reconstruct each view of a scan while the next one is being captured.

    Pass the instance as ``on_view`` to :func:`ringscan.hardware.capture.capture_scan`:
    each finished view is queued to one background thread, which brings
    ``out_dir`` up to date with :func:`reconstruct_scan` (``resume=True``, so views
    already there are kept and each view is reconstructed once). Warp launches and
    image decoding release the GIL, so the capture goes on meanwhile. A failed
    reconstruction is logged and kept; the capture is never stopped by it.

    Call :meth:`finish` with the final scan when the capture ends (also after it
    stopped on a fault): it waits for the queue, brings the folder up to date with
    every complete view, and returns the report (None when a reconstruction failed;
    :attr:`error` says why).
    """

    def __init__(self, out_dir: str | os.PathLike, *, settings: ReconstructSettings = ReconstructSettings(),
                 device: str | None = None):
        from concurrent.futures import ThreadPoolExecutor

        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise ValueError(f"{self.out_dir}: exists and is not a folder (the reconstruction's output folder)")
        self.settings = settings
        self.device = resolve_device(device)
        self.error: str | None = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ringscan-live")
        self._futures: list = []

    def _update(self, scan: Scan, names: list[str]) -> dict | None:
        if self.error is not None:
            return None
        try:
            report = reconstruct_scan(scan, self.out_dir, settings=self.settings, device=self.device, views=names,
                                      resume=True, progress=False)
        except Exception as e:  # noqa: BLE001 - the capture must go on; reported by finish()
            self.error = f"reconstructing {names[-1]} of {scan.folder} into {self.out_dir} failed: {e}"
            log.error("%s", self.error)
            return None
        log.info("live reconstruction: %s done (%d points)", names[-1], report["views"][-1]["points"])
        return report

    def __call__(self, scan: Scan, view: View) -> None:
        """Queue ``view`` (and any complete view before it) of ``scan``."""
        names = [v.name for v in scan.views[: scan.views.index(view) + 1]]
        self._futures.append(self._pool.submit(self._update, scan, names))

    def finish(self, scan: Scan | None = None) -> dict | None:
        """Wait for the queued views; then, given the scan, reconstruct its complete views not yet done."""
        for f in self._futures:
            f.result()
        self._futures.clear()
        report = None
        if scan is not None:

            need = set(frame_names(scan.patterns))
            names = [v.name for v in scan.views if need.issubset(v.frames)]
            if names:
                report = self._pool.submit(self._update, scan, names).result()
        self._pool.shutdown(wait=True)
        return report
