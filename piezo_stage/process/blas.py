"""One BLAS thread for the command line's numerical work, unless the user chose.

Our least-squares problems are tall and narrow (tens of thousands of samples by 10-40
regressors, solved hundreds of times in a search): OpenBLAS's threads cost more than
they bring there: with one thread the gap diagnosis and the fast identification run
faster, and `refit`'s worker processes stop fighting over the cores. Set before numpy is
imported, so it holds for this process and the node processes a command starts.
"""

from __future__ import annotations

import os

VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_thread_unless_set() -> None:
    """OPENBLAS_NUM_THREADS=1 when none of VARIABLES is set (the user's choice wins)."""
    if not any(v in os.environ for v in VARIABLES):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
