"""Previews: offscreen rendering of clouds and meshes (:mod:`.render`) and colour
maps, heat maps and ring overlays (:mod:`.colour`)."""

from ringscan.pipeline.preview.colour import colorize, depth_heatmap, error_heatmap, heatmap, ring_overlay
from ringscan.pipeline.preview.render import ViewSettings, render_geometries, render_to_png

__all__ = ["colorize", "depth_heatmap", "error_heatmap", "heatmap", "ring_overlay", "ViewSettings",
           "render_geometries", "render_to_png"]
