"""The NV200 backend on piezosystem jena's real nv200 package (NV200Device over its own
TelnetProtocol, through real TCP connections), with only the two amplifiers at the far
end replaced by the TEST DOUBLE (test/hardware_double/nv200_double.py)."""

import ast
import os
import sys

import numpy as np
import pytest

from conftest import ROOT

nv200 = pytest.importorskip("nv200")
DOUBLE = os.path.join(ROOT, "test", "hardware_double")
sys.path.insert(0, DOUBLE)
from nv200_double import NV200StageDouble  # noqa: E402

from piezo_stage.core.errors import BackendFault, ConfigError  # noqa: E402
from piezo_stage.core.params import defaults  # noqa: E402
from piezo_stage.drivers import BACKEND_PARAMS  # noqa: E402
from piezo_stage.drivers.nv200 import Nv200Backend  # noqa: E402

PARAMS = defaults(BACKEND_PARAMS)
SOURCE = os.path.join(ROOT, "piezo_stage", "drivers", "nv200.py")


@pytest.fixture
def stage(tmp_path):
    """Two amplifiers on the default simulated stage without sensor noise; after the
    test, nothing we sent may have been a command they do not model."""
    cfg = tmp_path / "quiet.yaml"
    cfg.write_text(open(os.path.join(ROOT, "config", "sim_stage.yaml")).read()
                   .replace("model: stage_model.yaml",
                            "model: " + os.path.join(ROOT, "config", "stage_model.yaml"))
                   .replace("noise_rms_um: 0.1", "noise_rms_um: 0.0"))
    d = NV200StageDouble(str(cfg))
    yield d
    d.close()
    assert not d.unmodelled, f"commands the double does not model: {d.unmodelled}"


def backend(d, rate=50.0, **over):
    return Nv200Backend(rate, {**PARAMS, "nv200_addresses": [d.address("x"),
                                                             d.address("y")], **over}, 0.0)


def test_the_package_is_piezosystem_jenas_and_every_call_we_make_exists_in_it():
    """nv200 is the installed package; every method drivers/nv200.py calls on a device,
    its PID controller, generator, recorder or transport exists there, with the
    arguments we pass."""
    import inspect

    from nv200.data_recorder import DataRecorder
    from nv200.nv200_device import NV200Device
    from nv200.serial_protocol import SerialProtocol
    from nv200.telnet_protocol import TelnetProtocol
    from nv200.waveform_generator import WaveformGenerator
    assert "site-packages" in nv200.__file__
    owners = {"dev": NV200Device, "pid": NV200Device.PIDController, "gen": WaveformGenerator,
              "rec": DataRecorder}
    seen = set()
    for node in ast.walk(ast.parse(open(SOURCE).read())):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            base = node.func.value
            name = base.id if isinstance(base, ast.Name) else \
                base.attr if isinstance(base, ast.Attribute) else None
            if name in owners:
                fn = getattr(owners[name], node.func.attr, None)
                assert fn is not None, f"nv200's {owners[name].__name__} has no " \
                                       f"{node.func.attr}"
                inspect.signature(fn).bind(None, *node.args,
                                           **{k.arg: None for k in node.keywords})
                seen.add(f"{name}.{node.func.attr}")
    assert {"dev.connect", "dev.set_setpoint", "dev.get_current_position",
            "gen.set_waveform_buffer", "gen.start", "rec.read_recorded_data"} <= seen, seen
    inspect.signature(TelnetProtocol).bind(host="h", port=23)
    inspect.signature(SerialProtocol).bind(port="/dev/ttyUSB0")


def test_set_up_opens_both_loops_and_keeps_inside_the_amplifiers_range(stage):
    b = backend(stage)
    try:
        assert b.hardware_id.startswith("NV200 x at tcp:127.0.0.1:")
        assert b.limits == {"x": (0.0, 130.0), "y": (0.0, 130.0)}   # 150 V cut to 130
        assert [a.closed_loop for a in stage.amps.values()] == [False, False]
        assert all(a.modsrc == 0 for a in stage.amps.values())
    finally:
        b.close(0.0, 1e5)
    for over, match in (({"nv200_addresses": ["tcp:h"]}, "two different"),
                        ({"nv200_addresses": ["bogus", "tcp:h"]}, "tcp:HOST"),
                        ({"output_limits_V": [140.0, 150.0, 0.0, 150.0]}, "overlap")):
        with pytest.raises(ConfigError, match=match):
            backend(stage, **over)
    with pytest.raises(ConfigError, match="set-up failed.*lost"):
        Nv200Backend(50.0, {**PARAMS, "nv200_addresses": ["tcp:127.0.0.1:9",
                                                         "tcp:127.0.0.1:7"]}, 0.0)


def test_streamed_steps_drive_both_axes_and_are_clamped(stage):
    b = backend(stage)
    try:
        b.start()
        for _ in range(10):
            r = b.step(50.0, 80.0)
        w, applied = r.measured, r.applied
        assert r.true is None and r.sample_index is None and applied == {"x": 50.0, "y": 80.0}
        assert 10.0 < w["x"] < 25.0 and 25.0 < w["y"] < 40.0, w
        applied = b.step(500.0, -50.0).applied
        assert applied == {"x": 130.0, "y": 0.0} and stage.max_abs_V <= 130.0
    finally:
        b.close(0.0, 1e5)
    assert [a.setpoint for a in stage.amps.values()] == [0.0, 0.0]   # ramped to safe


def test_an_amplifier_error_and_a_pulled_cable_are_backend_faults(stage):
    b = backend(stage, nv200_timeout_s=0.5)
    b.start()
    b.step(10.0, 10.0)
    stage.set_error(8)  # overload
    with pytest.raises(BackendFault, match="NV200 error during a sample"):
        b.step(11.0, 11.0)
    b.step(12.0, 12.0)
    stage.drop()
    with pytest.raises(BackendFault, match="link to the NV200 .* lost"):
        b.step(13.0, 13.0)
    b.close(0.0, 1e5)


def test_a_wave_played_on_the_generators_is_recorded_as_the_sim_gives_it(stage):
    """Tables loaded (percent of the voltage range), both generators run, the recorders
    (started by them) read back: the voltage is the wave, the position what the
    simulated stage gives for it; then back to the set command at the safe voltage. A
    waveform beyond the 1024-point table or off the 20 kHz clock is refused."""
    from piezo_stage.core.model.plant import Plant
    b = backend(stage, rate=5000.0)
    fs = 5000.0
    t = np.arange(0, 0.1, 1 / fs)
    vx, vy = 60 - 50 * np.cos(2 * np.pi * 20 * t), 60 - 40 * np.cos(2 * np.pi * 10 * t)
    try:
        applied, w = b.play(vx, vy, fs, 1e5)
        with pytest.raises(ConfigError, match="holds 1024"):
            b.play(np.full(2000, 10.0), np.full(2000, 10.0), fs, 1e5)
        with pytest.raises(ConfigError, match="20 kHz"):
            b.play(vx, vy, 3000.0, 1e5)
    finally:
        b.close(0.0, 1e5)
    np.testing.assert_allclose(applied["x"], vx, atol=1e-3)
    np.testing.assert_allclose(applied["y"], vy, atol=1e-3)
    ref = Plant(stage.plant.config, fs).run(vx, vy)
    # the amplifiers start one command apart (the host's skew, a few ms): compared after
    # the first period
    for a in "xy":
        assert np.abs(w[a] - ref[a])[t.size // 2:].max() < 1.0, a
    assert all(a.modsrc == 0 and a.setpoint == 0.0 for a in stage.amps.values())


def test_play_command_on_the_nv200_double_writes_the_record(tmp_path, stage):
    from piezo_stage.cli import main
    from piezo_stage.io.records import read_record
    wave = tmp_path / "wave.csv"
    t = np.arange(0, 0.05, 1 / 5000.0)
    wave.write_text("t,vx,vy\n" + "\n".join(
        f"{x:.6f},{60 - 50 * np.cos(2 * np.pi * 20 * x):.6f},30" for x in t) + "\n")
    out = tmp_path / "rec.csv"
    assert main(["play", str(wave), "--backend", "nv200", "--device",
                 f"{stage.address('x')},{stage.address('y')}", "--out", str(out)]) == 0
    rec = read_record(str(out))
    assert len(rec) == t.size and set(rec.w) == {"x", "y"}
    assert np.ptp(rec.w["x"]) > 20.0


class AmplifiersProcess:
    """The double in a process of its own at SCHED_FIFO 60: the two addresses, signals
    for the faults, and its final state once ended."""

    def __init__(self, tmp_path):
        import subprocess
        self.state_path = str(tmp_path / "amplifiers_state.json")
        self.proc = subprocess.Popen(
            [sys.executable, os.path.join(DOUBLE, "nv200_double.py"), "--state",
             self.state_path, "--priority", "60"], stdout=subprocess.PIPE, text=True,
            env=dict(os.environ, PYTHONPATH=os.pathsep.join([DOUBLE, ROOT])))
        self.addresses = self.proc.stdout.readline().strip().split(",")
        assert len(self.addresses) == 2, self.addresses

    def end(self) -> dict:
        import json
        import signal
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(10)
        with open(self.state_path) as fh:
            return json.load(fh)


# the package keeps 50 samples/s at most (its 10 ms input flush per write); the driver
# publishes a sample once both positions are read (about 22 ms) and needs the next
# command back within the period: 25 Hz leaves it some 15 ms
RT_RATE = 25.0


def _config(tmp_path, addresses):
    cfg = tmp_path / "nv200.yaml"
    cfg.write_text("/**/stage_driver:\n  ros__parameters:\n    backend: nv200\n"
                   f"    mode: realtime\n    nv200_addresses: ['{addresses[0]}', "
                   f"'{addresses[1]}']\n    control_rate_hz: {RT_RATE}\n"
                   "    stale_timeout_s: 0.3\n    nv200_timeout_s: 0.5\n"
                   "/**/feedforward:\n  ros__parameters:\n    model_file: " +
                   os.path.join(ROOT, "config", "stage_model.yaml") +
                   "\n/**/controller:\n  ros__parameters:\n    kp: 0.2\n"
                   "/**/trajectory:\n  ros__parameters:\n    kind: sine\n"
                   "    frequency_hz: 0.5\n    duration_s: 20.0\n")
    return str(cfg)


def _states(bag):
    from piezo_stage.io.bag import deserialize, iter_messages
    from piezo_stage.io.run_bag import status_node
    states, volts, diag = [], [], {}
    for topic, mt, _, data in iter_messages(bag):
        m = deserialize(data, mt)
        if topic.endswith("/joint_states"):
            volts.append(list(m.effort))
        elif topic.endswith("/state"):
            values = {kv.key: kv.value for kv in m.status[0].values}
            states.append((m.status[0].message, values.get("reason", "")))
        elif topic == "/diagnostics" and status_node(m.status[0].name) == "stage_driver":
            diag = {kv.key: kv.value for kv in m.status[0].values}
            diag["hardware_id"] = m.status[0].hardware_id
    return states, volts, diag


@pytest.mark.realtime
def test_driver_node_on_the_nv200_double_arms_tracks_and_ramps_down(tmp_path, ros_env):
    """The whole set in real time on the two amplifiers at 25 Hz (within the package's pace):
    it arms and tracks, the amplifiers are named, the outputs stay in their range and
    end at the safe voltage."""
    pytest.importorskip("rclpy")
    import warnings

    from piezo_stage.launcher.launcher import Launch, LaunchOptions

    def run(folder):
        folder.mkdir()
        c = AmplifiersProcess(folder)
        try:
            bag = str(folder / "nv200_run")
            assert Launch(_config(folder, c.addresses), LaunchOptions(record=bag,
                exclusive=False), env=ros_env).run(duration=10.0) == 0
        finally:
            end = c.end()
        assert not end["unmodelled"], end["unmodelled"]
        states, volts, diag = _states(bag)
        return end, [s for s, _ in states], states, volts, diag, bag
    end, names, states, volts, diag, bag = run(tmp_path / "first")
    if "armed" not in names:
        # real time on this shared 2-core VM, as the real-time tests run: once more,
        # and two failures fail (each sample's two telnet round trips take 23 of the
        # 40 ms period; a slow host once closed the loop 6 s into the 10 s run)
        warnings.warn(f"the set on the NV200 double did not arm: {states}; ran it again",
                      stacklevel=1)
        end, names, states, volts, diag, bag = run(tmp_path / "second")
    assert "armed" in names and names[-1] == "disarmed" and "faulted" not in names, states
    assert diag["hardware_id"].startswith("NV200 x at tcp:127.0.0.1")
    # the loop kept its pace from arming to the end (the set's start-up time varies)
    from piezo_stage.io.run_bag import read_run
    marks = read_run(bag).states
    ran_s = (marks[-1][0] - marks[1][0]) * 1e-9
    # (the last diagnostics may be up to their 1 s period older than the end)
    assert int(diag["samples"]) >= max(60, 0.8 * RT_RATE * (ran_s - 1.0)), (diag, ran_s)
    assert end["max_abs_V"] <= 130.0
    assert end["setpoint"] == {"x": 0.0, "y": 0.0} and volts[-1] == [0.0, 0.0]
    assert end["closed_loop"] == {"x": False, "y": False}


@pytest.mark.realtime
@pytest.mark.parametrize("fault", ["amplifier error", "pulled cable"])
def test_driver_node_on_the_nv200_double_faults_on_a_lost_link_or_an_error(
        tmp_path, ros_env, fault, capfd):
    """Once armed, the amplifiers report an overload or their cables are pulled: the
    driver faults with the reason on its state topic and exits 1; the launcher stops
    the set. With the links up the outputs ramp to safe."""
    import signal
    import threading
    pytest.importorskip("rclpy")
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    from ros_probe import Probe
    c = AmplifiersProcess(tmp_path)
    launch = Launch(_config(tmp_path, c.addresses), LaunchOptions(record=str(tmp_path / "bag"),
        exclusive=False), env=ros_env)
    probe = Probe(int(ros_env["ROS_DOMAIN_ID"]))

    def hurt():
        if probe.wait_state("armed", 60):
            probe.spin(1.0)
            c.proc.send_signal(signal.SIGUSR2 if fault == "amplifier error"
                               else signal.SIGUSR1)
    t = threading.Thread(target=hurt, daemon=True)
    try:
        t.start()
        rc = launch.run(duration=25.0)
    finally:
        t.join(5)
        probe.close()
        end = c.end()
    err = capfd.readouterr().err
    assert rc == 1, err[-2000:]
    assert "stage_driver died with exit code 1" in err, err[-2000:]
    states, _, _ = _states(str(tmp_path / "bag"))
    reason = dict(states).get("faulted", "")
    want = "NV200 error during a sample" if fault == "amplifier error" else \
        "link to the NV200 (x at tcp:127.0.0.1"
    assert want in reason, states
    if fault == "amplifier error":
        assert end["setpoint"] == {"x": 0.0, "y": 0.0}
    assert not end["unmodelled"], end["unmodelled"]
