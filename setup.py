"""ament_python package that also installs with plain pip.

The one command on the user's PATH is ``piezo-stage``. The node executables are
installed where ROS looks for them, ``<prefix>/lib/piezo_stage/<node>`` (``ros2 run
piezo_stage <node>``), as data files: so pip (a wheel, whose console scripts all go to
bin/) and colcon (``setup.py install``, whose scripts setup.cfg sends to lib/piezo_stage)
install them to the same place, and no node name (controller, recorder, gap...) lands on
PATH. Each is a small shell script, scripts/<node>, that runs ``python -m
piezo_stage.nodes.<node>_node`` with the prefix's own Python when it has one (a virtual
environment), else ``python3`` (a ROS install).
"""

from glob import glob

from setuptools import find_packages, setup

package_name = "piezo_stage"

def _nodes():
    """piezo_stage.nodes.NODES, read without importing the package (it needs rclpy)."""
    import ast
    import os
    here = os.path.dirname(os.path.abspath(__file__))
    with open(os.path.join(here, "piezo_stage", "nodes", "__init__.py")) as fh:
        tree = ast.parse(fh.read())
    for node in tree.body:
        if isinstance(node, ast.Assign) and node.targets[0].id == "NODES":
            return list(ast.literal_eval(node.value))
    raise RuntimeError("piezo_stage/nodes/__init__.py has no NODES")


NODES = _nodes()

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["piezo_stage", "piezo_stage.*",
                                    "piezo_stage_msgs_adapters",
                                    "piezo_stage_msgs_adapters.*"]),
    # the real-time set's Fast DDS profile (piezo_stage/launcher/launcher.py)
    package_data={"piezo_stage.launcher": ["*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
        ("lib/" + package_name, [f"scripts/{n}" for n in NODES]),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "pyyaml>=6",
        "numba>=0.58",
        "mcap>=1.1",
        "matplotlib>=3.7",
        "rosbags>=0.10",
        "tqdm>=4.60",  # progress of the long commands, on a terminal only
        "threadpoolctl>=3",  # the gap diagnosis: one BLAS thread per axis (optional in code)
    ],
    extras_require={
        # rclpy and the messages come from the ros-jazzy-* wheels; a full ROS install
        # provides them instead, so they are an extra rather than a hard requirement.
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces",
                # the live view node, and the client bench liveview watches it with
                "foxglove-sdk>=0.30", "websockets>=12"],
        "daq": ["nidaqmx>=1.0"],
        # refit --scheduler: an archive's bags on a Dask distributed cluster
        "dask": ["dask>=2024.1", "distributed>=2024.1"],
        "pi": ["pipython>=2.10"],
        # (nv200, for backend nv200, declares Python >= 3.12 and runs on 3.11: no extra
        # pip would honour here; dev.sh installs it with --ignore-requires-python)
        # the tests import the real nidaqmx (it installs without NI hardware) and run
        # the daq backend on it with only NI's driver layer replaced (the test double)
        # (and ruff and numpydoc: the suite runs the linters, test/test_lint.py)
        # (pytest-xdist: two workers, each test on its own ROS domain; pytest-timeout: a
        # hung test fails with every thread's stack instead of hanging the suite)
        # (hypothesis: the trajectory decoder against rclpy's own, on generated messages)
        # (wheel, setuptools: the install-layout tests build our wheel and a colcon-style
        # install without build isolation; a venv uv made has no setuptools of its own)
        # (pysindy: the sparse hysteresis peer that bench identify compares with)
        # (pipython: the pi backend on PI's real package, against a controller double)
        # (mypy: the type checker, on the layers setup.cfg's [mypy] lists)
        # (dask, distributed: refit --scheduler against a LocalCluster of processes)
        "test": ["pytest>=7", "pytest-xdist>=3.5", "pytest-timeout>=2.2", "nidaqmx>=1.0",
                 "pipython>=2.10",
                 "ruff>=0.5", "numpydoc>=1.6", "hypothesis>=6.90",
                 "wheel>=0.40", "setuptools>=61", "pysindy>=2.0", "mypy>=1.10",
                 "dask>=2024.1", "distributed>=2024.1"],
    },
    zip_safe=True,
    maintainer="piezo_stage developers",
    maintainer_email="dev@piezo-stage.local",
    description="Duhem hysteresis identification and control of 2-axis piezo stages",
    license="Apache-2.0",
    entry_points={
        "console_scripts": ["piezo-stage = piezo_stage.__main__:main"],
    },
)
