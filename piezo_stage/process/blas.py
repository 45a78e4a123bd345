"""One BLAS thread for the command line's numerical work, unless the user chose.

Our least-squares problems are tall and narrow (tens of thousands of samples by 10-40
regressors, solved hundreds of times in a search): OpenBLAS's threads cost more than
they bring there. With one thread here a one-axis gap diagnosis took 1.35 s instead of
2.96 s and a fast identification 0.27 s instead of 0.36 s, and `refit`'s worker
processes stopped fighting over the cores (docs/benchmarks.md). Set before numpy is
imported, so it holds for this process and the node processes a command starts.
"""

from __future__ import annotations

import os

VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_thread_unless_set() -> None:
    """OPENBLAS_NUM_THREADS=1 when none of VARIABLES is set (the user's choice wins)."""
    if not any(v in os.environ for v in VARIABLES):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
