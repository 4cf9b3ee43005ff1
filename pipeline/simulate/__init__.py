"""The virtual rig: procedural and file scenes (:mod:`.scenes`), the ray-traced
renderer (:mod:`.virtual_rig`), whole simulated scans (:mod:`.scan`) and their
ground truth (:mod:`.truth`)."""

from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.scenes import SCENES, SceneMesh, make_scene, pose_scene
from ringscan.pipeline.simulate.truth import Truth, load_truth
from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig, view_angles

__all__ = ["simulate_scan", "SCENES", "SceneMesh", "make_scene", "pose_scene", "Truth", "load_truth",
           "RenderSettings", "VirtualRig", "view_angles"]
