"""A node whose stop hangs (the middleware's teardown once held a controller past the
launcher's grace) prints every thread's stack and exits 1 within its watch: the real
``piezo_stage.process.signals`` in a real process, held in a sleep as a hung call
would hold it. The middleware's part of a teardown is bounded apart: a hang there, even
one that holds the GIL in native code, ends the process with the code of its stop."""

import os
import signal
import subprocess
import sys
import time

HUNG = """
import piezo_stage.process.signals as s
s.set_phase("running", "/stage/hung")
s.STATE.watch_s = {watch}
print("ready", flush=True)
import time
while True:
    time.sleep(0.01 if s.requested() is None else 3600)  # the stop, then a hang
"""


def _hung(watch_s: float):
    p = subprocess.Popen([sys.executable, "-c", HUNG.format(watch=watch_s)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=dict(os.environ, PYTHONFAULTHANDLER=""))
    assert p.stdout.readline().strip() == "ready"
    return p


def test_a_stop_that_hangs_prints_the_stacks_and_ends_within_its_watch():
    p = _hung(1.0)
    t0 = time.monotonic()
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=10)
    took = time.monotonic() - t0
    assert p.returncode == 1
    assert 0.9 <= took < 5.0, took
    assert "Timeout" in err and "<module>" in err, err  # where it hung


def test_a_node_that_stops_in_time_is_not_touched_by_its_watch():
    code = """
import piezo_stage.process.signals as s, time
s.set_phase("running", "/stage/quick")
s.STATE.watch_s = 1.0
print("ready", flush=True)
while s.requested() is None:
    time.sleep(0.01)
s.set_phase("stopping")
s.watch()          # teardown: already armed by the signal, stays armed
time.sleep(0.3)    # a teardown well within the watch
raise SystemExit(130)
"""
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=10)
    assert p.returncode == 130 and "Timeout" not in err, err


TEARDOWN = """
import re, time
import piezo_stage.process.signals as s
s.set_phase("stopping", "/stage/probe")
with s.bounded_teardown(130, 0.5):
    {block}
time.sleep(1.0)  # past the bound: the timers were cancelled with the block
print("after", flush=True)
"""


def _teardown(block: str):
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", TEARDOWN.format(block=block)],
                       capture_output=True, text=True, timeout=30)
    return p, time.monotonic() - t0


def test_a_middleware_teardown_that_hangs_holding_the_gil_ends_with_its_stop_code():
    # a regular expression that backtracks for ever: native code holding the GIL, as
    # rclpy's destroy_node does while Fast DDS hangs (no Python thread could run)
    p, took = _teardown('re.match(r"(a+)+$", "a" * 40 + "b")')
    assert p.returncode == 130, (p.returncode, p.stderr)
    assert "after" not in p.stdout
    lines = [ln for ln in p.stderr.splitlines() if "teardown did not end" in ln]
    assert len(lines) == 1 and "/stage/probe" in lines[0] and "(130)" in lines[0], p.stderr
    assert "Timeout" in p.stderr  # and the stacks, where it hung
    assert took < 5.0, took


def test_a_middleware_teardown_in_time_leaves_the_process_alone():
    p, _ = _teardown("time.sleep(0.1)")
    assert p.returncode == 0, p.stderr
    assert "after" in p.stdout and "Timeout" not in p.stderr and not p.stderr.strip()
