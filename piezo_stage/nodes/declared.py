"""The parameters each node declares, for the launcher to check a whole parameter file
before it starts any node (each node also refuses an undeclared name itself:
``nodes/_params.check_overrides``). The suite compares this table with what the
running nodes list (test_realtime.py), so it cannot drift. rclpy's own parameters
(``use_sim_time``, ``start_type_description_service``, ``qos_overrides.*``) are
taken by every node."""

from __future__ import annotations

RCLPY_OWN = frozenset({"use_sim_time", "start_type_description_service"})

DECLARED = {
    "stage_driver": frozenset({"ai_channels", "ai_range_V", "ai_terminal_config",
        "amplifier_gain", "ao_channels", "arm_confirm_ticks", "arm_tolerance_V",
        "auto_arm", "backend", "clock_period_s", "control_rate_hz", "exit_after_max_steps",
        "lookahead_s", "managed", "max_steps", "max_steps_from_arming",
        "min_record_subscribers",
        "min_subscribers", "mode",
        "nv200_addresses", "nv200_timeout_s",
        "output_limits_V", "pi_address", "pi_axes", "pi_timeout_s", "plant_config",
        "replay_bag", "safe_ramp_V_per_s", "safe_voltage_V", "seed", "sensor_offset_um",
        "sensor_um_per_V", "slew_V_per_s",
        "stale_timeout_s", "thread_priority", "watchdog_timeout_s"}),
    "feedforward": frozenset({"approach_accel_um_per_s2", "approach_speed_um_per_s",
        "compensate_effects", "control_rate_hz", "inverse_feedforward", "learning",
        "learning_gain", "learning_period_s",
        "max_resonance_inverse_hz", "max_trajectory_points", "min_subscribers",
        "model_file", "model_required_after_s", "nominal_um_per_V", "range_um",
        "thread_priority", "use_coupling", "wait_for_trajectory"}),
    "controller": frozenset({"control_rate_hz", "feedback", "integral_limit_V", "kd", "ki",
        "kp", "min_subscribers", "relay_amplitude_V", "relay_hysteresis_um",
        "thread_priority", "voltage_limits_V"}),
    "trajectory": frozenset({"amplitude_um", "center_um", "corner", "csv_path", "dt_s",
        "duration_s", "excite_amplitude_um", "excite_center_um", "excite_s", "excite_y_hz",
        "fast_axis", "frequency_hz", "kind", "lines", "min_subscribers", "scan_center_um",
        "scan_size_um", "slow"}),
    "identifier": frozenset({"auto_cycles", "max_samples", "method", "structure"}),
    "gap": frozenset({"control_rate_hz", "min_subscribers", "model_file", "window"}),
    "recorder": frozenset({"batch_period_s", "config_file", "flush_period_s", "log_time",
        "model_file", "output", "thread_priority"}),
    "live_view": frozenset({"batch_period_s", "host", "max_rate_hz", "port"}),
}


def parameter_limits() -> dict:
    """{node: {name: {"lo": .., "hi": .., "choices": ..}}}: the ranges and choices the
    loop nodes declare, from the core's parameter tables they declare from (the driver's
    sample loop and arming supervisor, the feedforward, the controller)."""
    from piezo_stage.core.loop import arming, control, feedforward, sample_loop
    driver = {name: kw for name, _, _, kw in sample_loop.PARAMETERS}
    driver.update({name: {"lo": r[0], "hi": r[1]} for name, _, _, r in arming.PARAMETERS
                   if r})
    return {"stage_driver": driver,
            "feedforward": {name: kw for name, _, _, kw in feedforward.PARAMETERS},
            "controller": {name: kw for name, _, _, kw in control.PARAMETERS}}


def check_value(node: str, name: str, value, limits: dict) -> str | None:
    """Why ``value`` is refused for ``node``'s parameter ``name`` (None: it is not):
    outside its declared range, not one of its choices, or not a number where one is
    declared."""
    kw = limits.get(node, {}).get(name) or {}
    if "choices" in kw and value not in kw["choices"]:
        return f"{name} = {value!r}: must be one of {', '.join(map(str, kw['choices']))}"
    if "lo" in kw:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"{name} = {value!r}: must be a number in [{kw['lo']:g}, {kw['hi']:g}]"
        if not kw["lo"] <= value <= kw["hi"]:
            return f"{name} = {value!r} is outside its range [{kw['lo']:g}, {kw['hi']:g}]"
    return None


def unknown_parameter(key: str, declared) -> str:
    """"unknown parameter 'kP' (did you mean 'kp'?)"; the nearest by spelling, any case."""
    import difflib
    by_lower = {d.lower(): d for d in declared}
    near = difflib.get_close_matches(key.lower(), list(by_lower), n=1, cutoff=0.6)
    hint = f" (did you mean {by_lower[near[0]]!r}?)" if near else ""
    return f"unknown parameter {key!r}{hint}"
