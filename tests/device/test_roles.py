"""The permission table: built-in and custom roles, the config's device.roles section, the codec's role check,
the rate-limited refusal log, and ``certs --modbus-role``."""

import logging

import pytest

from valve_emulator.cli import main
from valve_emulator.config import ConfigError, load_server
from valve_emulator.config.roles import WRITABLE_TAGS
from valve_emulator.device.guard import RefusalLog
from valve_emulator.device.registers import (
    CLOCK_REGISTERS,
    REGISTERS,
    UNIT_REGISTERS,
    R,
    RegisterAccessError,
    address_of,
    decode_write,
)
from valve_emulator.device.roles import (
    DEFAULT_ROLES,
    INSTRUCTOR,
    OPERATOR,
    UNAUTHENTICATED,
    VIEWER,
    RoleTable,
    tag_of,
)

LOOP = """\
plant:
  fopdt: {gain: 1.0, tau: 5.0, delay: 1.0}
controller: {kc: 0.5, ti: 10.0}
device:
  unit: 1
  roles:
    tuner: [kc, ti, td]
    %s
"""


def _writable(role, scaling):
    """The registers ``role`` may write on a loop with a controller in manual (a write of a valid word each)."""
    out = set()
    for reg in REGISTERS:
        if reg.access is R:
            continue
        lo, _ = reg.write
        try:
            decode_write(reg.address, [lo & 0xFFFF], scaling, 0, role=role)
        except RegisterAccessError:
            continue
        out.add(reg.name)
    return out


@pytest.fixture(scope="module")
def scaling():
    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.tick import Device

    config = server_from_mapping({"plant": {"fopdt": {"gain": 1.0, "tau": 5.0, "delay": 1.0}},
                                  "controller": {"kc": 0.5, "ti": 10.0}})
    return Device.from_config(config, time_scale=0).scaling


def test_the_built_in_roles_write_nothing_op_sp_mode_and_everything(scaling):
    assert _writable(VIEWER, scaling) == set()
    assert _writable(OPERATOR, scaling) == {"op_pct", "op_ma", "sp", "mode"}
    assert _writable(INSTRUCTOR, scaling) == {r.name for r in REGISTERS if r.access is not R}
    assert DEFAULT_ROLES.names == ("viewer", "operator", "instructor")


def test_a_client_without_credentials_writes_what_it_always_did(scaling):
    """The plain port's role: every writable register but the instructor ones, same as a write without a role."""
    assert _writable(UNAUTHENTICATED, scaling) == _writable(None, scaling) == {
        "op_pct", "op_ma", "sp", "mode", "kc", "ti", "td"}
    assert "step" in UNAUTHENTICATED.tags and "S" not in UNAUTHENTICATED.tags


def test_a_custom_role_writes_exactly_its_tags(scaling):
    tuner = RoleTable.of([("tuner", ("kc", "ti", "td"))]).get("tuner")
    assert _writable(tuner, scaling) == {"kc", "ti", "td"}
    with pytest.raises(RegisterAccessError, match="register sp .* not writable by role 'tuner'"):
        decode_write(address_of("sp"), [5000], scaling, 0, role=tuner)


def test_the_tags_are_the_register_maps_writable_quantities():
    registers = (*REGISTERS, *UNIT_REGISTERS, *CLOCK_REGISTERS)
    assert {tag_of(r.quantity) for r in registers if r.access is not R} == set(WRITABLE_TAGS)
    assert tag_of("auto") == "mode" and tag_of("op") == "op"


def test_device_roles_are_loaded_from_the_config(tmp_path):
    path = tmp_path / "loop.yaml"
    path.write_text(LOOP % "setter: [sp]")
    table = RoleTable.from_config(load_server(path))
    assert table.names == ("viewer", "operator", "instructor", "tuner", "setter")
    assert table.get("setter").tags == {"sp"} and table.get("readonly") is None


@pytest.mark.parametrize(("line", "key", "message"), [
    ("setter: [sp, pv]", "device.roles.setter[1]", "'pv' is not a writable tag"),
    ("setter: [sp, sp]", "device.roles.setter[1]", "listed twice"),
    ("operator: [op]", "device.roles.operator", "built-in role"),
    ("setter: sp", "device.roles.setter", "must be a list"),
    ("'a b': [sp]", "device.roles.a b", "plain word"),
])
def test_a_bad_roles_section_names_the_file_line_and_key(tmp_path, line, key, message):
    path = tmp_path / "loop.yaml"
    path.write_text(LOOP % line)
    with pytest.raises(ConfigError) as err:
        load_server(path)
    text = str(err.value)
    assert text.startswith(f"{path}:") and key in text and message in text
    assert err.value.line in (7, 8)   # the role's line (its list item's, where YAML gives one)


def test_refusals_are_logged_once_per_client_and_cause_per_interval(caplog):
    """A flood of 10,000 refusals over 60 s from one client for one cause: one line per 10 s interval, each
    saying how many were not logged; another cause or client has lines of its own."""
    caplog.set_level(logging.DEBUG, logger="test.refusals")
    now = [0.0]
    log = RefusalLog(logging.getLogger("test.refusals"), interval=10.0, clock=lambda: now[0])
    for k in range(10_000):
        now[0] = k * 0.006
        log.note("10.0.0.1", ("op_pct", 2), "refused %s", k)
    log.note("10.0.0.1", ("S", 2), "refused S")
    log.note("10.0.0.2", ("op_pct", 2), "refused from another client")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 6 + 2 and log.refused == 10_002
    assert "more like this in the last 10 s were not logged" in lines[1]
    suppressed = sum(int(line.split("; ")[1].split()[0]) for line in lines[1:6])
    assert suppressed + 6 <= 10_000


def test_the_refusal_log_is_bounded(caplog):
    caplog.set_level(logging.DEBUG, logger="test.bounded")
    log = RefusalLog(logging.getLogger("test.bounded"), capacity=3, clock=lambda: 0.0)
    for i in range(10):
        log.note(f"10.0.0.{i}", "S", "refused %s", i)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 4 and "holds 3" in warnings[-1]


def test_certs_refuses_a_role_outside_the_table_and_writes_nothing(tmp_path, capsys):
    assert main(["certs", "--modbus", str(tmp_path / "pki"), "--modbus-role", "readonly"]) == 2
    err = capsys.readouterr().err
    assert "--modbus-role 'readonly'" in err and "viewer, operator, instructor" in err
    assert not (tmp_path / "pki").exists()


def test_certs_makes_a_custom_role_defined_in_the_config(tmp_path, capsys):
    config = tmp_path / "loop.yaml"
    config.write_text(LOOP % "setter: [sp]")
    assert main(["certs", "--modbus", str(tmp_path / "pki"), "--modbus-role", "tuner", "--modbus-role",
                 "viewer", "--config", str(config)]) == 0
    assert (tmp_path / "pki" / "client-tuner.pem").is_file() and (tmp_path / "pki" / "client-viewer.pem").is_file()
    assert main(["certs", "--modbus", str(tmp_path / "pki2"), "--modbus-role", "tuner"]) == 2
    assert "needs --config" in capsys.readouterr().err
