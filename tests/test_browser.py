"""The live page in a real browser: ``tactile-run --serve`` on a simulated pen whose link drops
frames and is unplugged once, read by headless Chromium (Debian's ``chromium``), checked from the
page's DOM against what tactile-run printed on stdout.

The browser is installed by the fixture when it is missing (``apt-get install chromium``, as
root); without root or apt, or when the install fails (no package registry reachable), the test
is skipped, saying so; under CI (``CI`` set) a failed install fails the test.
``TACTILE_SCREENSHOT=docs/live.png`` also saves the screenshot there (the one the README shows).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from browser import Browser, find_chromium
from conftest import REPO

MODEL = REPO / "models" / "pen-exp2.onnx"
PEN = "sim://?texture=paper&seed=2&drop=0.003&unplug=4:1"  # gaps, and one unplug
STATE = """JSON.stringify({
  state: document.body.dataset.state,
  label: document.getElementById("label").textContent,
  seq: document.getElementById("label").dataset.seq,
  p: document.getElementById("label").dataset.p,
  bars: document.querySelectorAll("#probs .row").length,
  samples: +document.getElementById("samples").textContent,
  breaks: +(document.getElementById("samples").dataset.breaks || 0),
  gaps: +document.getElementById("gaps").textContent,
  reconnects: +document.getElementById("reconnects").textContent,
  events: [...document.querySelectorAll("#events li")].map((li) => li.dataset.event),
  overflow: document.documentElement.scrollWidth > window.innerWidth,
})"""


def install_chromium(run=subprocess.run) -> str:
    """``apt-get update`` and ``apt-get install chromium`` (``run``: :func:`subprocess.run` or
    a stand-in), each with a time limit; skips (fails under CI) when either does not succeed."""
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd, limit in ((["apt-get", "update", "-q"], 300),
                       (["apt-get", "install", "-y", "-q", "-o", "DPkg::Lock::Timeout=600",
                         "chromium"], 900)):
        try:
            done = run(cmd, env=env, capture_output=True, text=True, timeout=limit)
            last = (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
            why = "" if done.returncode == 0 else f"failed: {last}"
        except subprocess.TimeoutExpired:
            why = f"did not finish in {limit} s"
        if why:
            (pytest.fail if os.environ.get("CI") else pytest.skip)(
                f"chromium is not installed and {' '.join(cmd)} {why}")
    exe = find_chromium()
    if not exe:
        pytest.fail("apt-get installed chromium, but no chromium is on PATH")
    return exe

# the page's own functions fed by hand (after the end): a gap, then samples whose seq jumps
PLOT = """(() => {
  const b = view.breaks;
  onHeader({device: "t", sample_rate_hz: 10, every: 1, labels: false,
            channels: [{name: "a", unit: ""}]});
  onSamples({event: "samples", seq: 0, every: 1, values: [[1], [2]]});
  onSamples({event: "samples", seq: 2, every: 1, values: [[3]]});
  onEvent({event: "gap", seq: 3, missing: 7, reason: "drop"});
  onSamples({event: "samples", seq: 10, every: 1, values: [[4]]});
  const marks = view.marks.map((m) => ({at: m.at, cut: m.cut}));
  for (let i = 0; i < 300; i++) onSamples({event: "samples", seq: 11 + i, every: 1, values: [[i]]});
  return JSON.stringify({breaks: view.breaks - b, marks, after: view.marks.length,
                         points: view.points});
})()"""


@pytest.fixture(scope="session")
def chromium() -> str:
    """The system's Chromium, installed with apt-get when missing (root only)."""
    exe = find_chromium()
    if exe:
        return exe
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        pytest.skip("chromium is not installed, and installing it needs root and apt-get "
                    "(apt-get install chromium)")
    return install_chromium()


def test_a_failed_or_hung_install_skips_with_apts_message_outside_ci(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    limits = []

    def unreachable(cmd, timeout, **kw):
        limits.append(timeout)
        return subprocess.CompletedProcess(cmd, 100, "", "W: x\nE: Unable to fetch some archives")

    with pytest.raises(pytest.skip.Exception, match="apt-get update -q failed: E: Unable to "
                       "fetch some archives"):
        install_chromium(unreachable)

    def hung(cmd, timeout, **kw):
        limits.append(timeout)
        if cmd[1] == "install":
            raise subprocess.TimeoutExpired(cmd, timeout)
        return subprocess.CompletedProcess(cmd, 0, "", "")

    with pytest.raises(pytest.skip.Exception, match="install .* did not finish in 900 s"):
        install_chromium(hung)
    assert limits == [300, 300, 900]
    monkeypatch.setenv("CI", "true")  # there the registry is reachable: a failure is a failure
    with pytest.raises(pytest.fail.Exception, match="apt-get update -q failed"):
        install_chromium(unreachable)


class Lines:
    """Collects a pipe's lines in a thread (so that neither pipe of the child ever fills)."""

    def __init__(self, pipe) -> None:
        self.lines: list[str] = []
        self.thread = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self.thread.start()

    def _read(self, pipe) -> None:
        for line in pipe:
            self.lines.append(line)

    def find(self, pattern: str) -> re.Match | None:
        return next((m for m in map(re.compile(pattern).search, list(self.lines)) if m), None)


def save_small(png: Path, to: Path) -> None:
    """The screenshot in 64 colours (a third of the size), or as it is without Pillow."""
    try:
        from PIL import Image
    except ImportError:
        shutil.copyfile(png, to)
        return
    Image.open(png).convert("RGB").quantize(64, Image.Quantize.MEDIANCUT).save(to, optimize=True)


def poll(get, ok, what: str, limit: float = 120.0):
    """``get()`` until ``ok(value)``; the limit only turns a hang into a failure."""
    end = time.monotonic() + limit
    while True:
        value = get()
        if ok(value):
            return value
        if time.monotonic() > end:
            pytest.fail(f"never happened: {what}; last seen {value}")
        time.sleep(0.2)


def test_the_page_shows_stdouts_last_label_the_samples_a_gap_and_a_reconnect(
        chromium, tmp_path, reap):
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.run", "--model", str(MODEL), "--port", PEN,
         "--serve", "127.0.0.1:0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 300)
    out, err = Lines(proc.stdout), Lines(proc.stderr)
    url = poll(lambda: err.find(r"live page at (http://127\.0\.0\.1:\d+/)"), bool,
               "tactile-run said where its page is", 60)[1]
    with Browser(chromium, tmp_path / "profile") as browser:
        browser.open(url)
        state = lambda: json.loads(browser.evaluate(STATE))  # noqa: E731
        # 250 samples plotted (at 25 a second): the plots are full for the screenshot
        seen = poll(state, lambda s: s["samples"] >= 250 and s["seq"] and s["gaps"] >= 1
                    and s["reconnects"] >= 1, "the page showed samples, a label, a gap and a "
                    "reconnect")
        assert seen["state"] == "live" and seen["bars"] == 5 and not seen["overflow"]
        shot = browser.screenshot(tmp_path / "live.png")
        assert shot[:8] == b"\x89PNG\r\n\x1a\n" and len(shot) > 10_000
        if os.environ.get("TACTILE_SCREENSHOT"):
            save_small(tmp_path / "live.png", Path(os.environ["TACTILE_SCREENSHOT"]))
        proc.send_signal(signal.SIGINT)  # tactile-run sends the rest, then `end`, then exits
        assert proc.wait(60) == 0
        out.thread.join(10)
        err.thread.join(10)
        final = poll(state, lambda s: s["state"] == "ended", "the page received the end")
        # a phone's width: one column, nothing wider than the screen
        browser.call("Emulation.setDeviceMetricsOverride",
                     {"width": 390, "height": 844, "deviceScaleFactor": 1, "mobile": True})
        phone = state()
        plot = json.loads(browser.evaluate(PLOT))
    # samples missing (seq 3..9): one break, the gap's mark merged into it; pruned off the span
    assert plot == {"breaks": 1, "marks": [{"at": 3, "cut": True}], "after": 0, "points": 100}
    printed = [json.loads(line) for line in out.lines]
    labels = [o for o in printed if "label" in o]
    events = [o.get("event") for o in printed if "event" in o]
    assert labels and final["seq"] == str(labels[-1]["seq"])  # the page shows stdout's last
    assert final["label"] == labels[-1]["label"] and float(final["p"]) == labels[-1]["p"]
    assert final["gaps"] == events.count("gap") >= 1  # the status matches stdout's events
    assert final["reconnects"] == events.count("reconnect") == 1
    assert "gap" in final["events"] or "reconnect" in final["events"]
    assert final["samples"] > 0 and not phone["overflow"]
    summary = json.loads("".join(err.lines).split("tactile-run: summary ", 1)[1])
    assert summary["gaps"] == final["gaps"] and summary["reconnects"] == 1
    # how many messages a starved browser missed depends on speed: only that it was counted
    assert err.find(r"live page: viewers 1 served, 0 refused; \d+ messages dropped")
