"""Reconstruction: one view (:mod:`.view`), a whole scan folder with its report
(:mod:`.scan`), and live reconstruction during a capture (:mod:`.live`)."""

from ringscan.pipeline.reconstruct.live import LiveReconstructor
from ringscan.pipeline.reconstruct.scan import REPORT_FORMAT, reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import ViewCloud, reconstruct_view, write_view_ply

__all__ = ["LiveReconstructor", "REPORT_FORMAT", "reconstruct_scan", "ReconstructSettings", "ViewCloud",
           "reconstruct_view", "write_view_ply"]
