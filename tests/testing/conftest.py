"""Helpers of the testing kit's own tests: running pytest on a scratch project as a user would."""

from __future__ import annotations

import pytest
from kit_helpers import plugin_args


@pytest.fixture
def run_pytest(pytester):
    """``run_pytest(*args)``: pytest in a subprocess (as a user runs it: in-process runs would re-import the
    compiled kernels) inside pytester's scratch folder, with the kit's plugin."""
    def run(*args: str):
        return pytester.runpytest_subprocess(*plugin_args(), "-p", "no:cacheprovider", *args, timeout=300)
    return run


@pytest.fixture
def serve():
    """``with serve(*args) as port:`` runs ``valve-emulator serve --port 0 *args`` in a subprocess until the block
    ends (SIGINT, then a clean exit is required)."""
    import contextlib
    import re
    import signal
    import subprocess
    import sys

    @contextlib.contextmanager
    def run(*args: str):
        proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", "--port", "0", *args],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            line = proc.stdout.readline()
            m = re.search(r"listening on [\d.]+:(\d+),", line)
            assert m, line + proc.stderr.read()
            run.banner = line
            yield int(m.group(1))
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                code = proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                raise
            finally:
                proc.stdout.close()
                proc.stderr.close()
        assert code == 0, f"serve exited with status {code}"

    return run
