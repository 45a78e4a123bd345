"""The transform effects as operators on a design's columns (X -> E(X)): creep,
delay and dynamics, each alone or in turn (the gap diagnosis's candidates apply them
to the Duhem regressors)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from piezo_stage.core.model.effects import Creep, Delay, Dynamics, sampled_pair
from piezo_stage.core.types import EffectsBlock, Params

TRANSFORMS = ("creep", "dynamics", "delay")  # linear time-invariant: they commute
CREEP_TAUS = (0.05, 0.5, 5.0, 50.0)


def effect_operator(name: str, fs: float, params: Params) -> Callable[[np.ndarray], np.ndarray]:
    """The column operator (X -> E(X)) of a transform effect with these parameters."""
    if name == "creep":
        return Creep(fs, gamma=params["gamma"], tau_s=params.get("tau_s", CREEP_TAUS)).apply
    if name == "delay":
        return Delay(fs, delay_s=params["delay_s"]).apply
    if name == "dynamics":
        return Dynamics(fs, **params).apply
    raise ValueError(f"{name} is not a transform effect")


def transform_ops(effects: Sequence[tuple[str, EffectsBlock]],
                  fs: float) -> Callable[[np.ndarray], np.ndarray] | None:
    """The column operator of the transform effects among ``effects`` [(name, params)]
    (None: none), as the plant applies them at the rate ``fs`` (with both dynamics and
    a delay, their exact sampled pair form: effects.sampled_pair)."""
    eff = sampled_pair({n: dict(p) for n, p in effects if n in TRANSFORMS}, fs)
    return compose([effect_operator(n, fs, p) for n, p in eff.items()])


class _Chain:
    """Operators applied in turn (a class, not a closure: a diagnosis crosses a process
    boundary, see ``diagnose``)."""

    def __init__(self, ops: Sequence[Callable[[np.ndarray], np.ndarray]]) -> None:
        self.ops = ops

    def __call__(self, X: np.ndarray) -> np.ndarray:
        for o in self.ops:
            X = o(X)
        return X


def compose(ops: Sequence[Callable[[np.ndarray], np.ndarray] | None]
            ) -> Callable[[np.ndarray], np.ndarray] | None:
    """The operators (None left out) applied in turn; None when there is none."""
    kept = [o for o in ops if o is not None]
    if not kept:
        return None
    return kept[0] if len(kept) == 1 else _Chain(kept)


def identity(X: np.ndarray) -> np.ndarray:
    """No operator: the columns as they are."""
    return X
