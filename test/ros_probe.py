"""The tests' outside node: piezo_stage.benchmarks.probe."""

from piezo_stage.benchmarks.probe import Probe, _param_call_raw, get_params, set_params  # noqa: F401
