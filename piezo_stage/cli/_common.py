"""What the ``piezo-stage`` commands share: exit codes, the one-line error, the plant a
command simulates, voltage and port checks, parameter files."""

from __future__ import annotations

import argparse
import math
import sys
from typing import TYPE_CHECKING

from piezo_stage.core.errors import DataError, printable
from piezo_stage.core.types import Doc, PerAxis

if TYPE_CHECKING:
    import numpy as np

EXIT_USAGE = 2
EXIT_SOLVER = 3


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line and exit 2."""

    def error(self, message):  # argparse would print the usage as well
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        sys.exit(EXIT_USAGE)


def die(msg: str, code: int = EXIT_USAGE):
    """One line on stderr (control characters escaped, at most 500 characters), then
    exit with ``code``."""
    sys.stderr.write(f"piezo-stage: error: {printable(msg, 500)}\n")
    sys.exit(code)


def load_plant(args, rate_hz):
    """The plant a command simulates: --model exactly (with its effects), else the
    plant config (--config or the default); --no-noise, --seed applied."""
    from piezo_stage.core.model.plant import PlantConfig
    from piezo_stage.io.model_file import load_model
    from piezo_stage.io.plant_file import default_plant_config_path, load_plant_config
    if args.model:
        model, effects = load_model(args.model)
        cfg = PlantConfig.exact(model, rate_hz, effects)  # the model's twin
    else:
        cfg = load_plant_config(args.config or default_plant_config_path())
    if getattr(args, "no_noise", False):
        cfg.noise_rms_um = 0.0
        cfg.quantization_um = 0.0
    if getattr(args, "seed", None) is not None:
        cfg.seed = args.seed
    return cfg


def check_voltages(rec, limits, source):
    """DataError naming the first line of ``rec`` outside the voltage limits."""
    lo, hi = limits
    for a, v in rec.v.items():
        import numpy as np
        bad = np.flatnonzero((v < lo) | (v > hi))
        if bad.size:
            i = int(bad[0])
            raise DataError(f"{source}: v{a} = {v[i]:g} V at line {i + 2} is outside "
                                  f"the voltage limits [{lo:g}, {hi:g}] V")


def warn_past_fit_range(model, v: PerAxis[np.ndarray], source: str) -> None:
    """One line on stderr when the voltages ``v`` take ``model`` past the range it was
    fitted on (it runs there, its branches continuing straight from their ends)."""
    from piezo_stage.core.model.duhem import past_fit_range
    past = past_fit_range(model, v)
    if past:
        how = {m.continuation for m in model.axes.values()}
        how_s = "straight" if how == {"straight"} else "level" if how == {"level"} else \
            "straight or level (as the file says)"
        sys.stderr.write(f"piezo-stage: warning: {source}: the model is used past its "
                         f"fitted range ({'; '.join(past)}): its branches continue "
                         f"{how_s} from their ends there\n")


def warn_small_span(rec, limits_V, source: str) -> None:
    """One line on stderr when the record's voltages span under a tenth of the voltage
    limits its model gets (``--limits``, else 0-150 V widened to take them): a 0-3.6 V
    control input read against an amplifier's 150 V; the model is written bounded
    past the record's span, and the limits are the user's to give."""
    from piezo_stage.core.model.duhem import voltage_limits_for
    lo, hi = voltage_limits_for(list(rec.v.values()), limits_V)
    vmin = min(float(v.min()) for v in rec.v.values())
    vmax = max(float(v.max()) for v in rec.v.values())
    if vmax - vmin < 0.1 * (hi - lo):
        given = "given" if limits_V is not None else "default"
        sys.stderr.write(f"piezo-stage: warning: {source}: the voltages span "
                         f"{vmin:.4g}..{vmax:.4g} V, {100 * (vmax - vmin) / (hi - lo):.3g} "
                         f"% of the voltage limits {lo:g}..{hi:g} V ({given}): the model "
                         f"is written bounded past that span; give your amplifier's "
                         f"range with --limits LO,HI (e.g. --limits={vmin:.3g},"
                         f"{vmax:.3g} for an input that spans it)\n")


def number(lo: float, hi: float, integer: bool = False, lo_open: bool = False):
    """argparse type: a finite number in [lo, hi] (``lo_open``: (lo, hi]), an integer
    when ``integer``; anything else is a one-line usage error (exit 2)."""
    def parse(text):
        try:
            x = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{printable(text, 40)!s} is not {'a whole number' if integer else 'a number'}"
            ) from None
        if not math.isfinite(x) or x < lo or x > hi or (lo_open and x == lo):
            raise argparse.ArgumentTypeError(
                f"{printable(text, 40)!s} is outside {'(' if lo_open else '['}{lo:g}, {hi:g}]")
        return x
    return parse


def limits(text):
    """argparse type: "LO,HI" voltage limits [V], LO < HI."""
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        lo = hi = float("nan")
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise argparse.ArgumentTypeError(f"{printable(text, 40)!s}: give LO,HI in volts "
                                         "with LO < HI, e.g. 0,150 or -90,90")
    return lo, hi


def namespace(text):
    """argparse type: a ROS namespace, fully qualified ("stage2" -> "/stage2")."""
    from piezo_stage.core.errors import ConfigError
    from piezo_stage.core.ros_names import fully_qualified_namespace
    try:
        return fully_qualified_namespace(text)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def port(text):
    """argparse type: a TCP port."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a TCP port (1-65535)")
    return port


def param_overrides(paths) -> Doc:
    """Node parameters from parameter files (as `tune` writes), later files win."""
    from piezo_stage.launcher.launcher import read_parameters
    out: dict[str, Doc] = {}
    for p in paths or ():
        for node, params in read_parameters(p).items():
            out.setdefault(node, {}).update(params)
    return out


def pair(text):
    """argparse type: two finite numbers A,B [um] (a scan's fast and slow axis, or x
    and y), within +-10,000 um."""
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give two numbers, A,B (um)") \
            from None
    if not all(-1e4 < v < 1e4 for v in (a, b)):  # NaN and inf fail this too
        raise argparse.ArgumentTypeError(f"{text!r}: each within +-10,000 um")
    return [a, b]


# which of the loop's nodes share a process (launcher/launcher.py COMPOSE's keys, named
# here so that parsing a command line does not import the launcher)
COMPOSITIONS = ("loop", "command", "none")


def client_transport() -> None:
    """A command that only talks to a running set (``lifecycle``, ``move``) keeps off
    Fast DDS's shared-memory transport, as the real-time set does
    (launcher/transport.py ``realtime_transport_env``; a transport configuration of the
    user's own is left as it is). Call before the command's participant is made: on a
    host with stale shared-memory ports from killed processes Fast DDS printed
    "RTPS_TRANSPORT_SHM Error ... open_and_lock_file failed" into the command's
    output, and its lines were no longer its own."""
    import os

    from piezo_stage.launcher.transport import realtime_transport_env
    for key, value in realtime_transport_env(os.environ).items():
        os.environ[key] = value
