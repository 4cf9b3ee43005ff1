"""Meshing with the chosen method: Poisson (:mod:`.mesh`) or TSDF (:mod:`.tsdf`), for a
bare oriented cloud or for a turntable fusion result."""

from __future__ import annotations

from ringscan.pipeline.fusion.mesh import (
    MIN_MESH_POINTS,
    MeshResult,
    MeshSettings,
    check_mesh_settings,
    drop_unusable_points,
    poisson_mesh,
)
from ringscan.pipeline.fusion.tsdf import tsdf_mesh

__all__ = ["mesh_cloud", "mesh_fused"]


def mesh_cloud(cloud, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Mesh a bare oriented cloud with ``settings.method``.

    Points that meshing cannot use (NaN, infinite, beyond +-``MAX_COORDINATE_MM``)
    are dropped first and counted in the result's ``info["dropped_points"]``.

    Raises:
        ValueError: fewer than ``MIN_MESH_POINTS`` usable points.
    """
    check_mesh_settings(settings)
    n_in = len(cloud.points)
    cloud, dropped = drop_unusable_points(cloud)
    if len(cloud.points) < MIN_MESH_POINTS:
        raise ValueError(f"the cloud has {len(cloud.points)} usable points (of {n_in}; {dropped['non_finite']} "
                         f"non-finite, {dropped['out_of_range']} out of range): too few to mesh "
                         f"(need at least {MIN_MESH_POINTS})")
    res = tsdf_mesh(cloud, settings=settings) if settings.method == "tsdf" else poisson_mesh(cloud, settings=settings)
    res.info["dropped_points"] = dropped
    return res


def mesh_fused(result, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Mesh a :class:`~ringscan.pipeline.fusion.turntable.FuseResult`: Poisson on its fused
    cloud, or TSDF from its views' depth maps."""
    check_mesh_settings(settings)
    if settings.method == "tsdf":
        return tsdf_mesh(result, settings=settings)
    return poisson_mesh(result.cloud, settings=settings)
