"""The README and the documents say what the code does: their snippets run, their configs load, their links
resolve, and the register table in docs/device.md is what ``valve-emulator registers`` prints."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from valve_emulator.config import loop_from_mapping, server_from_mapping
from valve_emulator.scenario import DeviceShape, parse_scenario

ROOT = Path(__file__).resolve().parents[2]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^( *)```([\w+-]*)[^\n]*\n(.*?)^\1```", re.S | re.M)


def blocks(path: Path, *kinds: str) -> list[tuple[int, str]]:
    """The fenced code blocks of a Markdown file whose info string is one of ``kinds``: (line, code)."""
    text = path.read_text(encoding="utf-8")
    out = []
    for m in FENCE.finditer(text):
        if m.group(2) in kinds:
            indent = len(m.group(1))
            code = "\n".join(line[indent:] for line in m.group(3).splitlines())
            out.append((text.count("\n", 0, m.start()) + 1, code + "\n"))
    return out


def _ids(items):
    return [f"{p.relative_to(ROOT)}:{line}" if isinstance(p, Path) else str(p) for p, line, *_ in items]


def _workdir(tmp_path: Path) -> Path:
    """A scratch folder that sees the repository's example configs, so snippets write nothing into it."""
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    return tmp_path


PYTHON = [(p, 0) for p in DOCUMENTS if blocks(p, "python")]


@pytest.mark.parametrize(("path", "line"), PYTHON, ids=_ids(PYTHON))
def test_python_snippets_run(path, line, tmp_path):
    """All Python blocks of one document, in order, as one script (later blocks may use earlier names)."""
    code = "\n".join(f"# {path.name}:{ln}\n{src}" for ln, src in blocks(path, "python"))
    out = subprocess.run([sys.executable, "-c", code], cwd=_workdir(tmp_path), capture_output=True, text=True,
                         timeout=600, env={**os.environ, "MPLBACKEND": "Agg"})
    assert out.returncode == 0, f"{path.name}: a Python snippet failed:\n{out.stderr[-3000:]}"


YAML = [(p, ln, src) for p in DOCUMENTS for ln, src in blocks(p, "yaml")]


@pytest.mark.parametrize(("path", "line", "src"), YAML, ids=_ids(YAML))
def test_yaml_snippets_are_valid(path, line, src):
    """A config or training-scenario snippet loads through its validating loader; a Kubernetes manifest is at
    least valid YAML."""
    data = yaml.safe_load(src)
    assert isinstance(data, dict), f"{path.name}:{line}: not a mapping"
    if "apiVersion" in data:
        assert data["kind"] and data["spec"]
    elif "events" in data and "device" in data:
        parse_scenario(src, source=f"{path.name}:{line}", base=ROOT)
    elif "events" in data:   # a station's scenario: checked against a two-loop device like the station's
        two_loops = server_from_mapping({"loops": [{"unit": 1, "plant": {"num": [1.0], "den": [1.0, 1.0]}},
                                                   {"unit": 2, "plant": {"num": [1.0], "den": [1.0, 1.0]}}]})
        parse_scenario(src, source=f"{path.name}:{line}", device=DeviceShape.of_config(two_loops))
    elif "loops" in data or "fleet" in data:
        server_from_mapping(data, source=f"{path.name}:{line}")
    else:
        loop_from_mapping(data, source=f"{path.name}:{line}")


def _free_ports(n: int) -> list[int]:
    """``n`` distinct free ports (all bound at once, then released)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


BASH = [(p, ln, src) for p in DOCUMENTS for ln, src in blocks(p, "bash")]


@pytest.mark.slow
@pytest.mark.parametrize(("path", "line", "src"), BASH, ids=_ids(BASH))
def test_shell_snippets_run(path, line, src, tmp_path):
    """A ``bash`` block runs as written (``sh`` blocks are for other machines: systemd, another host), in a
    scratch folder, on free ports instead of 5020 (Modbus) and 8080 (the station); servers it starts in the
    background are stopped after. Any failing command fails it (``set -e``); a pipe into ``head`` may end
    early, as it does for a reader."""
    modbus, web = _free_ports(2)
    script = ("set -eu\ntrap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n"
              + src.replace("5020", str(modbus)).replace("8080", str(web)))
    proc = subprocess.Popen(["bash", "-c", script], cwd=_workdir(tmp_path), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env={**os.environ, "MPLBACKEND": "Agg"})
    try:
        out, _ = proc.communicate(timeout=600)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    assert proc.returncode == 0, f"{path.name}:{line}: the shell snippet failed:\n{out[-3000:]}"


LINK = re.compile(r"\[[^\]]*\]\(([^)#\s]+)(#[^)\s]*)?\)")


@pytest.mark.parametrize("path", DOCUMENTS, ids=[str(p.relative_to(ROOT)) for p in DOCUMENTS])
def test_relative_links_resolve(path):
    missing = [target for target, _ in LINK.findall(path.read_text(encoding="utf-8"))
               if "://" not in target and not target.startswith("mailto:")
               and not (path.parent / target).exists()]
    assert not missing, f"{path.relative_to(ROOT)} links to missing files: {missing}"


def test_device_md_register_table_is_the_commands_output(capsys):
    from valve_emulator.cli import main

    assert main(["registers", "--format", "md"]) == 0
    printed = capsys.readouterr().out.strip()
    text = (ROOT / "docs" / "device.md").read_text(encoding="utf-8")
    m = re.search(r"<!-- valve-emulator registers: begin -->\n(.*?)\n<!-- valve-emulator registers: end -->",
                  text, re.S)
    assert m, "docs/device.md has lost its register-table markers"
    assert m.group(1).strip() == printed, \
        "docs/device.md: regenerate the table with `valve-emulator registers --format md`"
