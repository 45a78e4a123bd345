"""The linters, run by the test command (as ament_flake8 / ament_pep257 run in a ROS
package's tests): ruff with ruff.toml (pycodestyle and pyflakes at 99 columns, import
order, a docstring on every module), and the first docstring line of every module says
what the module holds (a sentence, not a title)."""

import ast
import os
import shutil
import subprocess
import sys

from conftest import ROOT

PACKAGES = ("piezo_stage", "piezo_stage_msgs_adapters")


def test_ruff_passes():
    ruff = shutil.which("ruff", path=os.path.dirname(sys.executable)) or shutil.which("ruff")
    assert ruff, "ruff is part of the test extra (pip install -e .[test])"
    r = subprocess.run([ruff, "check", "--no-cache", "."], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-1000:]


def _modules():
    for pkg in PACKAGES:
        for dirpath, _, files in os.walk(os.path.join(ROOT, pkg)):
            for f in files:
                if f.endswith(".py"):
                    yield os.path.join(dirpath, f)


def test_every_module_says_what_it_holds():
    short = []
    for path in _modules():
        doc = ast.get_docstring(ast.parse(open(path).read())) or ""
        first = doc.strip().splitlines()[0] if doc.strip() else ""
        if len(first.split()) < 4:
            short.append(os.path.relpath(path, ROOT))
    assert not short, f"modules whose first docstring line does not say what they hold: {short}"
