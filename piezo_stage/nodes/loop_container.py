"""The control loop's nodes composed in one process: the stage driver, the feedforward and
the controller, still three nodes on the same topics (ROS's composition), spun on one
``LeanExecutor``.

Apart, each sample crosses three processes: the driver's joint state wakes the
feedforward's process, its reference the controller's, its command the driver's, and on
two cores those wake-ups, not the work, set the pace. Composed, one thread takes each
message as it is published, handed over in the process (``_executor.LocalLinks``: no
middleware between the composed nodes; the recorder still gets every message), so a
lockstep set runs about twice the samples a second, and a real-time set's command is
worked out on one core while the driver's sample clock keeps the other
(docs/realtime.md).

Run as the launcher runs it::

    python -m piezo_stage.nodes.loop_container stage_driver feedforward controller \\
        [--param NODE:NAME:=VALUE ...] --ros-args -r __ns:=/stage --params-file FILE

The ``--ros-args`` are every node's (the namespace, the parameter file whose sections
name the nodes); ``--param`` sets one node's parameter, as ``-p`` sets a lone node's.
"""

# first, before the heavy imports: stop signals work from here on (see process/signals.py)
import piezo_stage.process.signals  # noqa: F401, I001

# isort: split
import sys
from collections.abc import Callable, Sequence
from typing import Any

from rclpy.node import Node

from piezo_stage.nodes._executor import LeanNode, run_nodes

# the nodes that may be composed, in the order they are built (the driver last, as
# the launcher starts it last: its first sample finds the others listening)
COMPOSABLE = ("controller", "feedforward", "stage_driver")


class UsageError(ValueError):
    """The container's own arguments are wrong."""


def parse(argv: list[str]) -> tuple[list[str], dict[str, list[str]], list[str]]:
    """(node names in build order, {node: its -p arguments}, the --ros-args part)."""
    ros = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    own = argv[:len(argv) - len(ros)]
    names: list[str] = []
    params: dict[str, list[str]] = {}
    it = iter(own)
    for a in it:
        if a == "--param":
            spec = next(it, "")
            node, _, rest = spec.partition(":")
            if node not in COMPOSABLE or ":=" not in rest:
                raise UsageError(f"--param {spec!r}: give NODE:NAME:=VALUE, NODE one of "
                                 f"{', '.join(COMPOSABLE)}")
            params.setdefault(node, []).append(rest)
        elif a in COMPOSABLE:
            names.append(a)
        else:
            raise UsageError(f"{a!r}: the loop's nodes are {', '.join(COMPOSABLE)}")
    if not names:
        raise UsageError(f"no node to compose (give some of {', '.join(COMPOSABLE)})")
    names.sort(key=COMPOSABLE.index)
    return names, params, ros


def node_class(name: str) -> type[LeanNode]:
    """The class of the composable node ``name``."""
    if name == "stage_driver":
        from piezo_stage.nodes.stage_driver_node import StageDriver
        return StageDriver
    if name == "feedforward":
        from piezo_stage.nodes.feedforward_node import Feedforward
        return Feedforward
    from piezo_stage.nodes.controller_node import Controller
    return Controller


def factory(name: str, params: list[str]) -> Callable[[], Node]:
    """A builder of node ``name`` with its own ``-p`` arguments over the shared ones."""
    cls: Any = node_class(name)  # a LeanNode that is an rclpy node: node options too
    cli = ["--ros-args"] + [x for p in params for x in ("-p", p)] if params else []

    def build() -> Node:
        return cls(cli_args=cli) if cli else cls()
    build.__name__ = name
    return build


def main(argv: Sequence[str] | None = None) -> int:
    """Build the named nodes and spin them together; the exit code as a node's."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        names, params, ros = parse(list(argv))
    except UsageError as e:
        sys.stderr.write(f"loop_container: {e}\n")
        return 2
    return run_nodes([factory(n, params.get(n, [])) for n in names],
                     [sys.argv[0]] + ros,
                     warm_kernels=any(node_class(n).USES_KERNELS for n in names))


if __name__ == "__main__":
    from piezo_stage.process.stopping import exit_now
    exit_now(main())  # flushed, at-exit work done, no finalization (stopping.py)
