"""The JSON Schema (draft 2020-12) of a diagnosis' JSON, shipped with the package.

:data:`SCHEMA_PATH` is ``diagnosis.schema.json`` next to this module; :func:`schema` reads it and fills in the
vocabularies that come from the code, so that no list of candidates is kept by hand: the reason codes
(:class:`~valve_emulator.diagnosis.answers.Reason`, with every candidate registered by now), the physics of a
finding (:func:`~valve_emulator.diagnosis.candidates.base.registry`) and of a friction estimate
(:data:`~valve_emulator.diagnosis.answers.VALVE_FRICTION`). Any validator of draft 2020-12 checks a document
against it, e.g. ``jsonschema.validate(d.to_json(), schema())``.
"""

from __future__ import annotations

import copy
import json
from functools import cache
from pathlib import Path

from valve_emulator.diagnosis.answers import VALVE_FRICTION, Reason
from valve_emulator.diagnosis.candidates import registry

__all__ = ["SCHEMA_PATH", "schema"]

#: Where the schema lives in the installed package.
SCHEMA_PATH = Path(__file__).with_name("diagnosis.schema.json")


@cache
def _file() -> dict:
    """The schema as written in the file (read once)."""
    return json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))


def schema() -> dict:
    """The schema as a dict, its vocabularies those of the candidates registered now (a fresh copy)."""
    out = copy.deepcopy(_file())
    physics = list(registry())
    vocabularies = {"reason_code": list(dict.fromkeys([*physics, *(str(r) for r in Reason)])),
                    "physics": physics, "friction_physics": list(VALVE_FRICTION)}
    for name, words in vocabularies.items():
        out["$defs"][name]["enum"] = words
    return out
