"""Read Device Identification (function code 43, MEI type 0x0E): the objects and the response PDU.

Pure (no pymodbus). *Modbus Application Protocol Specification V1.1b3* §6.21. The device offers the basic
and regular categories with stream and individual access, conformity level ``0x82``::

    id  object               category  value
    0   VendorName           basic     "valve_emulator"
    1   ProductCode          basic     "VE-STICKY-VALVE"
    2   MajorMinorRevision   basic     the package version, e.g. "0.1.0"
    3   VendorUrl            regular   the package's index page
    4   ProductName          regular   "valve_emulator sticky control valve"
    5   ModelName            regular   the loop's name (config ``name``)
    6   UserApplicationName  regular   the loop's ``description``, or the name of its config file

Request ``2B 0E code id``; response ``2B 0E code conformity more_follows next_id count {id len value}...``.

- code 1 (basic stream) returns objects ``id .. 2``, code 2 (regular stream) objects ``id .. 6``; a start
  id outside the category restarts at object 0, as §6.21 prescribes.
- code 3 (extended stream) asks for more than the device's conformity level: it is answered like code 2
  ("respond in accordance with its actual conformity level").
- code 4 (individual access) returns object ``id`` alone; an id the device does not have is refused with
  :class:`~valve_emulator.device.registers.RegisterAddressError` (exception 0x02).
- A stream that does not fit in one PDU (253 bytes) sets ``more_follows = 0xFF`` and ``next_id``; the
  client asks again from there.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from valve_emulator.device.registers import RegisterAddressError

__all__ = ["CONFORMITY", "OBJECT_NAMES", "Identity"]

#: Conformity level: regular identification, stream and individual access.
CONFORMITY: Final = 0x82
OBJECT_NAMES: Final = ("VendorName", "ProductCode", "MajorMinorRevision", "VendorUrl", "ProductName",
                       "ModelName", "UserApplicationName")
_LAST: Final = {1: 2, 2: 6, 3: 6}   # read code -> last object id of the stream
_MAX_PDU: Final = 253
_HEADER: Final = 7                  # fc, MEI, code, conformity, more follows, next id, count
_URL: Final = "https://pypi.org/project/valve-emulator/"   # where the package is published


@dataclass(frozen=True, slots=True, kw_only=True)
class Identity:
    """The seven identification objects of one unit, as ASCII bytes in object id order (``objects``)."""

    objects: tuple[bytes, ...]

    @classmethod
    def of_loop(cls, loop: Any) -> Identity:
        """The identity of a ``LoopConfig``: fixed vendor objects, its name and description."""
        from valve_emulator import __version__

        application = loop.description or (Path(loop.source).stem if loop.source else loop.name)
        values = ("valve_emulator", "VE-STICKY-VALVE", __version__, _URL, "valve_emulator sticky control valve",
                  loop.name, application)
        # each object's length is one byte, and all of them must fit a PDU on their own
        return cls(objects=tuple(v.encode("ascii", "replace")[:_MAX_PDU - _HEADER - 2] for v in values))

    def response(self, code: int, object_id: int) -> bytes:
        """The response PDU (function code first) to read device id ``code`` (1..4) from ``object_id``."""
        if code == 4:
            if not 0 <= object_id < len(self.objects):
                raise RegisterAddressError(
                    f"device identification object {object_id} does not exist (objects 0..{len(self.objects) - 1}: "
                    f"{', '.join(OBJECT_NAMES)})", address=object_id, count=1)
            ids: Sequence[int] = (object_id,)
        else:
            last = _LAST[code]
            ids = range(object_id if object_id <= last else 0, last + 1)
        body, size, more, next_id, count = [], _HEADER, 0, 0, 0
        for i in ids:
            value = self.objects[i]
            if size + 2 + len(value) > _MAX_PDU:
                more, next_id = 0xFF, i
                break
            body.append(bytes((i, len(value))) + value)
            size += 2 + len(value)
            count += 1
        return bytes((43, 0x0E, code, CONFORMITY, more, next_id, count)) + b"".join(body)
