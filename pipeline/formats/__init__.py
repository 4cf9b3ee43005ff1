"""File formats (docs/design.md §11): everything ringscan reads and writes goes through here.

A leaf package: it imports nothing else of ringscan, so the hardware layer, the
pipeline and the tools all read and write scan folders, rig files, patterns,
settings, PLY clouds, meshes and images the same way. Writes are atomic; every
error names the file and the field.
"""

from ringscan.pipeline.formats.atomic import atomic_path, atomic_write_bytes, atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError, RingscanError
from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.meshes import MESH_FORMATS, read_cloud, read_mesh, write_cloud, write_mesh
from ringscan.pipeline.formats.patterns import CODECS, PatternSpec, frame_names, parse_patterns
from ringscan.pipeline.formats.ply import read_ply, write_ply
from ringscan.pipeline.formats.rig import Rig, default_rig, load_rig, parse_rig, rig_to_dict, save_rig
from ringscan.pipeline.formats.scan import Scan, View, load_scan, read_view_frames, save_scan
from ringscan.pipeline.formats.settings import settings_from_dict, settings_to_dict

__all__ = [
    "atomic_path", "atomic_write_bytes", "atomic_write_json", "read_json", "FormatError", "RingscanError",
    "read_image", "write_image", "MESH_FORMATS", "read_cloud", "read_mesh", "write_cloud", "write_mesh", "CODECS",
    "PatternSpec", "frame_names", "parse_patterns", "read_ply", "write_ply", "Rig", "default_rig", "load_rig",
    "parse_rig", "rig_to_dict", "save_rig", "Scan", "View", "load_scan", "read_view_frames", "save_scan",
    "settings_from_dict", "settings_to_dict",
]
