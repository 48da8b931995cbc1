"""The instructor station in a real browser: Debian's chromium driven by Selenium through the system
chromedriver, against ``valve-emulator serve --web 0`` in its own process."""

import json
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import yaml
from required import need

CHROMEDRIVER = "/usr/bin/chromedriver"
CONFIG = {"device": {"tick": 0.1, "instructor_writes": True}, "loops": [
    {"unit": 1, "name": "FIC101", "valve": {"model": "kano", "S": 5.0, "J": 2.0},
     "plant": {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0, "pv_range": [-10.0, 10.0], "units": "kg/m3"},
     "controller": {"kc": 0.2, "ti": 10.0, "sp": 0.0}},
    {"unit": 2, "name": "TIC102", "valve": {"model": "kano", "S": 3.0, "J": 1.0},
     "plant": {"num": [2.0], "den": [20.0, 1.0], "delay": 5.0, "pv_range": [0.0, 100.0], "pv0": 50.0, "units": "degC"},
     "controller": {"kc": 0.5, "ti": 20.0, "sp": 50.0}},
]}


def _browser_or_fail():
    need(None if os.path.exists(CHROMEDRIVER) and shutil.which("chromium") else
         "chromium / chromium-driver not installed (apt-get install chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver")
    opts = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-dev-shm-usage", "--window-size=1500,900", "--disable-extensions",
                "--disable-component-update", "--no-first-run"):
        opts.add_argument(arg)
    return webdriver.Chrome(service=webdriver.ChromeService(executable_path=CHROMEDRIVER), options=opts)


@pytest.fixture
def station(tmp_path):
    """A served device with the station: (modbus port, web URL)."""
    cfg = tmp_path / "plant.yaml"
    cfg.write_text(yaml.safe_dump(CONFIG))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", str(cfg), "--port", "0", "--web", "0",
                             "--time-scale", "2", "--snapshots", str(tmp_path / "snaps")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    port = url = None
    deadline = time.monotonic() + 60
    while (port is None or url is None) and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        if m := re.search(r"listening on 127\.0\.0\.1:(\d+)", line):
            port = int(m.group(1))
        if m := re.search(r"instructor station at (http://\S+/) ", line):
            url = m.group(1)
    assert port and url, "the server did not print its Modbus port and station URL"
    yield port, url
    proc.terminate()
    proc.wait(timeout=10)


def _read_op_pct(port, unit):
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    assert client.connect()
    try:
        rr = client.read_holding_registers(0, count=1, device_id=unit)
        assert not rr.isError(), rr
        return rr.registers[0]
    finally:
        client.close()


def _wait(predicate, timeout=10.0, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_trainee_and_instructor_in_a_real_browser(station, tmp_path):
    port, url = station
    shots = Path(os.environ.get("STATION_SCREENSHOTS", tmp_path))
    driver = _browser_or_fail()
    try:
        from selenium.webdriver.common.by import By

        # --- trainee: manual, set OP; the Modbus register follows --------------------------------------------
        driver.get(url)
        _wait(lambda: driver.find_element(By.ID, "mode").text == "AUTO", what="the faceplate to show AUTO")
        driver.find_element(By.ID, "btn-manual").click()
        _wait(lambda: driver.find_element(By.ID, "mode").text == "MANUAL", what="manual mode")
        box = driver.find_element(By.ID, "op-input")
        box.clear()
        box.send_keys("35")
        driver.find_element(By.ID, "op-set").click()
        _wait(lambda: _read_op_pct(port, 1) == 3500, what="the op_pct register to read 3500")
        # OP beyond the range: the register map's message appears on the page
        box.clear()
        box.send_keys("150")
        driver.find_element(By.ID, "op-set").click()
        _wait(lambda: "out of range" in driver.find_element(By.ID, "msg").text, what="the refusal message")
        assert _read_op_pct(port, 1) == 3500
        # the trainee page shows no MV and no stiction parameters, and neither does its view of the API
        assert driver.find_element(By.ID, "mv-legend").get_attribute("hidden") is not None
        trainee = json.loads(urllib.request.urlopen(url + "api/state?view=trainee").read())["loops"][0]
        assert "S" not in trainee and "mv" not in trainee
        _wait(lambda: len(driver.execute_script("return window.stationTrend()")) > 20, what="trend samples")

        # --- instructor: a sensor drift on the trainee's loop -----------------------------------------------------
        # A second window, opened and loaded through the driver (get waits for the page): switching to a window that a
        # script opened can meet it still navigating ("aborted by navigation", Chromium 156, 2026-11-28).
        trainee_window = driver.current_window_handle
        driver.switch_to.new_window("window")
        driver.get(url + "instructor")
        _wait(lambda: driver.find_element(By.ID, "mode").text == "MANUAL", what="the instructor faceplate")
        from selenium.webdriver.support.ui import Select

        Select(driver.find_element(By.ID, "mf-kind")).select_by_value("sensor_drift")
        driver.find_element(By.ID, "mf-bias").send_keys("4")
        driver.find_element(By.ID, "mf-inject").click()
        _wait(lambda: "injected" in driver.find_element(By.ID, "msg").text, what="the injection")
        driver.find_element(By.ID, "snap-name").send_keys("after-drift")
        driver.find_element(By.ID, "snap-save").click()
        _wait(lambda: "after-drift" in driver.find_element(By.ID, "snap-list").text, what="the snapshot list")
        time.sleep(2.0)
        driver.save_screenshot(str(shots / "station-instructor.png"))

        # --- back on the trainee page: the trend shows the drift ---------------------------------------------------
        driver.switch_to.window(trainee_window)
        def jumped():
            pv = [p["pv"] for p in driver.execute_script("return window.stationTrend()")]
            return len(pv) > 10 and max(pv) - pv[0] > 3.5
        _wait(jumped, what="the trainee trend to show the +4 drift")
        time.sleep(1.0)
        driver.save_screenshot(str(shots / "station-trainee.png"))
    finally:
        driver.quit()
    for name in ("station-trainee.png", "station-instructor.png"):
        assert (shots / name).stat().st_size > 10_000
