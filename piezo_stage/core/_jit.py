"""How the core compiles its sequential loops, and what every kernel shares.

The Duhem recursion is sequential in time, so numpy cannot vectorise it; numba compiles
such loops to machine code (``njit``: cached on disk, releasing the GIL). The kernels
live next to the job that uses them: ``core/model/_kernels.py`` (the Duhem law, the
plant, the play operators, the exact inverse, the effects' columns) and
``core/estimation/_kernels.py`` (the identification's objectives and regressors, the
gap's holds). With numba switched off (``NUMBA_DISABLE_JIT=1``, or numba missing) every
kernel runs as its plain-Python original: ``bench plant`` times that as its baseline.
"""

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]  # float64 arrays: what every kernel takes
I64 = NDArray[np.int64]

try:  # numba is a declared dependency; the fallback keeps the core importable without it
    from numba import njit as _njit

    def njit(fn: Callable) -> Callable:
        """Compile ``fn`` (cached on disk, releasing the GIL)."""
        return _njit(cache=True, nogil=True)(fn)

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only on installs without numba
    def njit(fn: Callable) -> Callable:
        """Without numba: ``fn`` itself, as its plain-Python original."""
        fn.py_func = fn  # type: ignore[attr-defined]
        return fn

    HAVE_NUMBA = False


# A branch row's layout, as every kernel takes it: PREFIX numbers, then the polynomial's
# coefficients (lowest power first). The prefix: [lo, hi, h(lo), slope below lo,
# h(hi), slope above hi], computed once per model (duhem.branch_row).
PREFIX = 6


def as_f64(x: ArrayLike) -> F64:
    """Contiguous float64 view/copy for the kernels."""
    return np.ascontiguousarray(x, dtype=np.float64)


