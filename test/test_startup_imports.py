"""What a process pays to start: the message packages import without their generator's
code-generation half (piezo_stage/process/rosidl_runtime.py), the launcher reads its
configuration without the model core, and a node's process maps its modules for rclpy's
logger and freezes its imports' objects before its start gate (nodes/_executor.py)."""

import os
import subprocess
import sys

from conftest import ROOT

ENV = dict(os.environ, PYTHONPATH=ROOT)


def _run(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_messages_import_without_the_generators_code_generation():
    out = _run(
        "import sys, piezo_stage\n"
        "import rclpy\n"
        "from rclpy.type_support import check_for_type_support\n"
        "from diagnostic_msgs.msg import DiagnosticArray\n"
        "from sensor_msgs.msg import JointState\n"
        "from rclpy.serialization import serialize_message, deserialize_message\n"
        "for t in (DiagnosticArray, JointState):\n"
        "    check_for_type_support(t)\n"
        "m = JointState(name=['x'], position=[1.5])\n"
        "assert deserialize_message(serialize_message(m), JointState).position[0] == 1.5\n"
        "try:\n"
        "    from rosidl_generator_py import generate_py\n"
        "    print('generator imported')\n"
        "except ImportError:\n"
        "    pass\n"
        "print(sorted(k for k in ('lark', 'em', 'rosidl_parser.parser', "
        "'rosidl_generator_py.generate_py_impl') if k in sys.modules))\n"
        "from piezo_stage.process.rosidl_runtime import runtime_only\n"
        "print(runtime_only())\n")
    assert out.splitlines() == ["[]", "False"], out  # (once in place: a no-op)


def test_the_package_imported_after_the_generator_leaves_it_whole():
    out = _run("import rosidl_generator_py\n"
               "import piezo_stage\n"
               "from rosidl_generator_py import generate_py, import_type_support\n"
               "print(callable(generate_py) and callable(import_type_support))\n")
    assert out == "True"


def test_the_launcher_reads_its_configuration_without_the_model_core():
    out = _run("import sys\n"
               "from piezo_stage.launcher.launcher import read_parameters\n"
               "from piezo_stage.paths import default_config\n"
               "p = read_parameters(default_config('stage.yaml'))\n"
               "print(bool(p), [m for m in ('piezo_stage.io.model_file', "
               "'piezo_stage.core.model.model_doc') if m in sys.modules])\n")
    assert out == "True []", out


def test_a_node_process_maps_its_modules_and_freezes_its_imports_before_the_gate():
    out = _run("import gc, inspect, sys\n"
               "from piezo_stage.nodes import _executor as E\n"
               "E.warm_caller_lookup()\n"
               "print(len(inspect.modulesbyfile) >= len(sys.modules) // 2, "
               "inspect.getabsfile(E) in inspect.modulesbyfile)\n"
               "src = inspect.getsource(E.run_nodes)\n"
               "gate = src.index('await_start_gate()')\n"
               "print(all(0 <= src.find(s) < gate for s in ('warm_caller_lookup()', "
               "'gc.collect()', 'gc.freeze()', 'preload_type_support()')))\n")
    assert out.splitlines() == ["True True", "True"], out
