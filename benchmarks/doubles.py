"""`bench doubles`: what the vendors' packages cost per sample, on their test doubles.

The PI backend (pipython's GCSDevice over its own PISocket) and the NV200 backend
(piezosystem jena's nv200 package, two telnet connections) each drive the checkout's
TEST DOUBLE of their controller (test/hardware_double/), started in a process of its
own as a controller has its own processor, over loopback TCP: the set-up, a streamed
step (the command and the position read back), and a waveform played on the
controller's generator and read back from its recorder. Every figure is the double's
and this host's, never a real controller's; the baseline is a bare TCP round trip to
an echo server on the same host, measured in the same invocation. Needs a checkout
(the doubles are test code, not installed).
"""

from __future__ import annotations

import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from benchmarks import ROOT

STEPS = 2000          # streamed PI steps timed
NV_STEPS = 100        # streamed NV200 samples timed (each ~20 ms)
FS = 5000.0           # the played waveform's rate [Hz]


def _double(script: str, tmp: str) -> tuple[subprocess.Popen, str]:
    """Start the double ``script``: the process and its first line (its address). At
    SCHED_FIFO 60 as the tests run it (a controller's firmware is not starved by the
    host's load), or at normal priority where the host does not allow that."""
    folder = os.path.join(ROOT, "test", "hardware_double")
    for priority in ("60", "0"):
        proc = subprocess.Popen(
            [sys.executable, os.path.join(folder, script), "--state",
             os.path.join(tmp, script + ".json"), "--priority", priority],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            env=dict(os.environ, PYTHONPATH=os.pathsep.join([folder, ROOT])))
        assert proc.stdout is not None
        address = proc.stdout.readline().strip()
        if address:
            return proc, address
        proc.wait(10)
    raise RuntimeError(f"{script} did not start")


def _end(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


def _echo_round_trip_ms(n: int = STEPS) -> list[float]:
    """A bare TCP round trip on loopback (one line out, one back), n times [ms]."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)

    def serve():
        c, _ = srv.accept()
        with c:
            while True:
                d = c.recv(256)
                if not d:
                    return
                c.sendall(d)
    th = threading.Thread(target=serve, daemon=True)
    th.start()
    cl = socket.create_connection(srv.getsockname())
    cl.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    out = []
    try:
        for _ in range(n):
            t0 = time.perf_counter()
            cl.sendall(b"POS? 1 2\n")
            cl.recv(256)
            out.append((time.perf_counter() - t0) * 1e3)
    finally:
        cl.close()
        srv.close()
    return out


def _steps_ms(b, n: int) -> list[float]:
    out = []
    for k in range(n):
        v = 30.0 + 10.0 * np.sin(2 * np.pi * k / 200)
        t0 = time.perf_counter()
        b.step(v, v)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def _measure(rep, tmp: str, script: str, steps: int, n: int, backend) -> tuple:
    """The double ``script`` started, ``backend(address)`` set up on it, ``steps``
    streamed steps and ``n`` points played at FS: (set-up s, step times ms, n, play s)."""
    proc, address = _double(script, tmp)
    try:
        t0 = time.perf_counter()
        b = backend(address)
        b.start()
        setup = time.perf_counter() - t0
        rep.progress(f"{script} at {address}: set up in {setup:.2f} s")
        st = _steps_ms(b, steps)
        t = np.arange(n) / FS
        vx = 60 - 50 * np.cos(2 * np.pi * 20 * t)
        t0 = time.perf_counter()
        b.play(vx, vx.copy(), FS, 1e5)
        played = time.perf_counter() - t0
        b.close(0.0, 1e5)
    finally:
        _end(proc)
    return setup, st, n, played


def _p(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q))


def bench_doubles(rep) -> int:
    """The vendor backends on their doubles (``rep``: the report)."""
    from piezo_stage.core.params import defaults
    from piezo_stage.drivers import BACKEND_PARAMS
    if not os.path.isdir(os.path.join(ROOT, "test", "hardware_double")):
        rep.fail("the doubles are test code: run it from a checkout")
        return 2
    params = defaults(BACKEND_PARAMS)
    rep.title("the vendors' packages on the checkout's test doubles (each in its own "
              "process), loopback TCP; every figure the double's and this host's")
    echo = _echo_round_trip_ms()
    rows = [("bare TCP round trip (echo server, the baseline)", "",
             f"{statistics.median(echo):.3f}", f"{_p(echo, 99):.3f}", "1.0")]
    base = statistics.median(echo)
    tmp = tempfile.mkdtemp(prefix="bench_doubles_")
    figures = []
    try:
        from piezo_stage.drivers.nv200 import Nv200Backend
        from piezo_stage.drivers.pi import PiBackend
        pi = _measure(rep, tmp, "pi_controller_double.py", STEPS, 20_000, lambda a: PiBackend(
            1000.0, {**params, "pi_address": a}, safe_V=0.0))
        nv = _measure(rep, tmp, "nv200_double.py", NV_STEPS, 1024, lambda a: Nv200Backend(
            50.0, {**params, "nv200_addresses": a.split(",")}, 0.0))
        for (setup, st, n, played), what, per, play in (
                (pi, "PI E-727 double: streamed step (SVA + POS?)", "PI: streamed steps",
                 "ramps included"),
                (nv, "NV200 double x 2: streamed sample (both set + meas, concurrently)",
                 "NV200: streamed samples", "nearly all of it the table upload")):
            med = statistics.median(st)
            rows.append((what, f"{setup:.2f} s", f"{med:.3f}", f"{_p(st, 99):.3f}",
                         f"{med / base:.1f}"))
            figures += [(f"{per} a second (1 / median)", f"{1e3 / med:,.0f}"),
                        (f"{per.split(':')[0]}: play {n:,} points at {FS:g} Hz "
                         f"({n / FS:.1f} s)", f"{played:.2f} s wall, {play}")]
        pi_med, nv_med = statistics.median(pi[1]), statistics.median(nv[1])
    except Exception as e:  # the report says what failed, in one line
        rep.fail(f"{type(e).__name__}: {e}")
        return 1
    finally:
        import shutil
        shutil.rmtree(tmp, ignore_errors=True)
    rep.table(("what", "set-up", "median ms", "p99 ms", "x the bare round trip"), rows,
              f"{STEPS} PI steps, {NV_STEPS} NV200 samples, a sine of 20-40 V")
    rep.figures(figures)
    rep.target(f"a PI step takes under half a 1 kHz period (median {pi_med:.3f} ms)",
               pi_med < 0.5)
    rep.target(f"an NV200 sample fits a 25 Hz period, the rate the tests run the set at "
               f"(median {nv_med:.1f} ms)", nv_med < 40.0)
    return 0
