"""A package's names imported on first use (PEP 562's module ``__getattr__``), so that importing the package
stays light: ``valve_emulator`` and ``valve_emulator.diagnosis`` export this way."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, MutableMapping
from typing import Any

__all__ = ["exports"]


def exports(package: str, names: Mapping[str, str], namespace: MutableMapping[str, Any]) -> Callable[[str], Any]:
    """The ``__getattr__`` of ``package`` (its ``__name__``) for ``names`` (name -> module that defines it): a
    name is imported from its module when first asked for and kept in ``namespace`` (the package's
    ``globals()``), so the next access does not come here; any other name is an :class:`AttributeError`."""

    def __getattr__(name: str) -> Any:
        if name in names:
            value = getattr(importlib.import_module(names[name]), name)
            namespace[name] = value
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
