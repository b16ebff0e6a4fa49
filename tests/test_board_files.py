"""The board's files as docs/runtime.md gives them (the udev rule, the systemd unit, the log
rotation): their syntax, the paths they share, and that the unit starts a tactile-run command
line its parser accepts, with the exit codes it must not restart on. udev and systemd cannot run
in the tests (nor in the emulated board's chroot), so this is what is checked of them."""

from __future__ import annotations

import configparser
import re
import shlex

import pytest
from conftest import REPO

from tactile.cli import EXIT_CONTRACT, EXIT_USAGE
from tactile.runtime.commands.run import build_parser

DOC = (REPO / "docs" / "runtime.md").read_text()


def block(lang: str, contains: str) -> str:
    """The fenced block of ``lang`` (may be empty) that holds ``contains``."""
    for m in re.finditer(r"^```(\w*)\n(.*?)^```", DOC, re.S | re.M):
        if m[1] == lang and contains in m[2]:
            return m[2]
    raise AssertionError(f"no ```{lang} block with {contains!r} in docs/runtime.md")


def unit() -> configparser.ConfigParser:
    u = configparser.ConfigParser(strict=True, interpolation=None)
    u.optionxform = str  # systemd's keys are case-sensitive
    u.read_string(block("ini", "ExecStart="))
    return u


def test_the_udev_rule_names_the_pen_and_keeps_modemmanager_away():
    rule = block("", 'SUBSYSTEM=="tty"').strip()
    assert "\n" not in rule  # one rule, one line
    pairs = re.findall(r'(\w+(?:\{\w+\})?)(==|\+=|=)"([^"]*)"', rule)
    assert ", ".join(f'{k}{op}"{v}"' for k, op, v in pairs) == rule  # nothing else on the line
    keys = {k: (op, v) for k, op, v in pairs}
    assert keys["SUBSYSTEM"] == ("==", "tty")
    assert re.fullmatch(r"[0-9a-f]{4}", keys["ATTRS{idVendor}"][1])
    assert re.fullmatch(r"[0-9a-f]{4}", keys["ATTRS{idProduct}"][1])
    assert keys["SYMLINK"] == ("+=", "tactile-pen")
    assert keys["ENV{ID_MM_DEVICE_IGNORE}"] == ("=", "1")
    assert keys["GROUP"] == ("=", "dialout") and keys["MODE"] == ("=", "0660")


def test_the_unit_starts_a_command_line_tactile_run_accepts():
    u = unit()
    assert set(u.sections()) == {"Unit", "Service", "Install"}
    argv = shlex.split(u["Service"]["ExecStart"])
    assert argv[0] == "/opt/tactile/bin/tactile-run"
    args = build_parser().parse_args(argv[1:])  # exits 1 on an option the parser refuses
    assert args.port == "/dev/tactile-pen"  # the udev rule's SYMLINK
    assert str(args.model) == "/opt/tactile/model.onnx"  # where the set-up commands copy it
    assert args.wait  # started before the pen is plugged in
    # the unit waits for the device the udev rule makes (systemd escapes '-' as \x2d)
    assert u["Unit"]["After"] == r"dev-tactile\x2dpen.device"
    assert u["Install"]["WantedBy"] == "multi-user.target"


def test_the_unit_restarts_on_failure_but_not_on_what_restarting_cannot_fix():
    s = unit()["Service"]
    assert s["Restart"] == "on-failure" and int(s["RestartSec"]) > 0
    assert {int(c) for c in s["RestartPreventExitStatus"].split()} == {EXIT_USAGE, EXIT_CONTRACT}
    assert unit()["Unit"]["StartLimitIntervalSec"] == "0"
    assert s["User"] == "tactile" and s["Group"] == "dialout"
    log = s["StandardOutput"]
    assert log == "append:/var/log/tactile/labels.jsonl"
    setup = block("sh", "useradd")
    assert "--groups dialout tactile" in setup and "install -d -o tactile -g tactile " \
        "/var/log/tactile" in setup and "/opt/tactile/model.onnx" in setup


def test_the_log_rotation_is_for_the_units_file():
    rot = block("", "copytruncate")
    path, body = rot.split("{", 1)
    assert path.strip() == unit()["Service"]["StandardOutput"].split(":", 1)[1]
    words = [ln.split()[0] for ln in body.strip().rstrip("}").splitlines() if ln.strip()]
    assert "copytruncate" in words  # the service keeps the file open
    assert set(words) <= {"daily", "maxsize", "rotate", "compress", "missingok", "notifempty",
                          "copytruncate"}


@pytest.mark.parametrize("code", [EXIT_USAGE, EXIT_CONTRACT])
def test_the_exit_codes_the_unit_names_are_the_readmes(code):
    readme = (REPO / "README.md").read_text()
    assert f"`{code}`" in readme
