"""piezo_stage: Duhem-model identification and control of 2-axis piezo stages.

From the bottom up: the numerical core (:mod:`piezo_stage.core`, pure numpy/scipy,
never ROS); records and files (:mod:`piezo_stage.io`); the stage backends
(:mod:`piezo_stage.drivers`); the ROS 2 nodes, thin shells over those
(:mod:`piezo_stage.nodes`); the launcher (:mod:`piezo_stage.launcher`); the
applications that run the node set and the offline studies (:mod:`piezo_stage.apps`);
the ``piezo-stage`` command (:mod:`piezo_stage.cli`). The benchmarks are the
workbench beside the package (the checkout's ``benchmarks/``, not installed), which
``piezo-stage bench`` runs from a checkout. Each folder imports only from those below it
(test/test_lint.py).
"""

__version__ = "0.1.0"

from piezo_stage.process.rosidl_runtime import runtime_only as _runtime_only

_runtime_only()  # the message packages' import without their code generator
del _runtime_only
