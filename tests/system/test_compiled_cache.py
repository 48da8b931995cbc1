"""Compiled kernels are cached in a user folder, never inside the package, and only the first run compiles."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from valve_emulator import _cache

ROOT = Path(__file__).resolve().parents[2]

# One process: run the stiction kernels and report numba's cache statistics for the module's compiled functions.
PROBE = """
import json, numpy as np
import valve_emulator
from valve_emulator.physics import stiction
stiction.simulate(np.linspace(0.0, 50.0, 200), S=3.0, J=1.0)
from numba.core.registry import CPUDispatcher
kernels = [k for k in vars(stiction).values() if isinstance(k, CPUDispatcher)]
print(json.dumps({"package": valve_emulator.__file__,
                  "hits": sum(sum(k.stats.cache_hits.values()) for k in kernels),
                  "misses": sum(sum(k.stats.cache_misses.values()) for k in kernels)}))
"""


def _env(tmp_path: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), HOME=str(tmp_path / "home"), **extra)
    return env


def _probe(env: dict[str, str], cwd: Path) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, cwd=cwd, capture_output=True, text=True,
                         timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_cache_dir_follows_numba_cache_dir_then_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "chosen"))
    assert _cache.cache_dir() == tmp_path / "chosen"
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert _cache.cache_dir() == tmp_path / "xdg" / "valve_emulator" / "numba"
        assert (tmp_path / "xdg" / "valve_emulator" / "numba").is_dir()


def test_cache_dir_falls_back_to_temp_when_the_user_cache_cannot_be_created(monkeypatch, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker / "below"))
    monkeypatch.setenv("HOME", str(blocker / "below"))
    path = _cache.cache_dir()
    assert not str(path).startswith(str(blocker))
    assert path.name == "numba" and path.parent.name.startswith("valve_emulator-")


@pytest.mark.slow
def test_first_run_compiles_into_the_user_cache_and_the_second_does_not_compile(tmp_path):
    env = _env(tmp_path)
    first = _probe(env, tmp_path)
    cached = list((tmp_path / "xdg" / "valve_emulator" / "numba").rglob("*.nbi"))
    assert first["misses"] >= 1 and cached, "the first run compiles and writes the user cache"
    second = _probe(env, tmp_path)
    assert second["misses"] == 0 and second["hits"] >= 1, "the second run loads the kernel from the cache"


@pytest.mark.slow
def test_a_read_only_install_caches_outside_the_package(tmp_path):
    """pip installs a copy of the package; made read-only, it runs, caches in the user folder and stays clean."""
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                    "--target", str(target), str(ROOT)], check=True, timeout=300, capture_output=True)
    package = target / "valve_emulator"
    before = sorted(p.relative_to(target) for p in package.rglob("*"))
    for p in [package, *package.rglob("*")]:
        p.chmod(p.stat().st_mode & ~0o222)
    try:
        env = _env(tmp_path, PYTHONPATH=str(target))
        first = _probe(env, tmp_path)
        assert Path(first["package"]).resolve().is_relative_to(target.resolve())
        second = _probe(env, tmp_path)
        assert second["misses"] == 0 and second["hits"] >= 1
        after = sorted(p.relative_to(target) for p in package.rglob("*") if p.suffix in (".nbi", ".nbc"))
        assert after == [], f"compiled code written into the installed package: {after[:3]}"
        assert sorted(p.relative_to(target) for p in package.rglob("*")
                      if "__pycache__" not in p.parts) == [p for p in before if "__pycache__" not in p.parts]
    finally:
        for p in [package, *package.rglob("*")]:
            p.chmod(p.stat().st_mode | 0o200)
        shutil.rmtree(target, ignore_errors=True)


# Runs what a user runs first — simulate a loop, diagnose the recording with and without a model, tick a device
# (a quiet run of ticks and a single one) —
# and counts the kernels that had to be compiled (cache misses) and loaded (hits) across the whole package.
FIRST_USE = """
import json, sys
from valve_emulator.cli import main
from valve_emulator.device.runtime import load_server_or_default
from valve_emulator.commands.compile import kernel_cache_stats
from valve_emulator.device.tick import Device

table1 = sys.argv[1]
assert main(["simulate", table1 + "/level_overshoot.yaml", "--out", "rec.csv", "--duration", "900"]) == 0
assert main(["diagnose", "rec.csv", "--json", "plant.json"]) == 0
assert main(["diagnose", "rec.csv", "--model", table1 + "/level_no_stiction.yaml", "--json", "m.json"]) == 0
device = Device.from_config(load_server_or_default(None), time_scale=0.0)
device.advance(5)
device.advance(1)   # one tick on its own, as a lockstep step = 1 runs it
stats = kernel_cache_stats()
print(json.dumps({"hits": sum(h for h, _ in stats.values()),
                  "misses": {name: m for name, (_, m) in stats.items() if m}}))
"""


@pytest.mark.slow
def test_compile_ahead_leaves_nothing_for_the_first_simulate_diagnose_and_serve_to_compile(tmp_path):
    env = _env(tmp_path)
    ahead = subprocess.run([sys.executable, "-m", "valve_emulator", "compile"], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=600)
    assert ahead.returncode == 0, ahead.stderr
    cache = tmp_path / "xdg" / "valve_emulator" / "numba"
    compiled = re.search(r"compiled (\d+) kernel\(s\) of diagnose, simulate, serve in .* s into "
                         + re.escape(str(cache)), ahead.stdout)
    assert compiled and int(compiled.group(1)) >= 10 and list(cache.rglob("*.nbi")), ahead.stdout
    out = subprocess.run([sys.executable, "-c", FIRST_USE, str(ROOT / "configs" / "table1")], env=env,
                         cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    assert counts["misses"] == {}, f"compiled on first use although compiled ahead: {counts['misses']}"
    assert counts["hits"] >= 8, "the first use ran the cached kernels"
    again = subprocess.run([sys.executable, "-m", "valve_emulator", "compile"], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=600)
    assert again.stdout.startswith("nothing to compile: the kernels of diagnose, simulate, serve were already in"), \
        again.stdout
