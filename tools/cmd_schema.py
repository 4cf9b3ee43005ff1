"""``ringscan schema settings|capture-settings|rig|scan``: the JSON Schema of a settings, rig or scan file."""

from __future__ import annotations

import importlib
import json

from ringscan.pipeline.formats.atomic import atomic_write_json, check_output_file
from ringscan.pipeline.formats.settings import settings_json_schema
from ringscan.tools.cli import basic_options

# What each name describes: (the dataclass's module, its name, where the file is used).
SCHEMAS = {
    "settings": ("ringscan.pipeline.reconstruct.settings", "ReconstructSettings",
                 "reconstruction settings: reconstruct/batch --settings, a run's settings.json"),
    "capture-settings": ("ringscan.hardware.capture.sequence", "CaptureSettings",
                         "capture settings: capture --capture-settings"),
    "rig": ("ringscan.pipeline.formats.schemas", "rig_json_schema", "a rig file: --rig, calibrate's output"),
    "scan": ("ringscan.pipeline.formats.schemas", "scan_json_schema", "a scan folder's scan.json"),
}


def add_parser(sub):
    p = sub.add_parser("schema", help="print the JSON Schema of a settings, rig or scan file",
                       description="Prints the JSON Schema (draft 2020-12, from pydantic) of a settings, rig or "
                                   "scan file, every field with its type, default and description, for editors "
                                   "and other tools. " + "; ".join(f"{k}: {v[2]}" for k, v in SCHEMAS.items()) + ".")
    p.add_argument("what", choices=list(SCHEMAS), help="which file")
    p.add_argument("--out", default=None, metavar="JSON", help="write it to this file (default: print it)")
    basic_options(p)
    return p


def run(args) -> int:
    module, name, _ = SCHEMAS[args.what]
    obj = getattr(importlib.import_module(module), name)
    if isinstance(obj, type):  # a settings dataclass
        schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", **settings_json_schema(obj)}
    else:  # a file's schema function (formats.schemas)
        schema = obj()
    if args.out:
        atomic_write_json(check_output_file(args.out, extensions=(".json",), what="schema file (--out)"), schema)
        print(f"wrote {args.out}")
    else:
        print(json.dumps(schema, indent=2))
    return 0
