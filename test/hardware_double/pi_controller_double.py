"""TEST DOUBLE of a PI E-727 digital piezo controller (the hardware boundary; the only
kind of double the project allows).

Everything on the host side is PI's real ``pipython``: ``GCSDevice`` over pipython's
own ``PISocket`` gateway, through a real TCP connection. What is simulated is the
controller at the far end of the cable: ``PIControllerDouble`` is a TCP server on
127.0.0.1 that speaks the GCS 2 text protocol (one command per line, answers of one or
more lines, every line but the last ending in a space before the line feed; errors kept
until ``ERR?`` reads and clears them) and drives the project's simulated stage
(piezo_stage.core.model.plant) with its output voltages.

What it models, per axis 1 (x) and 2 (y), servo off (open loop, the stage driven by
the open-loop control value in volts) or on (refused: we never close PI's own loop):
``*IDN?``, ``CSV?``, ``ERR?``, ``SAI?``, ``SVO``/``SVO?``, ``SVA``/``SVA?``,
``POS?`` (the sensor, um), ``VOL?`` (the output voltage), ``SPA?`` of the servo update
time (0x0E000200) and ``HPA?`` (the parameter list), ``TNR?``; the wave generator
(``WAV ... PNT``, ``WSL``, ``WGC``, ``WTR``, ``WGO``/``WGO?``) and the data recorder
(``DRC``, ``RTR``, ``DRR?`` in GCS array format), recording starting with ``WGO``
as the E-727 does by default.
Any other command is not modelled: the double sets error 2 (unknown command), as a
controller does, *and* records it in ``unmodelled``; the tests fail on any entry
there, so a call we make that the double does not know fails loudly, naming it.

Time: the servo cycle is ``servo_s`` (100 us here: the plant's own rate; an E-727's is
50 us). With ``clock="wall"`` the stage advances with the wall clock between commands
(the streamed loop) and a wave takes its real duration; ``clock="virtual"`` completes
a wave at once (fast tests). ``wave_store_s``: the time a ``WAV`` command's points take
to store before the next line is read (a loaded host, or a controller writing its wave
table), so the ``ERR?`` after it answers that much later. ``after_record_s``: the time
the first ``SVA?`` after a ``DRR?`` waits (a host still busy with the record it sent). Faults on
demand: ``drop()``
closes every connection (a pulled cable), ``set_error(code)`` makes the next ``ERR?``
report a controller error.
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from piezo_stage.core.model.plant import Plant
from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config

AXES = ("1", "2")
SERVO_UPDATE_TIME = 0x0E000200
POSITION, VOLTAGE = 2, 7   # record options: actual position of axis, piezo voltage
IDN = "(c)2026 Physik Instrumente (PI) GmbH & Co. KG, E-727, 0000000000, 00.000 (double)"


class PIControllerDouble:
    """See the module docstring. ``address`` is what the backend's ``pi_address`` takes."""

    def __init__(self, plant_config: str = "", clock: str = "wall", servo_s: float = 1e-4,
                 recorder_points: int = 262144, seed: int | None = None,
                 gcs: str = "2.0000", wave_store_s: float = 0.0,
                 after_record_s: float = 0.0):
        cfg = load_plant_config(plant_config or default_plant_config_path())
        if seed is not None:
            cfg.seed = seed
        self.servo_s, self.clock, self.gcs = servo_s, clock, gcs
        self.wave_store_s = float(wave_store_s)
        self.after_record_s = float(after_record_s)
        self._busy_after_record = False
        self.plant = Plant(cfg, 1.0 / servo_s)
        self.recorder_points = recorder_points
        self.servo = {a: True for a in AXES}     # an E-727 starts in closed loop
        self.sva = {a: 0.0 for a in AXES}
        self.w = {a: 0.0 for a in AXES}
        self.err = 0
        self.unmodelled: list[str] = []
        self.commands: list[str] = []
        self.max_abs_V = 0.0
        self.waves: dict[int, np.ndarray] = {}
        self.wsl = {1: 1, 2: 2}
        self.wgc = {1: 1, 2: 1}
        self.wtr = {1: 1, 2: 1}
        self.rtr = 1
        self.drc = {t: ("0", 0) for t in range(1, 9)}
        self.records: dict[int, np.ndarray] = {}
        self.wave_until = 0.0
        self.t_last = time.monotonic()
        self.lock = threading.Lock()
        self.conns: list[socket.socket] = []
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.address = f"tcp:127.0.0.1:{self.port}"
        self.running = True
        threading.Thread(target=self._accept, daemon=True).start()

    # -- the link ------------------------------------------------------------------------
    def _accept(self):
        while self.running:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn):
        buf = b""
        while self.running:
            try:
                data = conn.recv(65536)
            except OSError:
                return
            if not data:
                return
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                if self._busy_after_record and line.startswith(b"SVA?"):
                    self._busy_after_record = False  # busy with the record: it waits
                    time.sleep(self.after_record_s)
                if self.after_record_s and line.startswith(b"DRR?"):
                    self._busy_after_record = True
                with self.lock:
                    answer = self.handle(line.decode("cp1252").strip())
                if self.wave_store_s and line.startswith(b"WAV"):
                    time.sleep(self.wave_store_s)  # storing the points: the next line waits
                if answer:
                    try:
                        conn.sendall(answer.encode("cp1252"))
                    except OSError:
                        return

    def drop(self):
        """A pulled cable: every connection closes; the outputs keep their last value
        (the E-727 has no host watchdog)."""
        for c in self.conns:
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            c.close()
        self.conns.clear()

    def set_error(self, code: int):
        with self.lock:
            self.err = code

    def close(self):
        self.running = False
        self.drop()
        self.server.close()

    # -- the stage -----------------------------------------------------------------------
    def _advance(self):
        """The stage up to now with the outputs held (wall clock)."""
        now = time.monotonic()
        n = int((now - self.t_last) / self.servo_s) if self.clock == "wall" else 1
        if n <= 0:
            return
        self.t_last += n * self.servo_s if self.clock == "wall" else 0.0
        n = min(n, 200_000)
        w = self.plant.run(np.full(n, self.sva["1"]), np.full(n, self.sva["2"]))
        self.w = {"1": float(w["x"][-1]), "2": float(w["y"][-1])}

    def _set_error(self, code):
        if not self.err:
            self.err = code

    @staticmethod
    def _answer(lines):
        return " \n".join(lines) + "\n"

    def _items(self, args, known=AXES):
        items = args or list(known)
        if any(i not in known for i in items):
            self._set_error(15)  # invalid axis identifier
            return None
        return items

    # -- the commands --------------------------------------------------------------------
    def handle(self, line: str) -> str:
        if not line:
            return ""
        self.commands.append(line)
        cmd, *args = line.split()
        fn = getattr(self, "cmd_" + cmd.replace("*", "").replace("?", "_q").upper(), None)
        if fn is None:
            self.unmodelled.append(line[:80])
            self._set_error(2)  # unknown command
            return ""
        try:
            return fn(args) or ""
        except (ValueError, IndexError, KeyError):
            self._set_error(1)  # parameter syntax
            return ""

    def cmd_IDN_Q(self, args):
        return IDN + "\n"

    def cmd_CSV_Q(self, args):
        return self.gcs + "\n"  # the GCS version (3.0000: what a GCS 3 controller says)

    def cmd_ERR_Q(self, args):
        err, self.err = self.err, 0
        return f"{err}\n"

    def cmd_SAI_Q(self, args):
        return self._answer(AXES)

    def cmd_TNR_Q(self, args):
        return f"{len(self.drc)}\n"

    def cmd_SVO(self, args):
        pairs = dict(zip(args[::2], args[1::2]))
        if self._items(list(pairs)) is not None:
            self._advance()
            self.servo.update({a: v == "1" for a, v in pairs.items()})

    def cmd_SVO_Q(self, args):
        items = self._items(args)
        return self._answer([f"{a}={int(self.servo[a])}" for a in items]) if items else ""

    def cmd_SVA(self, args):
        pairs = {a: float(v) for a, v in zip(args[::2], args[1::2])}
        if self._items(list(pairs)) is None:
            return
        if any(self.servo[a] for a in pairs):
            return self._set_error(79)  # open-loop value set when servo on
        if self._wave_running():
            return self._set_error(73)  # wave generator active
        self._advance()
        self.sva.update(pairs)
        self.max_abs_V = max(self.max_abs_V, *(abs(v) for v in pairs.values()))

    def cmd_SVA_Q(self, args):
        items = self._items(args)
        return self._answer([f"{a}={self.sva[a]:.6f}" for a in items]) if items else ""

    def cmd_POS_Q(self, args):
        items = self._items(args)
        if items:
            self._advance()
            return self._answer([f"{a}={self.w[a]:.6f}" for a in items])
        return ""

    def cmd_VOL_Q(self, args):
        items = self._items(args)
        return self._answer([f"{a}={self.sva[a]:.6f}" for a in items]) if items else ""

    def cmd_SPA_Q(self, args):
        item, param = args[0], int(args[1], 0)
        if param != SERVO_UPDATE_TIME or item not in AXES:
            return self._set_error(54)  # unknown parameter
        return f"{item} 0x{param:08X}={self.servo_s:.6e}\n"

    def cmd_HPA_Q(self, args):
        # the parameter list (pipython reads it to convert SPA? answers by type)
        return self._answer(["<PAR_INFO>", f"0x{SERVO_UPDATE_TIME:08X}=\t0\t1\tFLOAT\t"
                             "System\tServo Update Time [s]", "end of help"])

    # wave generator and data recorder
    def cmd_WAV(self, args):
        table, append, kind = int(args[0]), args[1], args[2]
        if kind != "PNT":
            self.unmodelled.append(f"WAV {kind}")
            return self._set_error(2)
        first, n = int(args[3]), int(args[4])
        pts = np.array([float(x) for x in args[5:5 + n]])
        if pts.size != n or first < 1:
            return self._set_error(1)
        old = self.waves.get(table, np.zeros(0)) if append == "&" else np.zeros(0)
        if first != old.size + 1:
            return self._set_error(17)  # a segment must follow the table's last point
        if old.size + n > self.recorder_points:
            return self._set_error(67)  # wave too large
        self.waves[table] = np.concatenate([old, pts])

    def cmd_WSL(self, args):
        self.wsl.update({int(g): int(t) for g, t in zip(args[::2], args[1::2])})

    def cmd_WGC(self, args):
        self.wgc.update({int(g): int(n) for g, n in zip(args[::2], args[1::2])})

    def cmd_WTR(self, args):
        for g, r, _interp in zip(args[::3], args[1::3], args[2::3]):
            self.wtr[int(g)] = int(r)

    def cmd_RTR(self, args):
        self.rtr = int(args[0])

    def cmd_DRC(self, args):
        for t, src, opt in zip(args[::3], args[1::3], args[2::3]):
            if int(t) not in self.drc or int(opt) not in (0, POSITION, VOLTAGE):
                self.unmodelled.append(f"DRC option {opt}")
                return self._set_error(17)
            self.drc[int(t)] = (src, int(opt))

    def _wave_running(self):
        return time.monotonic() < self.wave_until

    def cmd_WGO_Q(self, args):
        gens = [int(g) for g in args] or [1, 2]
        on = int(self._wave_running())
        return self._answer([f"{g}={on}" for g in gens])

    def cmd_WGO(self, args):
        modes = {int(g): int(m) for g, m in zip(args[::2], args[1::2])}
        if any(m not in (0, 1) for m in modes.values()):
            self.unmodelled.append(f"WGO mode {sorted(set(modes.values()))}")
            return self._set_error(17)
        gens = [g for g, m in modes.items() if m == 1]
        if not gens:
            self.wave_until = 0.0
            return
        if any(self.servo[str(g)] for g in gens):
            return self._set_error(79)
        if len({self.wtr[g] for g in gens}) != 1 or self.rtr < 1:
            return self._set_error(17)
        self._advance()
        # every generator runs its table (the axis's open-loop value) on the servo clock,
        # each point held for WTR servo cycles, WGC times; an axis not started holds
        rate = self.wtr[gens[0]]
        cycles = {g: np.tile(self.waves[self.wsl[g]], self.wgc[g]) for g in gens}
        n = max(c.size for c in cycles.values()) * rate
        v = {a: np.full(n, self.sva[a]) for a in AXES}
        for g, c in cycles.items():
            v[str(g)][:c.size * rate] = np.repeat(c, rate)
        w = self.plant.run(v["1"], v["2"])
        w = {"1": w["x"], "2": w["y"]}
        self.max_abs_V = max(self.max_abs_V, *(float(np.abs(x).max()) for x in v.values()))
        keep = slice(self.rtr - 1, None, self.rtr)
        self.records = {}
        for t, (src, opt) in self.drc.items():
            if opt == POSITION:
                self.records[t] = w[src][keep][:self.recorder_points]
            elif opt == VOLTAGE:
                self.records[t] = v[src][keep][:self.recorder_points]
        self.sva.update({a: float(v[a][-1]) for a in AXES})
        self.w = {a: float(w[a][-1]) for a in AXES}
        self.wave_until = (time.monotonic() + n * self.servo_s) if self.clock == "wall" else 0
        self.t_last = time.monotonic() + (n * self.servo_s if self.clock == "wall" else 0)

    def cmd_DRR_Q(self, args):
        offset, n = int(args[0]), int(args[1])
        tables = [int(t) for t in args[2:]]
        if self._wave_running() or any(t not in self.records for t in tables):
            return self._set_error(17)
        cols = [self.records[t][offset - 1:offset - 1 + n] for t in tables]
        n = min(c.size for c in cols)
        head = ["# TYPE = 1", "# SEPARATOR = 32", f"# DIM = {len(tables)}",
                f"# SAMPLE_TIME = {self.servo_s * self.rtr:.9f}", f"# NDATA = {n}"]
        head += [f"# NAME{i} = table {t}" for i, t in enumerate(tables)]
        rows = [" ".join(f"{c[k]:.6f}" for c in cols) for k in range(n)]
        return self._answer(head + ["# END_HEADER"] + rows)


def main(argv=None):
    """The double as a process of its own, the way a controller has its own processor:
    prints its address on the first line of stdout; SIGUSR1 pulls the cable, SIGUSR2
    sets controller error 506 (servo loop unstable); SIGTERM ends it, writing its final
    state (outputs, servo, largest |V| sent, unmodelled commands) to ``--state`` as JSON.
    ``--priority``: SCHED_FIFO priority of all its threads (a controller's firmware is
    never starved by the host's load)."""
    import argparse
    import json
    import os
    import signal
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="")
    ap.add_argument("--clock", default="wall")
    ap.add_argument("--state", required=True)
    ap.add_argument("--priority", type=int, default=0)
    a = ap.parse_args(argv)
    d = PIControllerDouble(a.config, clock=a.clock)
    done = threading.Event()
    signal.signal(signal.SIGUSR1, lambda *_: d.drop())
    signal.signal(signal.SIGUSR2, lambda *_: d.set_error(506))
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    if a.priority > 0:
        for tid in os.listdir("/proc/self/task"):
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(a.priority))
    print(d.address, flush=True)
    while not done.wait(0.1):
        pass
    with d.lock:
        state = {"sva": d.sva, "servo": d.servo, "max_abs_V": d.max_abs_V,
                 "unmodelled": d.unmodelled, "commands": len(d.commands)}
    d.close()
    with open(a.state + ".tmp", "w") as fh:
        json.dump(state, fh)
    os.rename(a.state + ".tmp", a.state)


if __name__ == "__main__":
    main()
