"""The parameter schema (core/params.py, nodes/declared.py): one table the nodes declare
from and the launcher checks against, with types, units, ranges, choices and which
parameters are live."""

import pytest

from conftest import cli, one_line_exit_2
from piezo_stage.core.params import Param, defaults, names
from piezo_stage.nodes.declared import DECLARED, SCHEMAS, refusal


def test_a_param_says_its_unit_type_and_why_a_value_is_refused():
    p = Param("kp", 0.2, "proportional gain [V/um]", lo=0.0, hi=100.0, live=True)
    assert (p.unit, p.kind, p.read_only) == ("V/um", "float", False)
    assert p.refuses(5) is None and p.refuses(0.0) is None
    assert p.refuses(-5.0) == "kp = -5.0 is outside its range [0, 100]"
    assert p.refuses(True) == "kp = True: must be a number in [0, 100]"
    assert p.refuses("1") == "kp = '1': must be a number in [0, 100]"
    size = Param("scan_size_um", [40.0, 40.0], "raster: scan size [fast, slow] [um]")
    assert (size.unit, size.kind, size.read_only) == ("um", "float list", True)
    mode = Param("mode", "lockstep", "lockstep | realtime", choices=("lockstep", "realtime"))
    assert mode.refuses("realtime") is None
    assert mode.refuses("fast") == "mode = 'fast': must be one of lockstep, realtime"
    with pytest.raises(ValueError):
        Param("mode", "fast", "", choices=("lockstep", "realtime"))
    with pytest.raises(ValueError):
        Param("x", 1.0, "", lo=2.0, hi=1.0)
    assert defaults((p, mode)) == {"kp": 0.2, "mode": "lockstep"}
    assert names((p, mode)) == {"kp", "mode"}


@pytest.mark.parametrize("node", sorted(SCHEMAS))
def test_every_schema_is_consistent(node):
    """Names unique, every default accepted by its own declaration, a range's bounds of
    the default's type family, live only where the node applies it."""
    schema = SCHEMAS[node]
    assert len(names(schema)) == len(schema) == len(DECLARED[node])
    for p in schema:
        assert p.refuses(p.default) is None, (node, p.name)
        assert p.description, (node, p.name)
        if p.lo is not None:
            assert isinstance(p.default, (int, float)) and not isinstance(p.default, bool)


def test_the_live_parameters_are_the_ones_the_nodes_apply():
    live = {node: {p.name for p in schema if p.live} for node, schema in SCHEMAS.items()}
    assert live["controller"] == {"kp", "ki", "kd", "feedback"}
    assert live["feedforward"] == {"compensate_effects", "learning_period_s",
                                   "learning_gain", "learning", "on_target_tol_um",
                                   "on_target_window_ms", "on_target_filter_ms"}
    assert live["identifier"] == {"method", "structure", "auto_cycles"}
    assert live["stage_driver"] == set()
    assert "min_subscribers" not in live["trajectory"] and len(live["trajectory"]) == 17


@pytest.mark.parametrize("node, name, value, why", [
    ("controller", "kp", -5.0, "kp = -5.0 is outside its range [0, 100]"),
    ("identifier", "method", "gradient", "method = 'gradient': must be one of fast, afsa, "
     "afsa-bat"),
    ("recorder", "log_time", "wall", "log_time = 'wall': must be one of stamp, receive"),
    ("stage_driver", "stale_timeout_s", 0.0, "stale_timeout_s = 0.0 is outside its range "
     "[0.001, 10]"),
    ("live_view", "port", 70000, "port = 70000 is outside its range [0, 65535]"),
])
def test_the_launcher_refuses_what_the_node_would(tmp_path, node, name, value, why):
    """Every node's ranges and choices, the non-loop nodes' too, before any node
    starts: exit 2, one line naming the file, the node and the reason."""
    assert refusal(node, name, value) == why
    cfg = tmp_path / "params.yaml"
    cfg.write_text(f"/**/{node}:\n  ros__parameters:\n    {name}: {value!r}\n")
    r = cli("launch", cfg, "--duration", "5")
    one_line_exit_2(r)
    assert f"{cfg}: {node}: {why}" in r.stderr, r.stderr


@pytest.mark.parametrize("text, said", [
    ("stage_driver:\n  thread_priority: 0\n",
     "stage_driver: thread_priority outside 'ros__parameters:'"),
    ("/**/feedforward: 3\n", "feedforward: expected 'ros__parameters:'"),
])
def test_a_parameter_outside_ros_parameters_is_refused_not_left_out(tmp_path, text, said):
    """A node's section with its parameters straight under the node's name (a common
    slip) would otherwise run the set without them, silently: refused in one line."""
    from piezo_stage.core.errors import ConfigError
    from piezo_stage.launcher.launcher import read_parameters
    cfg = tmp_path / "params.yaml"
    cfg.write_text(text)
    with pytest.raises(ConfigError, match=said):
        read_parameters(str(cfg))
    cfg.write_text("/**/stage_driver:\n  ros__parameters:\n    thread_priority: 0\n")
    assert read_parameters(str(cfg)) == {"stage_driver": {"thread_priority": 0}}
