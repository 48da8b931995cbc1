"""Scenario YAML read with the line of every key, so that an error names ``file:line: key``.

Text is refused before parsing when it is longer than :data:`MAX_YAML_CHARS` or nests flow collections deeper
than :data:`MAX_FLOW_DEPTH`: PyYAML's pure-Python parser takes time quadratic in the nesting of ``[[[[...``
(2 s for 3,000), and the station parses scenarios in its event loop. A lesson is a few kB, three or four deep.
"""

from __future__ import annotations

from typing import Any

import yaml

from valve_emulator.errors import UserError

__all__ = ["MAX_FLOW_DEPTH", "MAX_YAML_CHARS", "ScenarioError", "Where", "load_yaml"]

MAX_YAML_CHARS = 64 * 1024
MAX_FLOW_DEPTH = 64


class ScenarioError(UserError):
    """A scenario that cannot be played; the message starts with ``file:line:`` (or ``source:`` without
    lines, for a scenario given as a mapping)."""


class Where:
    """Turns a dotted key (``events[2].malfunction.S``) into ``file:line: key`` for messages: the line of
    the key, or of the nearest enclosing key known."""

    def __init__(self, source: str, lines: dict[str, int] | None = None) -> None:
        self.source, self.lines = source, lines or {}

    def line(self, key: str) -> int:
        while key:
            if key in self.lines:
                return self.lines[key]
            cut = max(key.rfind("."), key.rfind("["))
            key = key[:max(cut, 0)]
        return 1

    def at(self, key: str) -> str:
        """``file:line`` of ``key`` (just ``file`` when the scenario came without lines)."""
        return f"{self.source}:{self.line(key)}" if self.lines else self.source

    def fail(self, key: str, message: str) -> ScenarioError:
        return ScenarioError(f"{self.at(key)}: {key}: {message}")


def _check_size(text: str, source: str) -> None:
    if len(text) > MAX_YAML_CHARS:
        raise ScenarioError(f"{source}:1: YAML text of {len(text)} characters; at most {MAX_YAML_CHARS}")
    depth = deepest = 0
    for opened in (ch in "[{" for ch in text if ch in "[]{}"):   # brackets inside quotes count too
        depth = depth + 1 if opened else max(0, depth - 1)
        deepest = max(deepest, depth)
        if deepest > MAX_FLOW_DEPTH:
            raise ScenarioError(f"{source}:1: YAML nested too deeply (more than {MAX_FLOW_DEPTH} levels of [ or {{)")


def _index(node: yaml.Node | None, key: str, lines: dict[str, int], source: str) -> None:
    """Record the 1-based line of every key and list item under ``key``; refuse duplicate keys."""
    if isinstance(node, yaml.MappingNode):
        seen: dict[str, int] = {}
        for k, v in node.value:
            if not isinstance(k, yaml.ScalarNode):
                continue
            child, line = (f"{key}.{k.value}" if key else k.value), k.start_mark.line + 1
            if k.value in seen:
                raise ScenarioError(f"{source}:{line}: duplicate key {child} (first on line {seen[k.value]})")
            seen[k.value] = lines[child] = line
            _index(v, child, lines, source)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            lines[f"{key}[{i}]"] = item.start_mark.line + 1
            _index(item, f"{key}[{i}]", lines, source)


def load_yaml(text: str, source: str) -> tuple[Any, Where]:
    """The document in ``text`` and a :class:`Where` holding the line of each of its keys."""
    _check_size(text, source)
    loader = yaml.SafeLoader(text)
    lines: dict[str, int] = {}
    try:
        node = loader.get_single_node()
        _index(node, "", lines, source)
        data = None if node is None else loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = "; ".join(str(p) for p in (exc.context, exc.problem) if p)
        raise ScenarioError(f"{source}:{mark.line + 1 if mark else 1}: YAML syntax error: {what}") from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{source}:1: YAML error: {exc}") from None
    except RecursionError:
        raise ScenarioError(f"{source}:1: YAML nested too deeply") from None
    finally:
        loader.dispose()
    return data, Where(source, lines)
