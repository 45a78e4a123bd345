"""The real-time rate this host holds a set at: short capacity runs of the set, from the
highest rate down, judged as the set's own check judges it (core/loop/capacity.py), with
room for the spread of one host's measurements. What the real-time tests and the
real-time benchmarks run at, so they are judged where the host can hold them."""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field
from statistics import median_low

from piezo_stage.core.types import Doc

RATES_HZ = (1000.0, 500.0, 250.0)
# a rate is chosen where the capacity run measured this much: more than the set's own
# check asks, since one host's measurements of one rate spread run to run (the spread:
# docs/benchmarks.md#realtime), and a rate chosen at the check's own margin is refused
# by the next set as often as not
CHOOSE_MARGIN = 3.0
RUN_S = 3.0  # a capacity run's tracking: three of the driver's 1 s reports


@dataclass
class RateRun:
    """One capacity run: its rate, whether the set faulted in it (then it says nothing
    of a capacity: the host did not hold that rate while it ran), and the driver's
    capacity readings [Capacity] in order (one a report, repeats left out)."""
    rate_hz: float
    faulted: str = ""
    readings: list = field(default_factory=list)

    @property
    def capacity(self):
        """The median reading (by capacity), None: none. One reading of a run can be
        far from its others: the last alone, as the rate was chosen by before, is as
        likely the odd one."""
        if not self.readings:
            return None
        mid = median_low([c.capacity_hz for c in self.readings])
        return next(c for c in self.readings if c.capacity_hz == mid)

    def describe(self) -> str:
        if self.faulted:
            return f"the capacity run at {self.rate_hz:g} Hz faulted ({self.faulted})"
        cap = self.capacity
        if cap is None:
            return f"the capacity run at {self.rate_hz:g} Hz gave no figures"
        spread = (f"; its {len(self.readings)} readings {self.low:.2f}-{self.high:.2f} x"
                  if len(self.readings) > 1 else "")
        return f"at {self.rate_hz:g} Hz this host sustains {cap.describe()}{spread}"

    @property
    def low(self) -> float:
        return min(c.margin for c in self.readings)

    @property
    def high(self) -> float:
        return max(c.margin for c in self.readings)


def rate_run(run, rate_hz: float, cores: int | None = None) -> RateRun:
    """A recorded capacity run (io.run_bag.Run) judged: a fault anywhere in it (a
    state, or the driver's fault count) makes it a faulted run; otherwise the driver's
    capacity readings while it reported them."""
    from piezo_stage.core.loop.capacity import Capacity
    cores = cores or os.cpu_count() or 1
    def count(r: Doc) -> int:  # the driver's faults so far, as its report says
        return int(float(r.get("faults", 0) or 0))
    faults = [r for r in run.driver_reports if r.get("state") == "faulted" or count(r)]
    if run.state_times("faulted") or faults:
        reasons = run.fault_reasons or [r.get("reason", "") for r in faults
                                        if r.get("state") == "faulted"]
        n = max(len(run.state_times("faulted")),
                max(map(count, faults), default=0))
        return RateRun(rate_hz, faulted=f"{n} fault{'s' * (n != 1)}"
                       + (f", the first: {reasons[0]}" if reasons else ""))
    readings, seen = [], set()
    for r in run.driver_reports:
        try:
            key = (float(r["loop_thread_ms_per_sample"]), float(r["host_busy_cpus"]))
        except (KeyError, ValueError):
            continue
        if key in seen:  # the same window reported again
            continue
        seen.add(key)
        readings.append(Capacity(rate_hz, 1, 1.0, key[0] * 1e-3, key[1], cores))
    return RateRun(rate_hz, readings=readings)


def measure(env: dict[str, str], rate_hz: float, compose=None, overrides=None) -> RateRun:
    """One capacity run of the set at ``rate_hz``, recorded and judged (``rate_run``).
    ``overrides``: more parameters per node (a test's, to make a run fault)."""
    from piezo_stage.io.run_bag import read_run
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    from piezo_stage.paths import default_config
    where = tempfile.mkdtemp(prefix="piezo-stage-host-rate-")
    bag = os.path.join(where, "capacity")
    o: dict[str, Doc] = {"stage_driver": {"mode": "realtime", "min_margin": 0.0},
                          "feedforward": {"model_file": default_config("stage_model.yaml")},
                          "trajectory": {"kind": "seed", "duration_s": RUN_S}}
    for node, params in (overrides or {}).items():
        o.setdefault(node, {}).update(params)
    try:
        launch = Launch(default_config("stage.yaml"), LaunchOptions(record=bag, overrides=o,
            nodes=["stage_driver", "feedforward", "controller", "trajectory"], exclusive=False,
            armed_s=RUN_S, rate=rate_hz, compose=compose), env=env)
        launch.quiet_stop = True
        launch.run(launch.wall_bound())
        return rate_run(read_run(bag), rate_hz)
    except (KeyError, ValueError, OSError) as e:
        return RateRun(rate_hz, faulted=f"no run: {e}")
    finally:
        shutil.rmtree(where, ignore_errors=True)


def host_rate(env: dict[str, str], rates=RATES_HZ, margin: float = CHOOSE_MARGIN, compose=None,
              runs: list | None = None, measure_at=None) -> tuple[float | None, str]:
    """(the highest of ``rates`` this host holds with ``margin``, or None; the figures
    in words). A capacity run at the highest rate first: there the loop thread's CPU a
    sample is the least diluted by its fixed work a second (timers, diagnostics: a
    sample reads dearer at a lower rate), and a lower rate is chosen by the samples a
    second measured there, which is generous: ``Capacity.at`` judges a lower rate's
    samples dearer, so a chosen rate keeps the margin a set's own check asks, not all
    of ``margin``. A run that faulted says the host did not
    hold its rate while it ran (taking its last report instead, a suite would run at a
    rate that faults): the next rate down gets a run of its own. The sets run at the rate chosen
    then take ``min_margin: 0`` (the host has been measured already). ``compose``: the
    loop's composition (the launcher's, ``COMPOSE``; None its real-time default).
    ``runs``: a list each capacity run (RateRun) is appended to. ``measure_at``:
    ``rate -> RateRun`` (default ``measure``)."""
    measure_at = measure_at or (lambda r: measure(env, r, compose))
    said = []
    for k, top in enumerate(rates):
        run = measure_at(top)
        if runs is not None:
            runs.append(run)
        said.append(run.describe())
        cap = run.capacity
        if cap is None:
            continue  # faulted, or no figures: the next rate down, measured on its own
        for rate in rates[k:]:
            if rate * margin <= cap.capacity_hz:
                return rate, "; ".join(said)
        break  # measured and short: a lower rate is judged from it already
    return None, "; ".join(said)
