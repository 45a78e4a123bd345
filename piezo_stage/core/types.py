"""Names for the values the package passes between its parts.

A stage has two axes, and most values travel as one number (or array) per axis, keyed by
the axis's name: ``PerAxis[float]`` is ``{"x": 1.0, "y": -0.5}``, as rclpy names a
message's type with a protocol and a TypeVar rather than a bare ``object``. The files
the package reads (models, plants, configurations, reports) are documents of names and
values checked where they are read; ``Doc`` names such a document, ``Params`` one
part's named parameters in it, and ``EffectsBlock`` / ``AxisEffects`` the two forms
the unmodelled effects take (as a file holds them, and as they act on one axis).
"""

from __future__ import annotations

from typing import Any, TypeAlias, TypeVar

T = TypeVar("T")

#: one value per stage axis, keyed by the axis's name ("x", "y")
PerAxis: TypeAlias = dict[str, T]

#: a document as YAML or JSON reads it (a file, a node's parameters, a report's row):
#: names to numbers, words, lists or further documents, checked where it is read
Doc: TypeAlias = dict[str, Any]

#: one part's named parameters (a Duhem axis, a coupling, an effect): numbers, and
#: where a part needs them a list (creep's time constants) or a word (dynamics' kind)
Params: TypeAlias = dict[str, Any]

#: the effects acting on one axis, each by its name: {"creep": {...}, "delay": {...}}
AxisEffects: TypeAlias = dict[str, Params]

#: a model or plant file's ``effects`` block: per effect its parameters, or a list of
#: them each naming its axes (``core.model.effects.validate_effects``)
EffectsBlock: TypeAlias = dict[str, Any]
