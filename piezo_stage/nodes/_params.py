"""Node parameters: declared with a descriptor (units in the description, ranges,
read_only), choices enforced at start and at run time. A parameter is read-only unless
it is declared ``live``: a `ros2 param set` either takes effect or is refused, never
silently kept."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.params import Schema
from piezo_stage.core.types import Doc

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.parameter import Parameter


def declare(node: Any, name: str, default: Any, description: str, lo: float | None = None,
            hi: float | None = None, choices: Sequence[str] | None = None,
            live: bool | Callable[[Any], Any] | None = None) -> Any:
    """Declare a parameter with a descriptor (units in the description, ranges,
    read_only). Values outside ``choices`` are refused, at start (ConfigError) and when
    set at run time (the set call fails with the reason).

    ``live``: None, read-only (the default: the node reads it once); True, writable and
    applied by the node's own on-set callback; a callable, writable and called with the
    new value after a successful set."""
    read_only = live is None
    d = ParameterDescriptor(description=description, read_only=read_only)
    if callable(live):
        if "_live" not in node.__dict__:
            node._live = {}
            def apply(ps: list[Parameter]) -> None:
                for p in ps:
                    if p.name in node._live:
                        node._live[p.name](p.value)
            node.add_post_set_parameters_callback(apply)
        node._live[name] = live
    if lo is not None and hi is not None and isinstance(default, float):
        d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi))]
    elif lo is not None and hi is not None and isinstance(default, int) and \
            not isinstance(default, bool):
        d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    if choices:
        d.additional_constraints = "one of: " + ", ".join(choices)
        if "_choices" not in node.__dict__:
            node._choices = {}
            node.add_on_set_parameters_callback(lambda ps: _check_choices(node, ps))
        node._choices[name] = tuple(choices)
    _float_override(node, name, default)
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    try:
        value = node.declare_parameter(name, default, d).value
    except (InvalidParameterTypeException, InvalidParameterValueException) as e:
        raise ConfigError(f"parameter {name}: {e}") from None  # a configuration error
    if choices and value not in choices:
        raise ConfigError(f"parameter {name} = {value!r}: must be one of "
                          f"{', '.join(choices)}")
    return value


def declare_schema(node: Any, schema: Schema, live: Doc | None = None) -> Doc:
    """Declare every parameter of ``schema`` (core/params.py) and return {name: value}.
    A live one is applied by ``live[name]`` (called with each new value) when given,
    else by the node's own on-set callback; the others are read-only."""
    live = live or {}
    return {p.name: declare(node, p.name, p.default, p.description, p.lo, p.hi,
                            p.choices or None, live=live.get(p.name, True) if p.live else None)
            for p in schema}


def _check_choices(node: Any, params: Sequence[Parameter]) -> SetParametersResult:
    for p in params:
        ch = node._choices.get(p.name)
        if ch and p.value not in ch:
            return SetParametersResult(successful=False,
                                       reason=f"{p.name} must be one of {', '.join(ch)}")
    return SetParametersResult(successful=True)


def _float_override(node: Any, name: str, default: Any) -> None:
    """``kp: 1`` where a float is declared: taken as 1.0 (people write it so; rclpy
    would refuse the type and the node would not start). Lists of numbers alike."""
    from rclpy.parameter import Parameter
    over = node._parameter_overrides.get(name)  # rclpy keeps the file's and -p values here
    if over is None:
        return
    if isinstance(default, float) and over.type_ == Parameter.Type.INTEGER:
        node._parameter_overrides[name] = Parameter(name, Parameter.Type.DOUBLE,
                                                    float(over.value))
    elif (isinstance(default, (list, tuple)) and default and
          all(isinstance(x, float) for x in default) and
          over.type_ == Parameter.Type.INTEGER_ARRAY):
        node._parameter_overrides[name] = Parameter(name, Parameter.Type.DOUBLE_ARRAY,
                                                    [float(x) for x in over.value])


def check_overrides(node: Node) -> None:
    """Refuse a parameter the node was given but does not declare (a misspelling such as
    ``kP`` would otherwise be ignored without a word): ConfigError naming the key and
    the closest declared one."""
    from piezo_stage.nodes.declared import RCLPY_OWN, unknown_parameter
    declared = set(node._parameters)
    unknown = sorted(k for k in node._parameter_overrides
                     if k not in declared and k not in RCLPY_OWN
                     and not k.startswith("qos_overrides."))
    if unknown:
        raise ConfigError(unknown_parameter(unknown[0], declared - RCLPY_OWN))

