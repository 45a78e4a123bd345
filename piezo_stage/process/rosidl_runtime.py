"""The ROS message packages' runtime import, without their code generator.

Every generated message module imports ``rosidl_generator_py`` for its one runtime
function, ``import_type_support``. The package's ``__init__`` also imports its code
generator (``generate_py_impl``: empy, lark and the IDL parser), which a running
process never calls: CPU in every process that imports a message (each node, the launcher's
look for a running set, the recorder), paid at once by the set's processes as it
starts (`bench startup` measures it).

``runtime_only()`` puts the package in ``sys.modules`` with that function alone, before
any message is imported; its submodules import as before, and ``from
rosidl_generator_py import generate_py`` raises ImportError, which the package's own
``__init__`` allows for. A no-op where the package is imported already or is not
installed.
"""

from __future__ import annotations

import importlib.util
import sys
import types

PACKAGE = "rosidl_generator_py"


def runtime_only() -> bool:
    """The package with its runtime function alone, where it is not imported yet:
    True where this put it in place."""
    if PACKAGE in sys.modules:
        return False
    try:
        spec = importlib.util.find_spec(PACKAGE)
    except (ImportError, ValueError):
        return False
    if spec is None or not spec.submodule_search_locations:
        return False
    module = types.ModuleType(PACKAGE, "rosidl_generator_py's runtime import alone "
                                       "(piezo_stage.process.rosidl_runtime)")
    module.__spec__, module.__file__ = spec, spec.origin
    module.__path__ = list(spec.submodule_search_locations)
    sys.modules[PACKAGE] = module
    try:
        from rosidl_generator_py.import_type_support_impl import import_type_support
    except ImportError:  # another layout: the package's own import instead
        del sys.modules[PACKAGE]
        return False
    module.import_type_support = import_type_support  # type: ignore[attr-defined]
    module.__all__ = ["import_type_support"]  # type: ignore[attr-defined]
    return True
