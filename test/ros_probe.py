"""The tests' outside node: piezo_stage.launch.probe."""

from piezo_stage.launch.probe import Probe, get_params, set_params  # noqa: F401
