"""TEST DOUBLE of two piezosystem jena NV200/D_NET amplifiers driving one 2-axis stage
(the hardware boundary; the only kind of double the project allows).

Everything on the host side is the real ``nv200`` package: ``NV200Device`` over its own
``TelnetProtocol`` (telnetlib3), through real TCP connections. What is simulated is the
two amplifiers at the far end, one per axis (an NV200 drives one actuator), each a TCP
server speaking the NV200 command protocol as the package reads it: one command per
line (``cmd`` or ``cmd,arg,...`` ended by CR LF), a reply ``cmd,value,...`` CR LF for a
query, every reply ended by XON (0x11, the flow control an NV200 passes to the host),
``error,N`` for an error, and the device type (``NV200/D_NET``) for an empty line.
Both drive the project's simulated stage (piezo_stage.core.model.plant) on one 20 kHz clock
(the NV200's 50 us cycle), on the wall clock: x's output and y's output as they are at
each tick, so the stage's coupling sees both.

Modelled, per amplifier: ``cl`` (0 open loop; closed loop refused: we never close the
NV200's own loop), ``modsrc`` (0 set command, 3 waveform generator), ``set`` (the
setpoint, volts in open loop), ``meas`` (the sensor, um), ``avmin``/``avmax`` (the
voltage range, -20..130 V), the waveform generator (``gbarb`` 1024 values in percent of
the voltage range, ``gtarb`` the output period in 50 us, ``goarb``/``gsarb``/``gearb``
indices, ``gcarb`` cycles, ``grun``) and the data recorder (``recsrc`` 0 position / 2
voltage, ``recast`` autostart 0 off / 2 on the generator's run, ``recstr`` stride,
``reclen`` up to 6144 samples, ``recrun``, ``recoutf`` the whole channel). Any other
command answers ``error,2`` (unknown command), as the amplifier does, and is listed in
``unmodelled``: the tests fail on any entry. Faults on demand: ``drop()`` closes every
connection (a pulled cable), ``set_error(code)`` answers the next command of each
amplifier with that error.
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from piezo_stage.core.model.plant import Plant
from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config

DEVICE_TYPE = "NV200/D_NET"
TICK_S = 50e-6            # the NV200's cycle: 20 kHz
WAVE_POINTS = 1024
RECORDER_POINTS = 6144
V_MIN, V_MAX = -20.0, 130.0
XON = b"\x11"


class _Amplifier:
    """One NV200: its settings, its generator and recorder, its connections."""

    def __init__(self, stage, axis):
        self.stage, self.axis = stage, axis
        self.closed_loop, self.modsrc, self.setpoint = True, 0, 0.0
        self.wave = np.zeros(WAVE_POINTS)
        self.gtarb, self.goarb, self.gsarb, self.gearb, self.gcarb = 1, 0, 0, 0, 1
        self.gen_start, self.gen_ticks = None, 0      # tick the generator started at
        self.recsrc, self.recast, self.recstr, self.reclen = [0, 2], 0, 1, RECORDER_POINTS
        self.rec_armed, self.rec_start = False, None
        self.rec = [[], []]
        self.err = 0
        self.conns = []
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.address = f"tcp:127.0.0.1:{self.port}"
        threading.Thread(target=self._accept, daemon=True).start()

    # -- what it outputs ---------------------------------------------------------------
    def wave_values(self):
        """The generator's sequence of output volts, one per tick, over its run."""
        seg = self.wave[self.goarb:self.gearb + 1]
        loop = self.wave[self.gsarb:self.gearb + 1]
        pts = np.concatenate([seg] + [loop] * max(0, self.gcarb - 1))
        return np.repeat(V_MIN + pts / 100.0 * (V_MAX - V_MIN), self.gtarb)

    def output(self, ks):
        """Volts at ticks ``ks`` (the setpoint, or the generator while it runs)."""
        v = np.full(ks.size, self.setpoint if self.modsrc == 0 else self.held)
        if self.gen_start is not None and self.modsrc == 3:
            seq = self.wave_values()
            i = ks - self.gen_start
            on = (i >= 0) & (i < seq.size)
            v[on] = seq[i[on]]
            after = i >= seq.size
            v[after] = seq[-1]
        return v

    @property
    def held(self):
        return self.setpoint

    def running(self, tick):
        return self.gen_start is not None and tick < self.gen_start + self.wave_values().size

    def feed(self, ks, v, w):
        """The recorder takes its samples of these ticks."""
        if self.rec_start is None:
            return
        i = ks - self.rec_start
        take = (i >= 0) & (i % self.recstr == 0) & (i // self.recstr < self.reclen)
        for ch in (0, 1):
            src = w if self.recsrc[ch] == 0 else v
            self.rec[ch].extend(src[take].tolist())

    def recording(self):
        return self.rec_start is not None and len(self.rec[0]) < self.reclen

    # -- the link ------------------------------------------------------------------------
    def _accept(self):
        while self.stage.running:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn):
        buf = b""
        while self.stage.running:
            try:
                data = conn.recv(65536)
            except OSError:
                return
            if not data:
                return
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                with self.stage.lock:
                    answer = self.handle(line.decode("latin1").strip())
                try:
                    conn.sendall(answer.encode("latin1") + XON)
                except OSError:
                    return

    def drop(self):
        for c in self.conns:
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            c.close()
        self.conns.clear()

    # -- the commands --------------------------------------------------------------------
    def handle(self, line: str) -> str:
        self.stage.commands.append(f"{self.axis}: {line}")
        if not line:
            return DEVICE_TYPE + "\r\n"
        if self.err:
            err, self.err = self.err, 0
            return f"error,{err}\r\n"
        cmd, *args = line.split(",")
        fn = getattr(self, "cmd_" + cmd, None)
        if fn is None:
            self.stage.unmodelled.append(f"{self.axis}: {line[:80]}")
            return "error,2\r\n"
        self.stage.advance()
        try:
            out = fn(args)
        except (ValueError, IndexError):
            return "error,3\r\n"   # parameter missing or malformed
        if isinstance(out, int) and out > 0:
            return f"error,{out}\r\n"
        return f"{cmd},{out}\r\n" if isinstance(out, str) else ""

    def cmd_cl(self, args):
        if not args:
            return str(int(self.closed_loop))
        if args[0] != "0":
            self.stage.unmodelled.append(f"{self.axis}: cl,{args[0]} (closed loop)")
            return 4
        self.closed_loop = False

    def cmd_modsrc(self, args):
        if not args:
            return str(self.modsrc)
        if int(args[0]) not in (0, 3):
            self.stage.unmodelled.append(f"{self.axis}: modsrc,{args[0]}")
            return 4
        if self.modsrc == 3 and int(args[0]) == 0:
            self.setpoint = float(self.output(np.array([self.stage.tick]))[0])
        self.modsrc = int(args[0])

    def cmd_set(self, args):
        if not args:
            return f"{self.setpoint:.3f}"
        if self.closed_loop:
            return 6  # locked: our set-up opens the loop first
        v = float(args[0])
        if not V_MIN <= v <= V_MAX:
            return 4
        self.setpoint = v
        self.stage.max_abs_V = max(self.stage.max_abs_V, abs(v))

    def cmd_meas(self, args):
        return f"{self.stage.w[self.axis]:.3f}"

    def cmd_avmin(self, args):
        return f"{V_MIN:.3f}"

    def cmd_avmax(self, args):
        return f"{V_MAX:.3f}"

    def cmd_gbarb(self, args):
        i, p = int(args[0]), float(args[1])
        if not (0 <= i < WAVE_POINTS and 0.0 <= p <= 100.0):
            return 4
        self.wave[i] = p
        self.stage.max_abs_V = max(self.stage.max_abs_V, abs(V_MIN + p / 100 * (V_MAX - V_MIN)))

    def _index(self, name, args, lo, hi):
        if not args:
            return str(getattr(self, name))
        x = int(args[0])
        if not lo <= x <= hi:
            return 4
        setattr(self, name, x)

    def cmd_gtarb(self, args):
        return self._index("gtarb", args, 1, 65535)

    def cmd_goarb(self, args):
        return self._index("goarb", args, 0, WAVE_POINTS - 1)

    def cmd_gsarb(self, args):
        return self._index("gsarb", args, 0, WAVE_POINTS - 1)

    def cmd_gearb(self, args):
        return self._index("gearb", args, 0, WAVE_POINTS - 1)

    def cmd_gcarb(self, args):
        return self._index("gcarb", args, 1, 65535)

    def cmd_grun(self, args):
        if not args:
            return str(int(self.running(self.stage.tick)))
        if args[0] == "1":
            self.gen_start = self.stage.tick
            if self.rec_armed and self.recast == 2:
                self.rec_start, self.rec = self.stage.tick, [[], []]
        else:
            self.setpoint = float(self.output(np.array([self.stage.tick]))[0])
            self.gen_start = None

    def cmd_recsrc(self, args):
        ch = int(args[0])
        if len(args) == 1:
            return f"{ch},{self.recsrc[ch]}"
        if int(args[1]) not in (0, 2):
            self.stage.unmodelled.append(f"{self.axis}: recsrc source {args[1]}")
            return 4
        self.recsrc[ch] = int(args[1])

    def cmd_recast(self, args):
        if int(args[0]) not in (0, 2):
            self.stage.unmodelled.append(f"{self.axis}: recast,{args[0]}")
            return 4
        self.recast = int(args[0])

    def cmd_recstr(self, args):
        return self._index("recstr", args, 1, 65535)

    def cmd_reclen(self, args):
        return self._index("reclen", args, 1, RECORDER_POINTS)

    def cmd_recrun(self, args):
        if not args:
            return str(int(self.recording() or (self.rec_armed and self.rec_start is None)))
        self.rec_armed = args[0] == "1"
        self.rec_start = None
        if self.rec_armed and self.recast == 0:
            self.rec_start, self.rec = self.stage.tick, [[], []]

    def cmd_recoutf(self, args):
        ch = int(args[0])
        return ",".join([str(ch)] + [f"{x:.4f}" for x in self.rec[ch][:self.reclen]])


class NV200StageDouble:
    """Two amplifiers (``x``, ``y``: their ``address``) on one simulated stage."""

    def __init__(self, plant_config: str = "", seed: int | None = None):
        cfg = load_plant_config(plant_config or default_plant_config_path())
        if seed is not None:
            cfg.seed = seed
        self.plant = Plant(cfg, 1.0 / TICK_S)
        self.plant.run(np.zeros(1), np.zeros(1))  # compiled now, not at the first command
        self.lock = threading.Lock()
        self.running = True
        self.commands: list[str] = []
        self.unmodelled: list[str] = []
        self.max_abs_V = 0.0
        self.w = {"x": 0.0, "y": 0.0}
        self.tick, self.t0 = 0, time.monotonic()
        self.amps = {a: _Amplifier(self, a) for a in ("x", "y")}

    def address(self, axis):
        return self.amps[axis].address

    def advance(self):
        """The stage up to now, both outputs as they were at each tick."""
        n = int((time.monotonic() - self.t0) / TICK_S) - self.tick
        if n <= 0:
            return
        if n > 200_000 and not any(a.running(self.tick) or a.recording()
                                   for a in self.amps.values()):
            self.tick += n - 200_000  # a long idle: outputs held, nothing recorded
            n = 200_000
        ks = np.arange(self.tick, self.tick + n)
        v = {a: amp.output(ks) for a, amp in self.amps.items()}
        w = self.plant.run(v["x"], v["y"])
        for a, amp in self.amps.items():
            amp.feed(ks, v[a], w[a])
        self.w = {a: float(w[a][-1]) for a in w}
        self.tick += n

    def drop(self):
        for amp in self.amps.values():
            amp.drop()

    def set_error(self, code: int):
        with self.lock:
            for amp in self.amps.values():
                amp.err = code

    def close(self):
        self.running = False
        for amp in self.amps.values():
            amp.drop()
            amp.server.close()


def main(argv=None):
    """The double as a process of its own (amplifiers have their own processors): prints
    the x and y addresses on the first line of stdout, comma separated; SIGUSR1 pulls
    both cables, SIGUSR2 makes both answer error 8 (overload) once; SIGTERM ends it,
    writing its final state (setpoints, loops, largest |V| sent, unmodelled commands)
    to ``--state`` as JSON. ``--priority``: SCHED_FIFO priority of all its threads."""
    import argparse
    import json
    import os
    import signal
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="")
    ap.add_argument("--state", required=True)
    ap.add_argument("--priority", type=int, default=0)
    a = ap.parse_args(argv)
    d = NV200StageDouble(a.config)
    done = threading.Event()
    signal.signal(signal.SIGUSR1, lambda *_: d.drop())
    signal.signal(signal.SIGUSR2, lambda *_: d.set_error(8))
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    if a.priority > 0:
        for tid in os.listdir("/proc/self/task"):
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(a.priority))
    print(f"{d.address('x')},{d.address('y')}", flush=True)
    while not done.wait(0.1):
        pass
    with d.lock:
        state = {"setpoint": {k: amp.setpoint for k, amp in d.amps.items()},
                 "closed_loop": {k: amp.closed_loop for k, amp in d.amps.items()},
                 "max_abs_V": d.max_abs_V, "unmodelled": d.unmodelled,
                 "commands": len(d.commands)}
    d.close()
    with open(a.state + ".tmp", "w") as fh:
        json.dump(state, fh)
    os.rename(a.state + ".tmp", a.state)


if __name__ == "__main__":
    main()
