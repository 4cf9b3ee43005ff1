"""The paper's single-shot ``rings`` codec: line detection (kernels), pieces
(:mod:`.pieces`), the nesting labeller (:mod:`.labeller`) and the reconstruct hook
(:mod:`.extract`)."""

from ringscan.pipeline.codecs.single_shot.extract import extract_rings
from ringscan.pipeline.codecs.single_shot.labeller import label_ring_lines, orientation_sign
from ringscan.pipeline.codecs.single_shot.pieces import build_pieces
from ringscan.pipeline.codecs.single_shot.settings import SECTOR_BITS, RingLabelling, SingleShotSettings

__all__ = ["extract_rings", "label_ring_lines", "orientation_sign", "build_pieces", "SECTOR_BITS", "RingLabelling",
           "SingleShotSettings"]
