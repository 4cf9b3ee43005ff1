"""Fusion and meshing: turntable views into one object (:mod:`.turntable`),
several poses aligned (:mod:`.poses`), Poisson (:mod:`.mesh`) and TSDF
(:mod:`.tsdf`) meshes and the choice between them (:mod:`.meshing`), reconstruction
folders read and fused (:mod:`.recon`), and the fuse-and-mesh workflow (:mod:`.workflow`)."""

from ringscan.pipeline.fusion.mesh import MeshResult, MeshSettings, compare_to_truth, poisson_mesh
from ringscan.pipeline.fusion.meshing import mesh_cloud, mesh_fused
from ringscan.pipeline.fusion.poses import PoseSettings, fuse_poses
from ringscan.pipeline.fusion.recon import fuse_recon, fuse_recons
from ringscan.pipeline.fusion.tsdf import tsdf_mesh
from ringscan.pipeline.fusion.turntable import FuseResult, FuseSettings, fuse_views
from ringscan.pipeline.fusion.workflow import fuse_and_mesh

__all__ = ["MeshResult", "MeshSettings", "compare_to_truth", "poisson_mesh", "PoseSettings", "fuse_poses",
           "tsdf_mesh", "FuseResult", "FuseSettings", "fuse_views", "fuse_and_mesh", "fuse_recon", "fuse_recons",
           "mesh_cloud", "mesh_fused"]
