"""Pay a first start's compilation once, where the package is installed.

A fresh environment compiles on first use: Python's bytecode of every module a process
imports (each process again where ``PYTHONDONTWRITEBYTECODE`` is set, as on many CI
hosts) and numba's kernels (cached on disk by the first process that needs them). A
first demo then spends about 9 s of its run compiling kernels, a lockstep set waiting
the while (the feedforward's inverse of the identified model the largest part; `bench
startup` measures it). ``dev.sh`` runs the parts below after an install, so that every
later process finds the bytecode and the kernels it needs::

    python -m piezo_stage.process.warm stage     # the kernels of the simulated stage and identify
    python -m piezo_stage.process.warm inverse   # the kernels of the feedforward's inverse
    python -m piezo_stage.process.warm modules   # bytecode of the package and what it imports

dev.sh runs the three side by side (three processes on two cores take as long as the
two kernel parts in one process beside ``modules``; installing the package's own
requirements first, to compile the kernels while ROS's wheels were fetched, took
longer in all: each install's overhead, and unpacking ROS's wheels needs the CPU
too).

Only what the package's processes import is compiled (about a third of the
environment's modules, in about half the time of compiling all of them). Each part
runs the real code paths with the types the nodes and commands use, so the kernels
cached are the ones they look up.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time


def modules() -> int:
    """Import every module of the package (bytecode for them and what they import)."""
    import piezo_stage
    n = 0
    for m in pkgutil.walk_packages(piezo_stage.__path__, "piezo_stage."):
        if m.name.endswith("__main__"):
            continue  # a command's entry point runs when imported
        try:
            importlib.import_module(m.name)
            n += 1
        except Exception:  # noqa: BLE001 (an optional vendor's package not installed)
            continue
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401  (the plots import it on first use)
    return n


def stage(rate_hz: float = 1000.0) -> int:
    """The simulated stage and the identification of an excitation on it (the identifier
    node's and identify's defaults): each compiled kernel they call, in the types they
    call it with."""
    import numpy as np

    from piezo_stage.core.estimation.identify import IdentifyOptions
    from piezo_stage.core.estimation.identify.api import identify_stage
    from piezo_stage.core.estimation.record import Record
    from piezo_stage.drivers import SimBackend
    sim = SimBackend("", rate_hz)  # the driver's: compiles the plant's kernels
    t = np.arange(int(2.2 * rate_hz)) / rate_hz
    v = 75.0 - 75.0 * np.cos(2 * np.pi * t)  # two cycles of a full-stroke 1 Hz sine
    w = [sim.step(x, x).measured for x in v]
    w_um = {"x": np.array([s["x"] for s in w]), "y": np.array([s["y"] for s in w])}
    rec = Record(t, {"x": v, "y": v.copy()}, w_um, source="warm-up", voltage_exact=True)
    fitted = identify_stage(rec, ("x", "y"), IdentifyOptions(), skip_unusable=True)
    return len(fitted.model.axes)


def inverse(rate_hz: float = 1000.0) -> int:
    """The feedforward's inverse (of the stage's shipped model: the kernels take every
    model in the same packed types, so an identified one finds them too)."""
    from piezo_stage.core.model.inverse import StageInverse
    from piezo_stage.io.model_file import load_model
    from piezo_stage.paths import default_config
    model, _ = load_model(default_config("stage_model.yaml"))
    StageInverse(model, use_coupling=True, dt_s=1.0 / rate_hz).warm_kernels()
    return len(model.axes)


PARTS = {"modules": modules, "stage": stage, "inverse": inverse}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or args[0] not in PARTS:
        sys.stderr.write(f"piezo_stage.process.warm: give one of {', '.join(PARTS)}\n")
        return 2
    t0 = time.perf_counter()
    PARTS[args[0]]()
    print(f"warm {args[0]}: {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
