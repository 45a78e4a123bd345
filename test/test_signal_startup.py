"""A SIGINT in the interpreter's own start-up (site, runpy, a package's ``__init__``)
meets Python's handler, not ours: the stress run tells that apart from a handler that
missed by the traceback's frames, read against the real source files."""

import os
import signal
import subprocess
import sys

import piezo_stage.nodes.trajectory_node as traj
from benchmarks.signals import Trial, before_our_handlers


def _line(path, text):
    with open(path) as fh:
        return next(i for i, ln in enumerate(fh, 1) if text in ln)


def _traceback(*frames):
    body = "".join(f'  File "{p}", line {n}, in {f}\n    x\n' for p, n, f in frames)
    return f"Traceback (most recent call last):\n{body}KeyboardInterrupt\n"


RUNPY = ("<frozen runpy>", 198, "_run_module_as_main")
NODE = traj.__file__


def test_frames_before_the_handlers_are_python_s_own_and_any_later_one_is_not():
    signals_line = _line(NODE, "import piezo_stage.process.signals")
    numpy_line = _line(NODE, "import numpy as np")
    assert before_our_handlers(_traceback(RUNPY, ("<frozen importlib._bootstrap>", 1, "_find")))
    # the node module's line that imports the handlers, and that module's top level
    handlers = os.path.join(os.path.dirname(os.path.dirname(NODE)), "process", "signals.py")
    assert before_our_handlers(_traceback(RUNPY, (NODE, signals_line, "<module>"),
                                          (handlers, 40, "<module>")))
    pkg_init = os.path.join(os.path.dirname(NODE), "__init__.py")
    assert before_our_handlers(_traceback(RUNPY, (pkg_init, 9, "<module>")))
    # past that line the handlers are in: a KeyboardInterrupt there is a miss
    assert not before_our_handlers(_traceback(RUNPY, (NODE, numpy_line, "<module>")))
    executor = os.path.join(os.path.dirname(NODE), "_executor.py")
    assert not before_our_handlers(_traceback(RUNPY, (NODE, 140, "main"),
                                              (executor, 203, "spin")))
    assert not before_our_handlers("KeyboardInterrupt\n")  # no traceback: not this case


def test_the_message_runtime_the_package_init_sets_up_is_start_up_too():
    """A SIGINT 0.11 s after the launcher's start landed in the import of the message
    packages' runtime, which the package's __init__ runs (rosidl_runtime.runtime_only)
    before any entry module can install the handlers. Its frames, as printed there; a
    frame of the package past them is still a miss."""
    pkg = os.path.dirname(os.path.dirname(NODE))
    start = [RUNPY, (os.path.join(pkg, "__init__.py"), 17, "<module>"),
             (os.path.join(pkg, "rosidl_runtime.py"), 43, "runtime_only"),
             (os.path.join(sys.prefix, "lib", "python3.11", "site-packages", "rpyutils",
                           "import_c_library.py"), 18, "<module>"),
             ("/usr/lib/python3.11/typing.py", 1253, "_is_dunder")]
    assert before_our_handlers(_traceback(*start))
    assert not before_our_handlers(_traceback(
        *start[:3], (os.path.join(pkg, "io", "bag.py"), 10, "<module>")))


def test_an_editable_installs_finder_run_by_site_is_start_up_too():
    """A SIGINT 0.11 s after the launcher's start landed in the
    editable install's finder, which site imports from a .pth line (its file name holds
    the package's name, but it is site-packages', not ours): "Fatal Python error:
    init_import_site", exit 1, nothing of ours had run. Its frames, as printed there."""
    site_packages = os.path.join(sys.prefix, "lib", "python3.11", "site-packages")
    finder = os.path.join(site_packages, "__editable___piezo_stage_0_1_0_finder.py")
    text = ("Fatal Python error: init_import_site: Failed to import the site module\n"
            + _traceback(("<frozen importlib._bootstrap>", 1176, "_find_and_load"),
                         ("<frozen site>", 186, "addpackage"), ("<string>", 1, "<module>"),
                         (finder, 7, "<module>"),
                         ("/usr/lib/python3.11/urllib/parse.py", 331, "<module>")))
    assert before_our_handlers(text)
    t = Trial("launcher", 0.11, signal.SIGINT, False, rc=1, stop_s=0.02, traceback=True,
              text=text)
    assert t.python_startup and t.ok
    # the same stack reaching into one of our modules past its handlers is a miss
    numpy_line = _line(NODE, "import numpy as np")
    assert not before_our_handlers(text.replace(
        'KeyboardInterrupt', f'  File "{NODE}", line {numpy_line}, in <module>\n    x\n'
        'KeyboardInterrupt'))


def test_a_sigint_during_site_ends_the_process_at_once_and_is_told_apart(tmp_path):
    """A sitecustomize that signals its own process stands for a SIGINT landing while
    site runs; a trial judged on that real output is Python's start-up, not a miss."""
    (tmp_path / "sitecustomize.py").write_text(
        "import os, signal\nos.kill(os.getpid(), signal.SIGINT)\n")
    env = dict(os.environ, PYTHONPATH=str(tmp_path))
    r = subprocess.run([sys.executable, "-m", "piezo_stage.nodes.trajectory_node"],
                       env=env, capture_output=True, text=True, timeout=30)
    assert r.returncode != 0 and "KeyboardInterrupt" in r.stderr, r.stderr
    t = Trial("trajectory", 0.0, signal.SIGINT, False, rc=r.returncode, stop_s=0.0,
              traceback="Traceback" in r.stderr, text=r.stderr)
    assert t.python_startup and t.ok, r.stderr
    # the same text for a SIGTERM is not this case (Python has no SIGTERM handler)
    assert not Trial("trajectory", 0.0, signal.SIGTERM, False, rc=r.returncode,
                     stop_s=0.0, text=r.stderr).python_startup
