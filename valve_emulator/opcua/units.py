"""Engineering units as OPC UA ``EUInformation``: UNECE Recommendation 20 codes, packed as OPC UA requires.

OPC UA Part 8 (§5.6.3, EUInformation) takes its units from UN/CEFACT Recommendation 20 ("Codes for Units of
Measurement used in International Trade"). ``NamespaceUri`` is ``http://www.opcfoundation.org/UA/units/un/cefact``
and ``UnitId`` is the unit's *common code* (two or three characters, e.g. ``SEC``, ``4K``) packed into an Int32,
one byte per character, first character highest::

    UnitId = 0
    for each character c of the common code: UnitId = (UnitId << 8) | ord(c)

so ``SEC`` (second) is ``0x53 << 16 | 0x45 << 8 | 0x43 = 5457219`` and ``4K`` (milliampere) is ``13387``.

:data:`UNITS` knows the unit texts a loop config is likely to use (``plant.units`` is free text, e.g. ``"kg/h"``,
``"m3/h"``, ``"degC"``). A text it does not know gets no guessed code: :func:`eu_information` answers
``UnitId = -1`` (Part 8: "no UnitId is available"), the text as ``DisplayName`` and this server's namespace, so a
client shows the configured text and knows it is not a UNECE unit. An empty text (no units configured) gets no
``EngineeringUnits`` at all.
"""

from __future__ import annotations

from dataclasses import dataclass

from asyncua import ua

__all__ = ["CEFACT", "UNITS", "Unece", "unit_id", "eu_information"]

#: The NamespaceUri of every EUInformation whose UnitId is a UNECE common code (OPC UA Part 8).
CEFACT = "http://www.opcfoundation.org/UA/units/un/cefact"


@dataclass(frozen=True)
class Unece:
    """One UNECE Recommendation 20 unit: its common code, its symbol and its name in the recommendation."""

    code: str
    symbol: str
    name: str


def unit_id(code: str) -> int:
    """The EUInformation.UnitId of a UNECE common code: its characters packed big-endian, one byte each."""
    packed = 0
    for char in code:
        packed = (packed << 8) | ord(char)
    return packed


_PERCENT = Unece("P1", "%", "percent")
_SECOND = Unece("SEC", "s", "second [unit of time]")
_KELVIN = Unece("KEL", "K", "kelvin")
_CELSIUS = Unece("CEL", "°C", "degree Celsius")
_FAHRENHEIT = Unece("FAH", "°F", "degree Fahrenheit")
_KG_PER_M3 = Unece("KMQ", "kg/m³", "kilogram per cubic metre")
_M3_PER_H = Unece("MQH", "m³/h", "cubic metre per hour")
_M3 = Unece("MTQ", "m³", "cubic metre")

#: Unit texts (as a loop config or the register map writes them) -> their UNECE unit. Case matters ("MPa" is
#: not "mPa"); "% travel" and "% flow", the register map's percentages, are percent.
UNITS: dict[str, Unece] = {
    "%": _PERCENT, "% travel": _PERCENT, "% flow": _PERCENT,
    "s": _SECOND, "ms": Unece("C26", "ms", "millisecond"), "min": Unece("MIN", "min", "minute [unit of time]"),
    "h": Unece("HUR", "h", "hour"),
    "mA": Unece("4K", "mA", "milliampere"), "A": Unece("AMP", "A", "ampere"), "V": Unece("VLT", "V", "volt"),
    "W": Unece("WTT", "W", "watt"), "Hz": Unece("HTZ", "Hz", "hertz"),
    "rpm": Unece("RPM", "r/min", "revolutions per minute"),
    "m": Unece("MTR", "m", "metre"), "mm": Unece("MMT", "mm", "millimetre"),
    "kg": Unece("KGM", "kg", "kilogram"), "g": Unece("GRM", "g", "gram"),
    "kg/h": Unece("E93", "kg/h", "kilogram per hour"), "kg/s": Unece("KGS", "kg/s", "kilogram per second"),
    "m3": _M3, "m³": _M3, "l": Unece("LTR", "l", "litre"),
    "m3/h": _M3_PER_H, "m³/h": _M3_PER_H,
    "kg/m3": _KG_PER_M3, "kg/m³": _KG_PER_M3,
    "bar": Unece("BAR", "bar", "bar [unit of pressure]"), "mbar": Unece("MBR", "mbar", "millibar"),
    "Pa": Unece("PAL", "Pa", "pascal"), "hPa": Unece("A97", "hPa", "hectopascal"),
    "kPa": Unece("KPA", "kPa", "kilopascal"), "MPa": Unece("MPA", "MPa", "megapascal"),
    "K": _KELVIN, "degC": _CELSIUS, "°C": _CELSIUS, "degF": _FAHRENHEIT, "°F": _FAHRENHEIT,
}


def eu_information(text: str, *, own_namespace: str) -> ua.EUInformation | None:
    """The EngineeringUnits of a variable in unit ``text``: UNECE where :data:`UNITS` knows the text; else
    ``UnitId`` -1 with the text as it is, in ``own_namespace``; ``None`` for no units (an empty text)."""
    text = text.strip()
    if not text:
        return None
    unit = UNITS.get(text)
    if unit is None:
        return ua.EUInformation(NamespaceUri=own_namespace, UnitId=-1, DisplayName=ua.LocalizedText(text),
                                Description=ua.LocalizedText(text))
    return ua.EUInformation(NamespaceUri=CEFACT, UnitId=unit_id(unit.code), DisplayName=ua.LocalizedText(unit.symbol),
                            Description=ua.LocalizedText(unit.name if unit.symbol == text else f"{unit.name} ({text})"))
