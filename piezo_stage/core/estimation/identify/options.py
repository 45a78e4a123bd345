"""How an axis is identified: the options every solver reads (their own module, so
the solvers and the identification that calls them import it without a circle)."""

from __future__ import annotations

from dataclasses import dataclass, field

from piezo_stage.core.types import Doc


@dataclass
class IdentifyOptions:
    """How to identify an axis.

    method: fast | afsa | afsa-bat; structure: whole | segmented; n, m: degrees of f and
    g; coupling: 'auto' (fit a coupling term when the other axis's voltage moves and the
    method is fast), 'on' or 'off'; budget: objective evaluations (None for the method's
    default); seed for the swarms; afsa: swarm settings; delay: the displacement's
    lag behind the voltage, 'auto' (the fast method: a whole number of samples, 0 to
    ``api.LAG_MAX``, taken where it fits clearly better: a DAQ reads its input a
    sample after it writes its output) or seconds (0: none)."""

    method: str = "fast"
    structure: str = "segmented"
    n: int = 3
    m: int = 2
    coupling: str = "auto"
    budget: int | None = None
    seed: int = 0
    afsa: Doc = field(default_factory=dict)
    delay: str | float = "auto"
