"""Reconstruction: one view (:mod:`.view`), a whole scan folder with its report
(:mod:`.scan`), when a result is done (:mod:`.freshness`), and live reconstruction
during a capture (:mod:`.live`)."""

from ringscan.pipeline.reconstruct.freshness import REPORT_FORMAT, DoneCheck, InputHashes, check_done, hash_inputs
from ringscan.pipeline.reconstruct.live import LiveReconstructor
from ringscan.pipeline.reconstruct.scan import reconstruct_scan, scan_inputs
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import ViewCloud, reconstruct_view, write_view_ply

__all__ = ["LiveReconstructor", "REPORT_FORMAT", "reconstruct_scan", "scan_inputs", "ReconstructSettings",
           "ViewCloud", "reconstruct_view", "write_view_ply", "DoneCheck", "InputHashes", "check_done",
           "hash_inputs"]
