"""The JSON Schema (draft 2020-12) of a diagnosis' JSON, shipped with the package.

:data:`SCHEMA_PATH` is ``diagnosis.schema.json`` next to this module; :func:`schema` reads it. Any validator
of draft 2020-12 checks a document against it, e.g. ``jsonschema.validate(d.to_json(), schema())``.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

__all__ = ["SCHEMA_PATH", "schema"]

#: Where the schema lives in the installed package.
SCHEMA_PATH = Path(__file__).with_name("diagnosis.schema.json")


@cache
def schema() -> dict:
    """The schema as a dict (read once)."""
    return json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))
