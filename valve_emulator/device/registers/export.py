"""The served register map as the tools integrators import: Kepware CSV, Ignition tag JSON, a Node-RED flow.

Pure (standard library only, no I/O). Each export describes the map one unit id serves
(:class:`~.mapping.RegisterMap`, the standard one or ``device.register_map``), one tag per row, with its
address, type, access and the linear scaling from raw counts to engineering units (:func:`linear_scaling`,
derived from the row's :class:`~.table.Conversion`; floats carry the engineering value itself):

- ``kepware``: the CSV a KEPServerEX Modbus device imports (*Tag Name, Address, Data Type, Respect Data Type,
  Client Access, Scan Rate, Scaling, Raw Low, Raw High, Scaled Low, Scaled High, Scaled Data Type, Clamp Low,
  Clamp High, Eng Units, Description, Negate Value*), six-digit addresses (``400101``). The word order of
  32/64-bit values is a property of the Kepware *device* ("First word low in 32-bit data types"): each such
  tag's description says which one it needs.
- ``ignition``: an Ignition tag folder (JSON, Tag Browser → Import Tags) of OPC tags whose item paths use the
  Ignition Modbus driver's designators (``[device]HRF101``: holding, float; one-based), with linear scaling.
  The word order is the Ignition device's *Reverse Word Order* setting, named in each tag's documentation.
- ``node-red``: a flow of ``node-red-contrib-modbus`` nodes: a ``modbus-client`` config node, a
  ``modbus-read`` per readable tag feeding a function node that decodes its words to the engineering value
  (``msg.topic`` the tag's name), and for each writable tag a function node that encodes an engineering
  value (``msg.payload``) into words feeding a ``modbus-write``. Addresses are zero-based, as the nodes take them.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

from valve_emulator.config.register_map import TABLES
from valve_emulator.device.registers.bits import Bit
from valve_emulator.device.registers.mapping import RegisterMap
from valve_emulator.device.registers.scaling import Scaling
from valve_emulator.device.registers.table import Conversion, R, Register
from valve_emulator.device.registers.words import CDAB

__all__ = ["EXPORT_FORMATS", "Tag", "export", "export_tags", "ignition", "kepware", "linear_scaling", "node_red"]

EXPORT_FORMATS: Final = ("kepware", "ignition", "node-red")
KEPWARE_COLUMNS: Final = ("Tag Name", "Address", "Data Type", "Respect Data Type", "Client Access", "Scan Rate",
                          "Scaling", "Raw Low", "Raw High", "Scaled Low", "Scaled High", "Scaled Data Type",
                          "Clamp Low", "Clamp High", "Eng Units", "Description", "Negate Value")
_KEPWARE_TYPES: Final = {"uint16": "Word", "int16": "Short", "uint32": "DWord", "int32": "Long", "float32": "Float",
                         "float64": "Double", "bits": "Boolean"}
_IGNITION_SUFFIX: Final = {"uint16": "", "int16": "S", "uint32": "UI", "int32": "I", "float32": "F", "float64": "D"}
_IGNITION_TABLE: Final = {"holding": "HR", "input": "IR", "coil": "C", "discrete_input": "DI"}
_IGNITION_TYPES: Final = {"uint16": "Int4", "int16": "Int2", "uint32": "Int8", "int32": "Int4", "float32": "Float4",
                          "float64": "Float8", "bits": "Boolean"}
_NODE_RED_READ: Final = {"holding": "HoldingRegister", "input": "InputRegister", "coil": "Coil",
                         "discrete_input": "Input"}
_JS_TYPE: Final = {"uint16": "UInt16", "int16": "Int16", "uint32": "UInt32", "int32": "Int32", "float32": "Float",
                   "float64": "Double"}


@dataclass(frozen=True, slots=True)
class Tag:
    """One exported tag: a row of the map with what every tool needs to know of it.

    ``scaling`` is ``(raw_lo, raw_hi, eng_lo, eng_hi)`` (engineering = linear in raw) or ``None`` (the raw value
    is the value: floats, bits, counters); ``word_order`` only for 32/64-bit types.
    """

    name: str
    table: str
    address: int
    type: str
    width: int
    writable: bool
    units: str
    scaling: tuple[float, float, float, float] | None
    word_order: str | None
    description: str


def linear_scaling(row: Register, scaling: Scaling, index: int = 0) -> tuple[float, float, float, float] | None:
    """``(raw_lo, raw_hi, eng_lo, eng_hi)`` of the linear map from a register's raw value to engineering units on
    loop ``index``, or ``None`` when the raw value is the value (floats, bits, counters, flags)."""
    conversion = row.conversion
    if row.type.is_float or conversion in (Conversion.FLAG, Conversion.BITS, Conversion.COUNTER):
        return None
    lo, hi = float(scaling.pv_lo[index]), float(scaling.pv_hi[index])
    if conversion is Conversion.COUNTS:
        e_lo, e_hi = row.span if row.span is not None else (lo, hi)
        return float(row.counts[0]), float(row.counts[1]), float(e_lo), float(e_hi)
    if conversion is Conversion.PV_RANGE:
        return 0.0, 100.0 * row.scale, lo, hi
    if conversion is Conversion.PV_SPAN:
        return 0.0, 100.0 * row.scale, 0.0, hi - lo
    if row.scale == 1:
        return None
    # LINEAR and LOOP_CURRENT: raw = value × scale, over the raw range the register takes (within its type)
    raw_lo, raw_hi = row.write if row.write[0] < row.write[1] else row.read_range
    return float(raw_lo), float(raw_hi), raw_lo / row.scale, raw_hi / row.scale


def _units(row: Register | Bit, pv_units: str) -> str:
    if isinstance(row, Bit):
        return ""
    if row.conversion is Conversion.PV_RANGE or (row.conversion is Conversion.COUNTS and row.quantity in ("pv", "sp")):
        return pv_units
    if row.conversion is Conversion.COUNTS:
        return row.units.replace("% of pv_range", pv_units)
    return pv_units if row.units in ("PV units", "% of pv_range") and row.type.is_float else row.units


def export_tags(regmap: RegisterMap, scaling: Scaling, *, pv_units: str = "", index: int = 0) -> list[Tag]:
    """The tags of ``regmap`` as loop ``index`` serves them (names made unique where a tag is placed twice;
    the standard map's input mirror is left out: its holding registers carry the same values)."""
    tables = ["holding", "coil", "discrete_input"] + ([] if regmap.standard else ["input"])
    tags: list[Tag] = []
    seen: set[str] = set()
    for table in sorted(tables, key=lambda t: ("holding", "input", "coil", "discrete_input").index(t)):
        for row in regmap.rows(table):
            name = row.name if row.name not in seen else f"{row.name}_{table}"
            seen.add(name)
            if isinstance(row, Bit):
                tags.append(Tag(name, table, row.address, "bits", 1, table == "coil", "", None, None, row.meaning))
                continue
            order = None
            if row.width > 1:
                order = (row.word_order or scaling.word_order).value
            tags.append(Tag(name, table, row.address, row.type.value, row.width, row.access is not R,
                            _units(row, pv_units or "PV units"), linear_scaling(row, scaling, index), order,
                            f"{row.quantity} ({row.access.value})"))
    return tags


# --- Kepware ---------------------------------------------------------------------------------------------------

def kepware(tags: Sequence[Tag], *, scan_rate_ms: int = 100) -> str:
    """The KEPServerEX tag-import CSV of ``tags`` (Modbus Ethernet driver, six-digit addresses)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\r\n")
    writer.writerow(KEPWARE_COLUMNS)
    for t in tags:
        address = f"{TABLES[t.table]}{t.address + 1:05d}"
        scaled = t.scaling is not None
        description = t.description + (f"; word order {t.word_order}: set the device's 'First word low in 32-bit "
                                       f"data types' {'on' if t.word_order == CDAB.value else 'off'}"
                                       if t.word_order else "")
        raw_lo, raw_hi, eng_lo, eng_hi = t.scaling if scaled else ("", "", "", "")
        writer.writerow([t.name, address, _KEPWARE_TYPES[t.type], 1, "R/W" if t.writable else "RO", scan_rate_ms,
                         "Linear" if scaled else "", _num(raw_lo), _num(raw_hi), _num(eng_lo), _num(eng_hi),
                         "Double" if scaled else "", 0 if scaled else "", 0 if scaled else "", t.units, description,
                         0])
    return buf.getvalue()


def _num(x: Any) -> str:
    return "" if x == "" else f"{float(x):g}"


# --- Ignition --------------------------------------------------------------------------------------------------

def ignition(tags: Sequence[Tag], *, device: str, folder: str) -> str:
    """An Ignition tag folder of OPC tags on the Modbus device connection ``device`` (JSON, Import Tags)."""
    items = []
    for t in tags:
        designator = _IGNITION_TABLE[t.table] + ("" if t.type == "bits" else _IGNITION_SUFFIX[t.type])
        tag: dict[str, Any] = {
            "name": t.name, "tagType": "AtomicTag", "valueSource": "opc", "opcServer": "Ignition OPC UA Server",
            "opcItemPath": f"ns=1;s=[{device}]{designator}{t.address + 1}",
            "dataType": "Float8" if t.scaling is not None else _IGNITION_TYPES[t.type],
            "accessRights": "Read_Write" if t.writable else "Read_Only",
            "documentation": t.description + (f"; word order {t.word_order} (device setting Reverse Word Order "
                                              f"{'on' if t.word_order == CDAB.value else 'off'})"
                                              if t.word_order else ""),
        }
        if t.units:
            tag["engUnit"] = t.units
        if t.scaling is not None:
            raw_lo, raw_hi, eng_lo, eng_hi = t.scaling
            tag.update(scaleMode="Linear", rawLow=raw_lo, rawHigh=raw_hi, scaledLow=eng_lo, scaledHigh=eng_hi)
        items.append(tag)
    return json.dumps({"name": folder, "tagType": "Folder", "tags": items}, indent=2) + "\n"


# --- Node-RED --------------------------------------------------------------------------------------------------

def _node_id(*parts: object) -> str:
    """A stable Node-RED node id (16 hex digits) for the node named by ``parts``."""
    return hashlib.sha1("/".join(map(str, parts)).encode()).hexdigest()[:16]


def _word_indices(t: Tag) -> list[int]:
    """Positions, in the words as read, of the words in big-endian (high first) order."""
    order = list(range(t.width))
    return order[::-1] if t.word_order == CDAB.value else order


def _decoder(t: Tag) -> str:
    """JavaScript of a function node: the words of ``t`` (``msg.payload`` of modbus-read) -> engineering value."""
    if t.type == "bits":
        return f'msg.payload = msg.payload[0] ? 1 : 0;\nmsg.topic = "{t.name}";\nreturn msg;\n'
    lines = [f"// {t.name}: {t.table} {t.address}..{t.address + t.width - 1}, {t.type}"
             + (f", word order {t.word_order}" if t.word_order else ""),
             f"const b = Buffer.alloc({2 * t.width});",
             f"{_word_indices(t)}.forEach((k, i) => b.writeUInt16BE(msg.payload[k], 2 * i));",
             f"const raw = b.read{_JS_TYPE[t.type]}BE(0);"]
    if t.scaling is None:
        lines.append("msg.payload = raw;")
    else:
        raw_lo, raw_hi, eng_lo, eng_hi = t.scaling
        lines.append(f"msg.payload = {eng_lo!r} + (raw - {raw_lo!r}) * ({eng_hi!r} - {eng_lo!r}) / ({raw_hi!r} - "
                     f"{raw_lo!r});")
    lines += [f'msg.topic = "{t.name}";', "return msg;"]
    return "\n".join(lines) + "\n"


def _encoder(t: Tag) -> str:
    """JavaScript of a function node: an engineering value (``msg.payload``) -> the words modbus-write sends."""
    if t.type == "bits":
        return "msg.payload = Boolean(Number(msg.payload));\nreturn msg;\n"
    lines = [f"// {t.name}: engineering value -> {t.type} at {t.table} {t.address}", "const x = Number(msg.payload);"]
    if t.scaling is None:
        lines.append("const raw = " + ("x;" if t.type.startswith("float") else "Math.round(x);"))
    else:
        raw_lo, raw_hi, eng_lo, eng_hi = t.scaling
        lines.append(f"const raw = Math.round({raw_lo!r} + (x - {eng_lo!r}) * ({raw_hi!r} - {raw_lo!r}) / "
                     f"({eng_hi!r} - {eng_lo!r}));")
    lines += [f"const b = Buffer.alloc({2 * t.width});", f"b.write{_JS_TYPE[t.type]}BE(raw, 0);",
              f"const words = {_word_indices(t)}.map(k => b.readUInt16BE(2 * k));",
              "msg.payload = " + ("words[0];" if t.width == 1 else "words;"), "return msg;"]
    return "\n".join(lines) + "\n"


def node_red(tags: Sequence[Tag], *, host: str, port: int, unit: int, label: str,
             rate_ms: int = 1000) -> str:
    """A Node-RED flow (JSON, Import) reading and writing ``tags`` of unit ``unit`` at ``host:port``."""
    tab, client, debug = _node_id(label, "tab"), _node_id(label, "client"), _node_id(label, "debug")
    nodes: list[dict[str, Any]] = [
        {"id": tab, "type": "tab", "label": label, "disabled": False, "info": ""},
        {"id": client, "type": "modbus-client", "name": f"{label} {host}:{port}", "clienttype": "tcp",
         "bufferCommands": True, "stateLogEnabled": False, "queueLogEnabled": False, "failureLogEnabled": True,
         "tcpHost": host, "tcpPort": str(port), "tcpType": "DEFAULT", "serialPort": "/dev/ttyUSB",
         "serialType": "RTU-BUFFERD", "serialBaudrate": "9600", "serialDatabits": "8", "serialStopbits": "1",
         "serialParity": "none", "serialConnectionDelay": "100", "serialAsciiResponseStartDelimiter": "0x3A",
         "unit_id": str(unit), "commandDelay": "1", "clientTimeout": "1000", "reconnectOnTimeout": True,
         "reconnectTimeout": "2000", "parallelUnitIdsAllowed": True},
        {"id": debug, "type": "debug", "z": tab, "name": "values", "active": True, "tosidebar": True,
         "console": False, "tostatus": False, "complete": "payload", "targetType": "msg", "x": 820, "y": 40,
         "wires": []},
    ]
    y = 40
    for t in tags:
        read, decode = _node_id(label, t.name, "read"), _node_id(label, t.name, "decode")
        nodes.append({"id": read, "type": "modbus-read", "z": tab, "name": f"read {t.name}", "topic": t.name,
                      "showStatusActivities": False, "logIOActivities": False, "showErrors": True,
                      "unitid": str(unit), "dataType": _NODE_RED_READ[t.table], "adr": str(t.address),
                      "quantity": str(t.width), "rate": str(rate_ms), "rateUnit": "ms", "delayOnStart": False,
                      "startDelayTime": "", "server": client, "useIOFile": False, "ioFile": "",
                      "useIOForPayload": False, "emptyMsgOnFail": False, "x": 150, "y": y,
                      "wires": [[decode], []]})
        nodes.append({"id": decode, "type": "function", "z": tab, "name": f"decode {t.name}", "func": _decoder(t),
                      "outputs": 1, "noerr": 0, "initialize": "", "finalize": "", "libs": [], "x": 420, "y": y,
                      "wires": [[debug]]})
        y += 60
        if t.writable:
            encode, write = _node_id(label, t.name, "encode"), _node_id(label, t.name, "write")
            single = t.width == 1
            kind = ("Coil" if t.type == "bits" else "HoldingRegister") if single else "MHoldingRegisters"
            nodes.append({"id": encode, "type": "function", "z": tab, "name": f"encode {t.name}",
                          "func": _encoder(t), "outputs": 1, "noerr": 0, "initialize": "", "finalize": "",
                          "libs": [], "x": 150, "y": y, "wires": [[write]]})
            nodes.append({"id": write, "type": "modbus-write", "z": tab, "name": f"write {t.name}",
                          "showStatusActivities": False, "showErrors": True, "unitid": str(unit),
                          "dataType": kind, "adr": str(t.address), "quantity": str(t.width), "server": client,
                          "emptyMsgOnFail": False, "keepMsgProperties": False, "x": 420, "y": y, "wires": [[], []]})
            y += 60
    return json.dumps(nodes, indent=2) + "\n"


def export(fmt: str, regmap: RegisterMap, scaling: Scaling, *, index: int = 0, pv_units: str = "",
           host: str = "127.0.0.1", port: int = 502, unit: int = 1, device: str = "valve_emulator",
           tick: float = 0.1) -> str:
    """``regmap`` as loop ``index`` of ``scaling`` serves it on ``unit``, rendered as ``fmt`` (one of
    :data:`EXPORT_FORMATS`)."""
    tags = export_tags(regmap, scaling, pv_units=pv_units, index=index)
    if fmt == "kepware":
        return kepware(tags, scan_rate_ms=max(1, round(tick * 1000)))
    if fmt == "ignition":
        return ignition(tags, device=device, folder=f"{device}_unit{unit}")
    if fmt == "node-red":
        return node_red(tags, host=host, port=port, unit=unit, label=f"{device} unit {unit}")
    raise ValueError(f"export: fmt must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
