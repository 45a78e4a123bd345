"""The tests' outside node: piezo_stage.launch.probe."""

from piezo_stage.launch.probe import Probe, _param_call_raw, get_params, set_params  # noqa: F401
