"""Progress of the long commands (identify, gap, study, bench), drawn by tqdm on a
terminal only: piped or redirected output stays clean. The core takes plain callbacks;
this module turns them into bars."""

from __future__ import annotations

import sys


def bar(desc: str, total: float | None = None, unit: str = "it"):
    """A tqdm bar on stderr, disabled unless stderr is a terminal (a context manager)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit=unit, leave=False, file=sys.stderr,
                disable=not sys.stderr.isatty(), dynamic_ncols=True)


def best_so_far(b):
    """A solver callback ``(iteration, best, label="")`` that advances bar ``b`` and
    shows the best objective so far."""
    def cb(it, best, label=""):
        b.set_postfix_str(f"{label + ' ' if label else ''}best {best:.5g} um", refresh=False)
        b.update(max(int(it) - b.n, 0))
    return cb


def steps(b):
    """A callback ``(what)`` that advances bar ``b`` by one and names the step."""
    def cb(what=""):
        if what:
            b.set_postfix_str(str(what), refresh=False)
        b.update(1)
    return cb
