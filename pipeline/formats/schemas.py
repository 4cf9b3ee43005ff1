"""JSON Schemas of the rig file and scan.json (``ringscan schema rig|scan``), for editors and other tools.

The loaders (:func:`.rig.parse_rig`, :func:`.scan.load_scan`, :func:`.patterns.parse_patterns`)
stay the authority: they read every file, and their messages name the field. These pydantic
models only describe the same files as a JSON Schema (draft 2020-12), with the loaders' types,
required fields and ranges, so that a file the loaders accept validates, and a file with a
missing field, a wrong type or a value out of range does not. What a JSON Schema cannot say is
left to the loaders and named in the descriptions: a rotation matrix being a rotation, the
working volume in front of each camera, two cameras apart, the patterns' size equal to the
projector's, a path that leaves the scan folder through a link, frame files present, view names
unique ignoring case. A JSON Schema also takes ``1280.0`` for an integer, where the loaders
want ``1280``. Unknown keys are accepted, as the loaders accept (and keep) them.

The two-camera fields (a rig's ``camera2``, the ``uncalibrated`` light, a view's ``camera2``)
are optional: a one-camera file validates as before.
"""

from __future__ import annotations

import copy
import functools
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, create_model

from ringscan.pipeline.formats.patterns import PATTERN_LAYOUTS, PRECOMPENSATED_GAMMA_RANGE
from ringscan.pipeline.formats.rig import (
    GAMMA_RANGE,
    MAX_DISTORTION,
    MAX_IMAGE_SIZE,
    MAX_LENGTH_MM,
    MAX_PIXELS,
    MIN_FOCAL_PX,
    PIXEL_PITCH_RANGE_MM,
    RIG_FORMAT,
)
from ringscan.pipeline.formats.scan import SCAN_FORMAT, SCAN_FORMAT_PACKED

__all__ = ["rig_json_schema", "scan_json_schema", "DRAFT"]

DRAFT = "https://json-schema.org/draft/2020-12/schema"

# the loaders accept (and ignore or keep) unknown keys; Python's re for the path patterns' look-aheads
_OPEN = ConfigDict(extra="allow", regex_engine="python-re")

# ----------------------------------------------------------------------------- rig

Size = Annotated[int, Field(ge=1, le=MAX_IMAGE_SIZE, description="pixels")]
Length = Annotated[float, Field(ge=-MAX_LENGTH_MM, le=MAX_LENGTH_MM)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Row3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Rotation = Annotated[list[Row3], Field(min_length=3, max_length=3,
                                       description="3x3 rotation, world -> this device (the loader checks "
                                                   "R R^T = I and det R = 1)")]
Translation = Annotated[list[Length], Field(min_length=3, max_length=3,
                                            description="translation world -> this device (mm): X = R X_w + t")]
_Focal = Annotated[float, Field(ge=MIN_FOCAL_PX, le=MAX_PIXELS)]
_Pixels = Annotated[float, Field(ge=-MAX_PIXELS, le=MAX_PIXELS)]
_Zero = Annotated[float, Field(ge=0, le=0)]
_One = Annotated[float, Field(ge=1, le=1)]
Intrinsics = Annotated[tuple[tuple[_Focal, _Pixels, _Pixels], tuple[_Zero, _Focal, _Pixels],
                             tuple[_Zero, _Zero, _One]],
                       Field(description="3x3 intrinsic matrix [[fx, skew, cx], [0, fy, cy], [0, 0, 1]], pixels")]
Distortion = Annotated[list[Annotated[float, Field(ge=-MAX_DISTORTION, le=MAX_DISTORTION)]],
                       Field(min_length=4, max_length=14,
                             json_schema_extra={"anyOf": [
                                 *({"minItems": n, "maxItems": n} for n in (4, 5, 8, 12)),
                                 {"minItems": 14, "maxItems": 14,  # the tilt (taux, tauy) must be 0
                                  "prefixItems": [True] * 12 + [{"const": 0}, {"const": 0}]}]},
                             description="OpenCV distortion, 4, 5, 8 or 12 coefficients (k1, k2, p1, p2[, k3[, k4, "
                                         "k5, k6[, s1, s2, s3, s4]]]: the rational and thin-prism models); 14 (+ "
                                         "taux, tauy) only with a zero tilt; absent or null: none")]


class Response(BaseModel):
    model_config = _OPEN
    gamma: float = Field(ge=GAMMA_RANGE[0], le=GAMMA_RANGE[1], description="response gamma (1 = linear)")


class Camera(BaseModel):
    """A calibrated OpenCV pinhole camera."""

    model_config = _OPEN
    width: Size
    height: Size
    K: Intrinsics
    dist: Distortion | None = None
    R: Rotation
    t: Translation
    response: Response | None = Field(None, description="recorded = full_scale * (irradiance / full)^(1/gamma)")


class ParallelLight(BaseModel):
    """The paper's collimated light: projector pixel (u, v) lights x_L = s (u - a_u), y_L = s (v - a_v)."""

    model_config = _OPEN
    model: Literal["parallel"]
    R: Rotation = Field(None, description="rotation world -> light frame (default: identity)")
    t: Translation = Field(None, description="translation world -> light frame, mm (default: 0)")
    pixel_pitch_mm: float = Field(ge=PIXEL_PITCH_RANGE_MM[0], le=PIXEL_PITCH_RANGE_MM[1],
                                  description="s: one projector pixel at the object (mm)")
    axis_px: Annotated[list[_Pixels], Field(min_length=2, max_length=2)] = Field(
        description="(a_u, a_v): the projector pixel on the light axis")
    width: Size | None = Field(None, description="projector width (absent: unknown)")
    height: Size | None = Field(None, description="projector height (absent: unknown)")
    response: Response | None = Field(None, description="emitted = (value / full_scale)^gamma")


class PerspectiveLight(BaseModel):
    """A calibrated projector: an inverse OpenCV camera."""

    model_config = _OPEN
    model: Literal["perspective"]
    width: Size
    height: Size
    K: Intrinsics
    dist: Distortion | None = None
    R: Rotation
    t: Translation
    response: Response | None = Field(None, description="emitted = (value / full_scale)^gamma")


class UncalibratedLight(BaseModel):
    """A projector of unknown geometry (its size only): two-camera rigs only (``camera2`` present)."""

    model_config = _OPEN
    model: Literal["uncalibrated"]
    width: Size
    height: Size
    response: Response | None = Field(None, description="emitted = (value / full_scale)^gamma")


class Volume(BaseModel):
    """The working volume in the world frame (the loader checks z_max > z_min)."""

    model_config = _OPEN
    z_min: Length
    z_max: Length
    r_max: float = Field(gt=0, le=MAX_LENGTH_MM, description="largest distance from the light axis (mm)")


class Turntable(BaseModel):
    model_config = _OPEN
    axis_point: Translation = Field(description="a point on the axis (world, mm)")
    axis_dir: Vec3 = Field(description="direction of the axis (world; not zero; normalised when read)")


class Rig(BaseModel):
    """A ringscan rig file (docs/formats.md, docs/design.md §11)."""

    model_config = ConfigDict(**_OPEN, title="ringscan rig",
                              json_schema_extra={"if": {"properties": {"light": {"properties": {
                                  "model": {"const": "uncalibrated"}}}}, "required": ["light"]},
                                  "then": {"required": ["camera2"],
                                           "properties": {"camera2": {"type": "object"}}}})
    format: Literal[RIG_FORMAT]  # type: ignore[valid-type]
    units: Literal["mm"] = "mm"
    camera: Camera
    camera2: Camera | None = Field(None, description="a second camera in the same world frame (two-camera rigs)")
    light: Annotated[Union[ParallelLight, PerspectiveLight, UncalibratedLight], Field(discriminator="model")]
    volume: Volume
    turntable: Turntable | None = None


# ----------------------------------------------------------------------------- scan.json

RelPath = Annotated[str, Field(
    min_length=1, pattern=r"^(?![A-Za-z]:)(?![/\\])(?!(.*[/\\])?\.\.([/\\]|$))[^\x00-\x1f\x7f]+$",
    description="a path relative to the scan folder that stays inside it (no '..', not absolute)")]
ViewName = Annotated[str, Field(
    pattern=r'^(?!\.)[^/\\<>:"|?*\x00-\x1f\x7f]{1,200}$',
    description="folder-safe: 1-200 characters, no leading dot, none of / \\ < > : \" | ? * or control characters "
                "(unique ignoring case: checked by the loader)")]


class Packed(BaseModel):
    model_config = _OPEN
    store: RelPath = Field(description="the frame store (a Zarr v3 folder) relative to the scan folder")
    frames: list[ViewName] = Field(min_length=1, description="the store's frame names, in store order (distinct)")


def _frames_or_packed(title: str):
    """A camera's frames of a view: image files (``frames``) or one store (``packed``), not both."""
    return {"title": title, "oneOf": [{"required": ["frames"], "not": {"required": ["packed"]}},
                                      {"required": ["packed"], "not": {"required": ["frames"]}}]}


class CameraFrames(BaseModel):
    """Camera 2's frames of a view (two-camera rigs): its own files or store, the same frame names."""

    model_config = ConfigDict(**_OPEN, json_schema_extra=_frames_or_packed("CameraFrames"))
    frames: dict[str, RelPath] = Field(None, description="frame name -> image file")
    packed: Packed = Field(None, description="camera 2's frames as one frame store (format scan/2)")


class View(BaseModel):
    model_config = ConfigDict(**_OPEN, json_schema_extra=_frames_or_packed("View"))
    name: ViewName = Field(None, description="default view_<index> (3 digits)")
    turntable_deg: float = Field(0.0, description="turntable angle of this view (degrees)")
    frames: dict[str, RelPath] = Field(None, description="frame name -> image file (PNG or TIFF)")
    packed: Packed = Field(None, description="the view's frames as one frame store (format scan/2)")
    camera2: CameraFrames = Field(None, description="camera 2's frames (needs a rig with camera2)")


def _pattern_models():
    """One model per codec, from its layout's parameters (patterns.py), so a new codec or range is here too."""
    models = []
    for codec, layout in PATTERN_LAYOUTS.items():
        fields = {"codec": (Literal[codec], ...),
                  "width": (Size, ...), "height": (Size, ...),
                  "center": (Annotated[list[float], Field(min_length=2, max_length=2,
                                                          description="ring centre (c_u, c_v), projector px")], ...),
                  "rho0": (float, Field(ge=0, description="inner radius of the coded annulus (px)")),
                  "pitch": (float, Field(gt=0, description="ring pitch (px)"))}
        for p in layout.parameters:
            if p.kind is int:
                kind = Annotated[int, Field(ge=p.lo, le=p.hi, description=p.doc)]
            else:
                kind = Annotated[float, Field(gt=0, description=p.doc)] if p.positive else \
                    Annotated[float, Field(description=p.doc)]
            fields[p.name] = (kind, ... if p.default is None else p.default)
        config = _OPEN
        if layout.projectable:
            fields["precompensated_gamma"] = (float, Field(
                None, ge=PRECOMPENSATED_GAMMA_RANGE[0], le=PRECOMPENSATED_GAMMA_RANGE[1],
                description="gamma the frames were pre-compensated for"))
        else:  # nothing is projected: nothing to pre-compensate
            config = ConfigDict(**_OPEN, json_schema_extra={"not": {"required": ["precompensated_gamma"]}})
        models.append(create_model(f"Patterns_{codec.replace('-', '_')}", __config__=config, **fields))
    return tuple(models)


_PATTERNS = _pattern_models()


class TruthView(BaseModel):
    model_config = _OPEN
    depth: RelPath = Field(description="the view's true depth map")
    lit: RelPath = Field(description="the view's lit-pixel mask")


class Truth(BaseModel):
    """The virtual rig's ground truth (``ringscan simulate``; read by evaluate)."""

    model_config = _OPEN
    mesh: RelPath = Field(description="the scene's mesh")
    views: dict[str, TruthView] = Field(None, description="view name -> its truth maps")
    reference_plane_z: float = Field(0.0, description="height of the reference plane (mm)")
    reference_plane: bool = Field(True, description="the scene has the reference plane")
    settings: Any = Field(None, description="the simulation's settings (kept as written)")
    scene: Any = Field(None, description="the scene's name")
    light: Any = Field(None, description="the light the virtual rig rendered with (a rig's light block; evaluate "
                                         "uses it where the scan's rig has an uncalibrated projector)")


class Scan(BaseModel):
    """A ringscan scan.json (docs/formats.md, docs/design.md §11)."""

    model_config = ConfigDict(**_OPEN, title="ringscan scan.json", json_schema_extra={
        # packed views need format scan/2 (views' own or camera 2's)
        "if": {"properties": {"views": {"contains": {"anyOf": [
            {"required": ["packed"]},
            {"properties": {"camera2": {"required": ["packed"]}}, "required": ["camera2"]}]}}},
            "required": ["views"]},
        "then": {"properties": {"format": {"const": SCAN_FORMAT_PACKED}}}})
    format: Literal[SCAN_FORMAT, SCAN_FORMAT_PACKED]  # type: ignore[valid-type]
    rig: Union[Rig, RelPath] = Field(description="the rig, or the name of a rig file in the scan folder")
    patterns: Annotated[Union[_PATTERNS], Field(discriminator="codec")]  # type: ignore[valid-type]
    views: list[View]
    frame_bits: int = Field(None, ge=8, le=16, description="bits a frame holds: 8 for 8-bit frames, 9..16 for 16-bit "
                                                          "frames holding 0..2^frame_bits - 1 (a 10- or 12-bit "
                                                          "camera's), read scaled to 16 bits; default the frames' "
                                                          "own (the loader checks it against the frames as they are "
                                                          "read)")
    truth: Truth | None = None


@functools.cache
def _schema(model) -> dict:
    schema = {"$schema": DRAFT, **model.model_json_schema(mode="validation")}
    _drop_null_defaults(schema)
    return schema


def _drop_null_defaults(node) -> None:
    """Remove ``"default": null`` where null is not a valid value (an optional key with no default value)."""
    if isinstance(node, dict):
        if node.get("default", 0) is None and not any(o.get("type") == "null" for o in node.get("anyOf", ())):
            del node["default"]
        for v in node.values():
            _drop_null_defaults(v)
    elif isinstance(node, list):
        for v in node:
            _drop_null_defaults(v)


def rig_json_schema() -> dict:
    """The JSON Schema (draft 2020-12) of a rig file."""
    return copy.deepcopy(_schema(Rig))


def scan_json_schema() -> dict:
    """The JSON Schema (draft 2020-12) of scan.json (its rig inline or a file name)."""
    return copy.deepcopy(_schema(Scan))
