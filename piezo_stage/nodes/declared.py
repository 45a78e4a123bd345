"""Every node's parameter schema (core/params.py), in one table: the loop nodes' from
their cores (core/loop), the others' here. Each node declares its parameters from its
schema (nodes/_params.declare_schema), so the launcher, which checks a whole parameter
file against this table before it starts any node, and the nodes cannot disagree; the
suite also compares it with what the running nodes list (test_realtime.py). rclpy's own
parameters (``use_sim_time``, ``start_type_description_service``, ``qos_overrides.*``)
are taken by every node. No rclpy here: the launcher reads it before any node exists."""

from __future__ import annotations

from collections.abc import Iterable

from piezo_stage.core.loop.trajectory import KINDS
from piezo_stage.core.params import Param, Schema, names
from piezo_stage.core.types import Doc

RCLPY_OWN = frozenset({"use_sim_time", "start_type_description_service"})



def _live(name: str, default: object, description: str) -> Param:
    return Param(name, default, description, live=True)


# live: a set builds and publishes the new trajectory (or is refused with why)
TRAJECTORY: Schema = tuple(_live(*a) for a in (
    ("kind", "seed", "one of: " + ", ".join(KINDS)),
    ("frequency_hz", 10.0, "frequency [Hz]"),
    ("duration_s", 1.0, "length [s]"),
    ("center_um", 21.0, "centre [um]"),
    ("amplitude_um", 24.0, "amplitude [um]"),
    ("dt_s", 0.001, "point spacing [s]"),
    ("csv_path", "", "CSV t,wx,wy for kind csv"),
    ("lines", 16, "raster: line periods (trace and retrace) in the scan"),
    ("scan_size_um", [40.0, 40.0], "raster: scan size [fast, slow] [um]"),
    ("scan_center_um", [40.0, 40.0], "raster: scan centre [fast, slow] [um]"),
    ("corner", 0.1, "raster: share of each line spent turning around, 0-0.5"),
    ("slow", "steps", "raster: slow axis, steps (a line at a time) or ramp"),
    ("fast_axis", "x", "raster: the fast axis, x or y"),
    ("excite_s", 0.0, "prepended excitation [s] (0: none)"),
    ("excite_center_um", 35.0, "excitation centre [um]"),
    ("excite_amplitude_um", 34.0, "excitation amplitude [um]"),
    ("excite_y_hz", 1.5, "y excitation frequency [Hz] (x: 1 Hz); unequal, so the axes' "
     "coupling is identifiable"),
)) + (Param("min_subscribers", 1, "trajectory subscribers to wait for"),)

# live: the next fit uses them
IDENTIFIER: Schema = (
    Param("method", "fast", "fast | afsa | afsa-bat", choices=("fast", "afsa", "afsa-bat"),
          live=True),
    Param("structure", "segmented", "segmented | whole", choices=("segmented", "whole"),
          live=True),
    Param("auto_cycles", 0, "identify after this many complete cycles (0: on request "
          "only)", lo=0, hi=1000, live=True),
    Param("max_samples", 200_000, "buffer length", lo=100, hi=10_000_000),
)

GAP: Schema = (
    Param("control_rate_hz", 1000.0, "control rate [Hz]", lo=1.0, hi=1e5),
    Param("model_file", "", "the twin's model ('' = config/stage_model.yaml)"),
    Param("window", 1000, "samples in the rolling RMS", lo=10, hi=10_000_000),
    Param("min_subscribers", 0, "residual subscribers to wait for"),
    Param("watch", False, "diagnose the live gap when it rises, hand a refit that "
          "shrinks it on as the model (docs/watch.md)"),
    Param("watch_effects", ["creep", "drift"], "the effects the watch may name"),
    Param("watch_hold", False, "lockstep: the set waits at a window's last sample while "
          "it is diagnosed (on watch/hold; launch --watch sets it in lockstep)"),
)

RECORDER: Schema = (
    Param("output", "", "bag directory ('' = bags/<timestamp>)"),
    Param("config_file", "", "config to store as metadata"),
    Param("model_file", "", "model to store as metadata"),
    Param("batch_period_s", 0.004, "wait between takes [s]; queues hold 5000 samples per "
          "topic", lo=0.0, hi=60.0, live=True),
    Param("log_time", "stamp", "bag log time: stamp (lockstep) | receive (real time)",
          choices=("stamp", "receive")),
    Param("thread_priority", 40, "real-time recording (log_time receive): SCHED_FIFO "
          "priority of the middleware's receiving threads (the writing stays at normal "
          "priority; 0: leave the scheduler alone)", lo=0, hi=99),
    Param("flush_period_s", 0.5, "chunk flush period [s]", lo=0.01, hi=60.0),
)

LIVE_VIEW: Schema = (
    Param("host", "127.0.0.1", "address the WebSocket server binds (0.0.0.0: every "
          "interface; mind who can reach it)"),
    Param("port", 8765, "WebSocket port (foxglove.websocket.v1)", lo=0, hi=65535),
    Param("max_rate_hz", 200.0, "per topic, at most this many messages per wall-clock "
          "second to the viewers (0: all)", lo=0.0, hi=1e6, live=True),
    Param("batch_period_s", 0.01, "wait between takes [s] (off the loop's path)", lo=0.0,
          hi=1.0, live=True),
)

def __getattr__(name: str) -> Doc:
    """``SCHEMAS`` (every node's schema) and ``DECLARED`` (their names), built at first
    use: the loop nodes' schemas live in their cores, whose numerics (numba, scipy) the
    other nodes, which import this module for their own schema, need not start with."""
    if name not in ("SCHEMAS", "DECLARED"):
        raise AttributeError(name)
    from piezo_stage.core.loop import arming, control, feedforward, sample_loop
    from piezo_stage.drivers import BACKEND_PARAMS
    schemas: dict[str, Schema] = {
        "stage_driver": sample_loop.PARAMETERS + arming.PARAMETERS + BACKEND_PARAMS,
        "feedforward": feedforward.PARAMETERS,
        "controller": control.PARAMETERS,
        "trajectory": TRAJECTORY,
        "identifier": IDENTIFIER,
        "gap": GAP,
        "recorder": RECORDER,
        "live_view": LIVE_VIEW,
    }
    globals()["SCHEMAS"] = schemas
    globals()["DECLARED"] = {node: names(schema) for node, schema in schemas.items()}
    return globals()[name]


def refusal(node: str, name: str, value: object) -> str | None:
    """Why ``value`` is refused for ``node``'s parameter ``name`` (None: it is not, or
    no such parameter): outside its declared range, not one of its choices, or not a
    number where one is declared."""
    found = next((p for p in __getattr__("SCHEMAS").get(node, ()) if p.name == name),
                 None)
    return found.refuses(value) if found is not None else None


def unknown_parameter(key: str, declared: Iterable[str]) -> str:
    """"unknown parameter 'kP' (did you mean 'kp'?)"; the nearest by spelling, any case."""
    import difflib
    by_lower = {d.lower(): d for d in declared}
    near = difflib.get_close_matches(key.lower(), list(by_lower), n=1, cutoff=0.6)
    hint = f" (did you mean {by_lower[near[0]]!r}?)" if near else ""
    return f"unknown parameter {key!r}{hint}"
