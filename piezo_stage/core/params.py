"""Node parameters as data: each a :class:`Param` (name, default and so type, unit,
range or choices, live or read-only), each node's a tuple of them (a schema).

The loop cores hold their nodes' schemas (core/loop: the driver's sample loop and
arming supervisor, the feedforward, the controller), ``nodes/declared.py`` the other
nodes' and the table of all of them. From one schema the node declares its parameters
(nodes/_params.declare_schema), the launcher checks a whole parameter file before any
node starts, and the docs and tests read the same names and ranges."""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

_UNIT = re.compile(r"\[([^\[\]]+)\]")


@dataclass(frozen=True)
class Param:
    """One node parameter. ``default`` fixes its type (a float parameter takes an
    integer written in a file as that float); ``lo``/``hi`` its range (numbers),
    ``choices`` its allowed values (text); ``live``: writable while the node runs
    (applied at once), else read-only (the node reads it once). ``field``: the name
    of the core setting it fills when that differs (the arming supervisor's)."""

    name: str
    default: object
    description: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] = ()
    live: bool = False
    field: str = ""

    def __post_init__(self) -> None:
        if (self.lo is None) != (self.hi is None) or (
                self.lo is not None and self.hi is not None and self.lo > self.hi):
            raise ValueError(f"parameter {self.name}: a range needs lo <= hi")
        if self.choices and self.default not in self.choices:
            raise ValueError(f"parameter {self.name}: its default is not one of its choices")

    @property
    def unit(self) -> str:
        """The unit, as the description's last bracket says it ("" for none)."""
        found = _UNIT.findall(self.description)
        return found[-1] if found else ""

    @property
    def kind(self) -> str:
        """The parameter's type as its default has it: bool, int, float, str, or a
        list of them ("float list")."""
        d = self.default
        if isinstance(d, (list, tuple)):
            inner = {type(x).__name__ for x in d}
            return f"{inner.pop() if len(inner) == 1 else 'any'} list"
        return type(d).__name__

    @property
    def read_only(self) -> bool:
        """Set once at start (True), or writable while running (False)."""
        return not self.live

    def refuses(self, value: object) -> str | None:
        """Why ``value`` is refused (None: it is not): not one of the choices, not a
        number where a range is declared, or outside the range."""
        if self.choices and value not in self.choices:
            return f"{self.name} = {value!r}: must be one of {', '.join(self.choices)}"
        if self.lo is not None and self.hi is not None:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return f"{self.name} = {value!r}: must be a number in " \
                       f"[{self.lo:g}, {self.hi:g}]"
            if not self.lo <= value <= self.hi:
                return f"{self.name} = {value!r} is outside its range " \
                       f"[{self.lo:g}, {self.hi:g}]"
        return None


Schema = tuple[Param, ...]


def names(schema: Iterable[Param]) -> frozenset[str]:
    """The parameters' names."""
    return frozenset(p.name for p in schema)


def defaults(schema: Iterable[Param]) -> dict[str, object]:
    """{name: default}: what a node runs with when nothing is set."""
    return {p.name: p.default for p in schema}
