"""A sampled value's DataValue is built without asyncua's constructors (``scalar_data_value``): it must be the
object they build, field by field and byte by byte on the wire, for every type and status the server serves."""

import math
from dataclasses import fields
from datetime import UTC, datetime

import pytest
from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.ua.ua_binary import struct_from_binary, struct_to_binary

from valve_emulator.opcua import server
from valve_emulator.opcua.server import _EU_EXCEEDED, _GOOD, VARIABLES, _SharedDataValue, scalar_data_value

SOURCE, SERVED = datetime(2026, 11, 28, 10, 0, 0, 123456, tzinfo=UTC), datetime(2026, 11, 28, 10, 0, 0, 150000,
                                                                                 tzinfo=UTC)
CASES = [(61.3, ua.VariantType.Double), (-0.0, ua.VariantType.Double), (math.inf, ua.VariantType.Double),
         (1e39, ua.VariantType.Double), (0, ua.VariantType.UInt16), (65535, ua.VariantType.UInt16),
         (4_000_000_000, ua.VariantType.UInt32), (True, ua.VariantType.Boolean), (False, ua.VariantType.Boolean)]


def _field_by_field(dv):
    return [(f.name, getattr(dv, f.name)) for f in fields(ua.DataValue)] + \
        [(f.name, getattr(dv.Value, f.name)) for f in fields(ua.Variant)]


def test_every_variable_type_the_server_serves_is_among_the_cases():
    served = {v.variant for v in VARIABLES} | {ua.VariantType.Boolean}
    assert served <= {variant for _, variant in CASES}


@pytest.mark.parametrize("status", [_GOOD, _EU_EXCEEDED])
@pytest.mark.parametrize(("value", "variant"), CASES)
def test_a_data_value_built_directly_is_the_one_asyncuas_constructors_build(value, variant, status):
    theirs = _SharedDataValue(Value=ua.Variant(value, variant), StatusCode=status, SourceTimestamp=SOURCE,
                              ServerTimestamp=SERVED)
    ours = scalar_data_value(value, variant, status, SOURCE, SERVED)
    assert type(ours) is _SharedDataValue and type(ours.Value) is ua.Variant
    assert ours == theirs and _field_by_field(ours) == _field_by_field(theirs)
    wire = struct_to_binary(ours)
    assert wire == struct_to_binary(theirs)
    back = struct_from_binary(ua.DataValue, Buffer(wire))
    assert (back.Value.Value, back.Value.VariantType, back.StatusCode) == (value, variant, status)


def test_another_asyncuas_classes_are_built_by_their_constructors(monkeypatch):
    """Where asyncua's Variant or DataValue has other fields than those set directly, the constructors build it."""
    monkeypatch.setattr(server, "_BUILT_DIRECTLY", False)
    built = scalar_data_value(2.5, ua.VariantType.Double, _GOOD, SOURCE, SERVED)
    assert built == _SharedDataValue(Value=ua.Variant(2.5, ua.VariantType.Double), StatusCode=_GOOD,
                                     SourceTimestamp=SOURCE, ServerTimestamp=SERVED)
    assert server._BUILT_DIRECTLY is False
    monkeypatch.undo()
    assert server._BUILT_DIRECTLY   # asyncua 2.1.0, installed here: built directly
