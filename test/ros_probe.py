"""The tests' outside node: benchmarks.probe."""

from benchmarks.probe import Probe, _param_call_raw, get_params, set_params  # noqa: F401
