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

__all__ = ["settings_to_dict", "settings_from_dict", "check_finite_settings", "check_settings_types",
           "settings_json_schema", "apply_setting"]


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
    _check_keys(cls, d, "")
    _validate(cls, d)
    return _build(cls, d)


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


def _validate(cls, d: dict, where: str = "") -> None:
    """Check every value of ``d`` against the type of its field of ``cls``."""
    from pydantic import ValidationError

    try:
        text = json.dumps(d, allow_nan=True, default=lambda o: o.item() if hasattr(o, "item") else str(o))
        _adapter(cls).validate_json(text, strict=True)
    except ValidationError as e:
        err = e.errors(include_url=False)[0]
        path = ".".join(str(p) for p in err["loc"])
        want = _EXPECTED.get(err["type"])
        what = f"expected {want}" if want else err["msg"][0].lower() + err["msg"][1:]
        got = f", got {err['input']!r}" if "input" in err and not isinstance(err["input"], dict) else ""
        raise ValueError(f"{where}{path}: {what}{got}") from None


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
    _validate(type(s), dataclasses.asdict(s), f"{where or type(s).__name__}.")


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
    """Each field's docstring (the string literal after it in the class body)."""
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
