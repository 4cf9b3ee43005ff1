"""Settings dataclasses <-> JSON: every stage's frozen dataclass is written next to
its outputs and read back with unknown keys refused and every value checked
against its field's type (pydantic, strict JSON rules: a number for a float, a
whole number for an int, true/false for a bool), the field's path in the message.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from dataclasses import dataclass

__all__ = ["settings_to_dict", "settings_from_dict", "check_finite_settings", "check_settings_types",
           "settings_json_schema", "apply_setting", "Bound", "check_ranges",
           "WHY_GREY", "WHY_MARGIN", "WHY_MODULATION", "WHY_FRACTION", "WHY_DEG", "WHY_ARC", "WHY_CAM_PX", "WHY_PROJ_PX", "WHY_MM", "WHY_LEVELS"]


def settings_to_dict(s) -> dict:
    return dataclasses.asdict(s)


def settings_from_dict(cls, d: dict):
    """Build a (nested) settings dataclass from a dict, rejecting unknown keys and
    values of the wrong type.

    Raises:
        ValueError: naming the setting, e.g. ``min_confidence: expected a number, got 'high'``.
    """
    if d is None:
        return cls()
    d = _drop_retired(cls, d, "")
    _check_keys(cls, d, "")
    if d:  # nothing given, nothing to check: the defaults are the class's own
        _validate(cls, d)
    return _build(cls, d)


def _drop_retired(cls, d, where: str):
    """``d`` without the fields a settings class no longer has (its ``RETIRED``: name ->
    the value it was fixed at), so that a run's old settings.json still loads; a
    retired field with another value is refused (the run would not be what it says)."""
    if not isinstance(d, dict):
        return d
    retired = getattr(cls, "RETIRED", {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = {}
    for k, v in d.items():
        if k in retired and k not in fields:
            if v != retired[k]:
                raise ValueError(f"{where}{k}: no longer a setting (fixed at {retired[k]!r}): leave it out")
            continue
        f = fields.get(k)
        sub = f.default_factory() if f is not None and f.default_factory is not dataclasses.MISSING else None
        out[k] = _drop_retired(type(sub), v, f"{where}{k}.") if dataclasses.is_dataclass(sub) else v
    return out


def _check_keys(cls, d, where: str) -> None:
    if not isinstance(d, dict):
        raise ValueError(f"{where.rstrip('.') or cls.__name__}: expected an object of settings, got {d!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k, v in d.items():
        if k not in fields:
            raise ValueError(f"{where}{k}: unknown setting of {cls.__name__} (known: {', '.join(fields)})")
        f = fields[k]
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(sub):
            _check_keys(type(sub), v, f"{where}{k}.")


@functools.cache
def _adapter(cls):
    from pydantic import TypeAdapter

    return TypeAdapter(cls)


_EXPECTED = {"float_type": "a number", "int_type": "a whole number", "bool_type": "true or false",
             "string_type": "a string", "tuple_type": "a list", "list_type": "a list",
             "dataclass_type": "an object of settings", "int_from_float": "a whole number"}


_SCALAR_CHECKS = {
    float: ("float_type", lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)),
    int: ("int_type", lambda v: isinstance(v, int) and not isinstance(v, bool)),
    bool: ("bool_type", lambda v: isinstance(v, bool)),
    str: ("string_type", lambda v: isinstance(v, str)),
}
"""A number, a whole number, true/false and a string, as pydantic's strict JSON rules have them (a bool is no
number), checked here: pydantic's own check costs its import (~0.05 s of a command given ``--set``)."""


def _validate(cls, d: dict, where: str = "") -> None:
    """Check every value of ``d`` against the type of its field of ``cls``: a nested settings class's values
    in turn, a scalar as :data:`_SCALAR_CHECKS` says, any other value against its field's own type (pydantic's
    schema of that type only: a whole settings class's costs ~0.07 s, one field's type a millisecond). Each
    value as JSON has it (a NumPy scalar as its Python value, anything else JSON cannot hold as its text)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k, v in d.items():
        f = fields[k]
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(sub) and isinstance(v, dict):
            _validate(type(sub), v, f"{where}{k}.")
            continue
        text = json.dumps(v, allow_nan=True, default=lambda o: o.item() if hasattr(o, "item") else str(o))
        t = _field_types(cls)[k]
        if t in _SCALAR_CHECKS:
            kind, ok = _SCALAR_CHECKS[t]
            value = json.loads(text)
            if not ok(value):
                got = "" if isinstance(value, dict) else f", got {value!r}"
                raise ValueError(f"{where}{k}: expected {_EXPECTED[kind]}{got}")
            continue
        _validate_with_pydantic(t, text, f"{where}{k}")


def _validate_with_pydantic(t, text: str, path: str) -> None:
    from pydantic import ValidationError

    try:
        _adapter(t).validate_json(text, strict=True)
    except ValidationError as e:
        err = e.errors(include_url=False)[0]
        path = ".".join(str(p) for p in (path, *err["loc"]))
        want = _EXPECTED.get(err["type"])
        what = f"expected {want}" if want else err["msg"][0].lower() + err["msg"][1:]
        got = f", got {err['input']!r}" if "input" in err and not isinstance(err["input"], dict) else ""
        raise ValueError(f"{path}: {what}{got}") from None


@functools.cache
def _field_types(cls) -> dict:
    import typing

    return typing.get_type_hints(cls)


def _build(cls, d: dict):
    kwargs = {}
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k, v in d.items():
        if k not in fields:
            raise ValueError(f"{cls.__name__}: unknown setting {k!r} (known: {', '.join(fields)})")
        f = fields[k]
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        kwargs[k] = _build(type(sub), v) if dataclasses.is_dataclass(sub) else v
    return cls(**kwargs)


def check_settings_types(s, *, where: str | None = None) -> None:
    """Refuse a settings dataclass (nested ones too) holding a value of the wrong
    type, e.g. ``ReconstructSettings(min_confidence="high")``, before it reaches a kernel.

    Raises:
        ValueError: naming the field, e.g. ``ReconstructSettings.min_confidence: expected a number, got 'high'``.
    """
    given = _changed(dataclasses.asdict(s), dataclasses.asdict(type(s)()))
    if given:  # (the defaults are the class's own: only what differs is checked)
        _validate(type(s), given, f"{where or type(s).__name__}.")


def _changed(d: dict, defaults: dict) -> dict:
    """The entries of ``d`` (nested dicts too) that are not their default, by value and by type."""
    out = {}
    for k, v in d.items():
        dv = defaults.get(k)
        if isinstance(v, dict) and isinstance(dv, dict):
            sub = _changed(v, dv)
            if sub:
                out[k] = sub
        elif type(v) is not type(dv) or not _same(v, dv):
            out[k] = v
    return out


def _same(a, b) -> bool:
    try:
        return bool(a == b)
    except (TypeError, ValueError):  # (an array's elementwise comparison, say: let the check see it)
        return False


def settings_json_schema(cls) -> dict:
    """The JSON Schema of a settings dataclass's JSON file (pydantic), each field
    described by its docstring."""
    schema = _adapter(cls).json_schema()
    docs = {}
    for c in _dataclasses_below(cls):
        docs[c.__name__] = _field_docs(c)
    for name, block in [(cls.__name__, schema), *schema.get("$defs", {}).items()]:
        for field, prop in block.get("properties", {}).items():
            if field in docs.get(name, {}):
                prop["description"] = docs[name][field]
    return schema


def _dataclasses_below(cls) -> list:
    out = [cls]
    for f in dataclasses.fields(cls):
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(sub):
            out += _dataclasses_below(type(sub))
    return out


def _field_docs(cls) -> dict:
    """Each field's docstring (the string literal after it in the class body), an
    inherited field's from its base class."""
    docs = {}
    for c in reversed(cls.__mro__):
        if dataclasses.is_dataclass(c):
            docs.update(_own_field_docs(c))
    return docs


def _own_field_docs(cls) -> dict:
    import ast
    import inspect
    import textwrap

    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError, SyntaxError):
        return {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs = {}
    for a, b in zip(body, body[1:]):
        if (isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr)
                and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str)):
            docs[a.target.id] = " ".join(b.value.value.split())
    return docs


def apply_setting(d: dict, assignment: str) -> dict:
    """Apply ``KEY=VALUE`` (``--set``) to a settings dict: ``KEY`` is a field's path
    (``min_confidence``, ``triangulate.sector_margin``), ``VALUE`` JSON (``0.5``,
    ``true``, ``[1, 2]``) or else a plain string. Returns ``d`` changed.

    Raises:
        ValueError: no ``=``, or an empty key.
    """
    key, sep, value = assignment.partition("=")
    key = key.strip()
    if not sep or not key or any(not p for p in key.split(".")):
        raise ValueError(f"--set {assignment!r}: expected KEY=VALUE, e.g. min_confidence=0.5 or "
                         f"triangulate.sector_margin=0.3")
    try:
        v = json.loads(value)
    except json.JSONDecodeError:
        v = value
    *parents, last = key.split(".")
    node = d
    for p in parents:
        nxt = node.get(p)
        if not isinstance(nxt, dict):
            nxt = node[p] = {}
        node = nxt
    node[last] = v
    return d


def check_finite_settings(s, *, where: str | None = None) -> None:
    """Refuse a settings dataclass (nested ones too) with a NaN or infinite number.

    Raises:
        ValueError: naming the field, e.g. ``FuseSettings.voxel_mm must be a finite number, got nan``.
    """
    where = where or type(s).__name__
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if dataclasses.is_dataclass(v):
            check_finite_settings(v, where=f"{where}.{f.name}")
        elif isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{where}.{f.name} must be a finite number, got {v}")


@dataclass(frozen=True)
class Bound:
    """The range a numeric setting may take, and why (:func:`check_ranges`)."""

    lo: float
    hi: float
    why: str
    lo_open: bool = False
    """True: ``lo`` itself is outside (``> lo``)."""

    def holds(self, v: float) -> bool:
        return (v > self.lo if self.lo_open else v >= self.lo) and v <= self.hi

    def text(self) -> str:
        lo = f"> {self.lo:g}" if self.lo_open else f"{self.lo:g}"
        return f"{lo} .. {self.hi:g}" if not self.lo_open else f"{lo} and <= {self.hi:g}"


WHY_GREY = "8-bit grey levels of white - black (x257 for 16-bit frames): below 1 an unlit pixel counts as lit; " \
        "above 200 only a white - black step of nearly the camera's whole range (255) passes"
WHY_MARGIN = "a fraction of white - black: 0 trusts a bit at the noise level, and |frame - inverse| never exceeds " \
          "white - black, so at 1 no bit is strong"
WHY_MODULATION = "a fringe modulation (1 for a perfect fringe): at 1 or more no pixel passes"
WHY_FRACTION = "a fraction of the pairs or samples: at most all of them (1)"
WHY_DEG = "degrees between two directions: at most 180"
WHY_ARC = "degrees of a circle: at most 360"
WHY_CAM_PX = "camera px: at most the largest camera side ringscan reads (65536)"
WHY_PROJ_PX = "projector px: at most the largest projector side a rig may have (65536)"
WHY_MM = "mm: at most the rig's sane length range (100 m)"
WHY_LEVELS = "8-bit grey levels: a frame holds at most 255"


def check_ranges(s, ranges: dict[str, Bound]) -> None:
    """Refuse a numeric setting of ``s`` outside its range: ``ranges`` maps a field's
    path (``decode.min_contrast``) to its :class:`Bound`.

    Raises:
        ValueError: naming the setting, e.g. ``decode.min_contrast: 1e+308 is outside 1 .. 200 (8-bit grey
            levels ...)``.
    """
    for path, bound in ranges.items():
        v = s
        for part in path.split("."):
            v = getattr(v, part)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue  # a value of the wrong type is check_settings_types's to name
        if not bound.holds(v):
            raise ValueError(f"{path}: {v:g} is outside {bound.text()} ({bound.why})")
