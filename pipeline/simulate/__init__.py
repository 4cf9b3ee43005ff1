"""The virtual rig: procedural and file scenes (:mod:`.scenes`), the ray-traced
renderer (:mod:`.virtual_rig`), whole simulated scans (:mod:`.scan`) and their
ground truth (:mod:`.truth`), OpenCV Gray-code captures with truth (:mod:`.opencv_graycode`)."""

from ringscan.pipeline.simulate.opencv_graycode import read_graycode_truth, render_graycode_captures
from ringscan.pipeline.simulate.scan import prepare_scene, simulate_scan
from ringscan.pipeline.simulate.scenes import SCENES, SceneMesh, add_wall, make_scene, place_scene, pose_scene
from ringscan.pipeline.simulate.truth import Truth, load_truth
from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig, view_angles

__all__ = ["simulate_scan", "prepare_scene", "SCENES", "SceneMesh", "make_scene", "pose_scene", "place_scene",
           "add_wall", "Truth", "load_truth", "RenderSettings", "VirtualRig", "view_angles",
           "render_graycode_captures", "read_graycode_truth"]
