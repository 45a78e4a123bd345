"""The core must import and run with ROS absent: rclpy and *_msgs blocked."""

import os
import subprocess
import sys

from conftest import ROOT

BLOCKER = r"""
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        top = name.split('.')[0]
        if top == 'rclpy' or top.endswith('_msgs') or top.startswith('rcl') \
                or name.startswith('piezo_stage.nodes') or top == 'piezo_stage_msgs_adapters':
            raise ImportError('blocked for this test: ' + name)
sys.meta_path.insert(0, Block())
import pkgutil, importlib
import piezo_stage.core as core
mods = [m.name for m in pkgutil.walk_packages(core.__path__, 'piezo_stage.core.')]
for m in mods:
    importlib.import_module(m)
import piezo_stage.io.model_file, piezo_stage.io.plant_file, piezo_stage.io.csv_table
import numpy as np
from piezo_stage.io.plant_file import load_plant_config, default_plant_config_path
from piezo_stage.core.model.plant import Plant
p = Plant(load_plant_config(default_plant_config_path()), 1000.0)
w = p.run(np.linspace(0, 100, 50), np.zeros(50))
assert w['x'][-1] > 10
bad = [m for m in sys.modules if m.split('.')[0] == 'rclpy' or m.endswith('_msgs')]
assert not bad, bad
print('core-ok', len(mods))
"""


def test_core_imports_and_runs_without_ros():
    env = dict(os.environ, PYTHONPATH=ROOT)
    r = subprocess.run([sys.executable, "-c", BLOCKER], capture_output=True, text=True,
                       env=env, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "core-ok" in r.stdout


def test_core_sources_do_not_import_ros():
    core = os.path.join(ROOT, "piezo_stage", "core")
    for dirpath, _, files in os.walk(core):
        for f in files:
            if f.endswith(".py"):
                src = open(os.path.join(dirpath, f)).read()
                # layers point down: the core imports no io, cli, launch, drivers, nodes,
                # messages or ROS
                for bad in ("import rclpy", "from rclpy", "_msgs", "piezo_stage.nodes",
                            "piezo_stage.io", "piezo_stage.cli", "piezo_stage.launcher",
                            "piezo_stage.drivers", "piezo_stage.apps.experiments"):
                    assert bad not in src, (f, bad)
