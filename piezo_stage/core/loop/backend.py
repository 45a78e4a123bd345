"""What the sample loop asks of a stage backend (simulated, NI-DAQ, PI, NV200, replay:
piezo_stage/drivers): the ``Backend`` protocol and each step's ``StepResult``."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Protocol, TypeVar

from piezo_stage.core.types import PerAxis


@dataclass(frozen=True)
class StepResult:
    """One sample period of a backend: the displacement measured [um] and the voltages
    applied [V] per axis; the true displacement [um] where the stage is simulated (else
    None); the hardware's own sample count where it keeps one (the DAQ: its missed
    clocks show in it), else None."""

    measured: PerAxis[float]
    applied: PerAxis[float]
    true: PerAxis[float] | None = None
    sample_index: int | None = None


class Backend(Protocol):
    """A stage behind the driver.

    ``rate_hz``, ``limits`` ({axis: (lo, hi)} V), ``slew_V_per_s`` ({axis: V/s}),
    ``hardware_id`` (what /diagnostics names), ``paced`` (True when ``step`` itself
    waits for the hardware's sample clock), ``exhausted`` (a replay that ran out: no
    sample left). ``step(vx, vy)`` advances one sample period with the voltages held;
    ``start()`` starts the hardware's sample clock (the driver calls it just before its
    first tick and maps its stamps after it; ``step`` starts a backend not yet started);
    ``close(safe_V, ramp_V_per_s)`` leaves the outputs at the safe voltage. A lost link
    or a controller error raises core.errors.BackendFault."""

    rate_hz: float
    limits: dict[str, tuple[float, float]]
    slew_V_per_s: dict[str, float]
    hardware_id: str
    paced: bool

    @property
    def exhausted(self) -> bool:
        """No sample left (a replay that ran out)."""

    def step(self, vx: float, vy: float) -> StepResult:
        """One sample period with ``vx``, ``vy`` [V] held."""

    def start(self) -> None:
        """Start the hardware's sample clock."""

    def close(self, safe_V: float = 0.0, ramp_V_per_s: float = 0.0) -> None:
        """Leave the outputs at ``safe_V``, ramped at ``ramp_V_per_s`` (0: at once)."""


B = TypeVar("B", bound=Backend)


@contextmanager
def opened(backend: B, safe_V: float = 0.0, ramp_V_per_s: float = 0.0) -> Iterator[B]:
    """A backend for a block, closed on the way out however the block ends.

    As mcap's ``Writer`` finishes its file: ramped to ``safe_V`` at ``ramp_V_per_s``,
    released (``with opened(make_backend(...), safe_V) as b:``).
    """
    try:
        yield backend
    finally:
        backend.close(safe_V, ramp_V_per_s)
