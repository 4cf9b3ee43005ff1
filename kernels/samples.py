"""The one samples type: what every codec's decode + sampling stages hand to
triangulation (``kernels.triangulation``), and what the kernel samplers
(``ring_sampling``, ``phase``) return."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

__all__ = ["Samples"]


@dataclass
class Samples:
    """Samples of one view (Warp arrays of length n, on the frames' device).

    The required fields are what triangulation reads today; the optional ones
    (None where the codec does not give them) carry the rest of each sample's
    projector position and its predicted errors.
    """

    uv: wp.array
    """vec2 (u, v) camera pixel coordinates."""
    rho: wp.array | None
    """float32 ring radius (projector px). None only straight out of
    ``ring_sampling.sample_gray_rings`` called without ``rho0``/``pitch`` (it
    knows band indices; ``ring_radii`` maps them)."""
    ring: wp.array | None
    """int32 ring / band-boundary index k (radius rho0 + k * pitch), or None for
    dense codecs (one sample per pixel, no ring)."""
    sector: wp.array
    """int32 decoded sector of the polar angle, -1 where unknown."""
    confidence: wp.array
    """float32 in [0, 1] (edge slope, fringe modulation or contrast, per codec)."""
    pixel: wp.array
    """int32 linear camera pixel index y * W + x of each sample."""
    phi: wp.array | None = None
    """float32 polar angle (radians) around the pattern centre on the projector
    grid, atan2(v_p - c_v, u_p - c_u); None where the codec has no angle."""
    sigma_rho: wp.array | None = None
    """float32 predicted standard deviation of ``rho`` (projector px), or None."""
    sigma_tan: wp.array | None = None
    """float32 predicted standard deviation of the tangential position
    rho * phi (projector px), or None."""
    sigma_uv: wp.array | None = None
    """vec2 the camera-side standard deviation of a sample placed across a line (the single-shot
    codec's line centres): its length in camera px, its direction across the line; None where the
    codec's errors are on the projector's side (``sigma_rho``; triangulation turns this one into
    it: ``kernels.error_terms.camera_side_sigmas``)."""
    across: wp.array | None = None
    """vec2i the samples of the next lines across a line sample's, along +``sigma_uv`` and against it
    (-1: none): where the surface's depth slope across the line is read; None where the codec has none."""
    across_px: wp.array | None = None
    """vec2 their distances (camera px) along that direction, each side (0: none)."""
    bias_uv: wp.array | None = None
    """float32 camera px: how far a line centre may sit off its line by what its neighbours along the
    line share and so cannot check (the light's gradient across it: ``RingLines.shading``), along
    ``sigma_uv``; None where the codec has none."""
    indirect: wp.array | None = None
    """float32 share (0..1) of the pixel's white - black that stays lit under both the
    finest band patterns and their inverses: about half the light that reaches it other
    than straight from the projector (inter-reflection, subsurface scattering: a fine
    pattern and its inverse each light half of what bounces in), plus what blur mixes
    across the patterns' edges; None where the codec gives none."""

    shading: wp.array | None = None
    """float32 the relative gradient of white - black at the sample (per camera px; |grad ln| where
    it changes smoothly, at most 1 across a step: ``kernels.light_gradient``): how fast the light its surface
    sends back changes across the image there (shading, texture, a highlight, a silhouette). The
    camera's blur weighs every edge and fringe by that light, so both coordinates read off their
    place by more where it is steep (``pipeline.reconstruct.error_scale``); None where the codec
    gives none."""

    def __len__(self) -> int:
        return self.uv.shape[0]

    def numpy(self) -> dict[str, np.ndarray]:
        """The fields that are set, as NumPy arrays (name -> (n,) or (n, 2))."""
        names = ("uv", "rho", "ring", "sector", "confidence", "pixel", "phi", "sigma_rho", "sigma_tan", "sigma_uv",
                 "across", "across_px", "bias_uv", "indirect", "shading")
        return {k: getattr(self, k).numpy() for k in names if getattr(self, k) is not None}

