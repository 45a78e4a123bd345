"""The package's install metadata as a ROS machine meets it: every package.xml key is one
rosdep resolves, the optional hardware packages are no hard dependency, and the node
executables come from one list (the install itself is run by test_nodes.py)."""

import ast
import os
import xml.etree.ElementTree as ET

import pytest

from conftest import ROOT

# ROS 2 Jazzy packages (rosdep resolves them from the distribution file)
ROS_PACKAGES = {
    "rclpy", "rcl_interfaces", "builtin_interfaces", "rosgraph_msgs", "std_msgs",
    "std_srvs", "geometry_msgs", "sensor_msgs", "trajectory_msgs", "diagnostic_msgs",
    "lifecycle_msgs",  # (ros2/rcl_interfaces, as rcl_interfaces itself)
    "rosidl_generator_py",  # (ros2/rosidl_python: every Python message package's)
    "ament_index_python", "launch", "launch_ros",
}
# The keys we use, each found in rosdistro's rosdep/python.yaml (read 2026-11-25 from a
# 2025 copy of ros/rosdistro: the fork InvincibleRMC/rosdistro at 30d139d7). Not there,
# so never to be used: python3-mcap-pip, python3-foxglove-sdk-pip, python3-nidaqmx-pip,
# python3-threadpoolctl, python3-numpydoc.
ROSDEP_PYTHON_KEYS = {
    "python3-numpy", "python3-scipy", "python3-yaml", "python3-numba",
    "python3-matplotlib", "python3-rosbags-pip", "python3-tqdm", "python3-websockets",
    "python3-pytest", "python3-ruff-pip",
}
# hardware / speed only: never a hard dependency
OPTIONAL = ("nidaqmx", "pipython", "nv200", "threadpoolctl")


def _depends():
    root = ET.parse(os.path.join(ROOT, "package.xml")).getroot()
    return [(e.tag, e.text.strip()) for e in root
            if e.tag.endswith("depend") and e.text]


def test_every_package_xml_key_is_one_rosdep_resolves():
    unknown = [key for _, key in _depends()
               if key not in ROS_PACKAGES and key not in ROSDEP_PYTHON_KEYS]
    assert not unknown, f"rosdep has no key for {unknown}"


def test_optional_hardware_packages_are_no_hard_dependency():
    keys = " ".join(key for _, key in _depends())
    assert not any(name in keys for name in OPTIONAL), keys
    setup = open(os.path.join(ROOT, "setup.py")).read()
    tree = ast.parse(setup)
    requires = next(kw.value for node in ast.walk(tree) if isinstance(node, ast.Call)
                    for kw in node.keywords if kw.arg == "install_requires")
    assert not any(name in ast.literal_eval(el) for el in requires.elts
                   for name in ("nidaqmx", "pipython", "nv200"))


def test_one_executable_script_per_node_and_no_node_console_script():
    from piezo_stage.nodes import NODES
    scripts = os.path.join(ROOT, "scripts")
    assert sorted(os.listdir(scripts)) == sorted(NODES)
    for n in NODES:
        path = os.path.join(scripts, n)
        assert os.access(path, os.X_OK), path
        assert f"-m piezo_stage.nodes.{n}_node " in open(path).read(), path
    setup = open(os.path.join(ROOT, "setup.py")).read()
    assert '"console_scripts": ["piezo-stage = piezo_stage.__main__:main"]' in setup


def test_without_mcap_a_bag_command_says_what_to_install(tmp_path):
    """rosdep cannot install mcap: a bag command on a machine without it says the pip
    line in one line and exits 2 (no traceback, no 'unreadable bag')."""
    import subprocess
    import sys
    (tmp_path / "b").mkdir()
    code = ("import sys; sys.modules['mcap'] = None; "  # as if not installed
            "sys.argv = ['piezo-stage', 'identify', sys.argv[1]]; "
            "from piezo_stage.__main__ import main; main()")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "b")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "pip install mcap" in r.stderr and "unreadable" not in r.stderr, r.stderr


# imported, but with no rosdep key: the "ROS install" pip line (docs/nodes.md) installs them
PIP_ONLY = {"mcap": "mcap", "foxglove": "foxglove-sdk", "threadpoolctl": "threadpoolctl",
            "nidaqmx": "nidaqmx", "pipython": "pipython", "nv200": "nv200",
            "distributed": "distributed"}


# imported only by a benchmark's peer (piezo_stage/apps/studies/sparse_peer.py, which says
# so when it is missing): in setup.py's test extra, never a run dependency
BENCH_ONLY = {"pysindy": "pysindy"}


def test_package_xml_declares_what_the_code_imports():
    """Every third-party module the package imports has an exec_depend (a rosdep key),
    or has no key and is on the docs' pip line for ROS installs, or serves only a
    benchmark and is in the test extra."""
    import sys
    deps = {key for tag, key in _depends() if tag == "exec_depend"}
    key = {"numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml",
           "numba": "python3-numba", "matplotlib": "python3-matplotlib",
           "tqdm": "python3-tqdm", "rosbags": "python3-rosbags-pip",
           "websockets": "python3-websockets"}
    std = set(sys.stdlib_module_names) | {"piezo_stage", "piezo_stage_msgs_adapters",
                                          "benchmarks"}
    files = [os.path.join(d, f) for base in ("piezo_stage", "piezo_stage_msgs_adapters",
                                             "launch", "benchmarks")
             for d, _, fs in os.walk(os.path.join(ROOT, base)) for f in fs
             if f.endswith(".py")]
    used = set()
    for f in files:
        for node in ast.walk(ast.parse(open(f).read())):
            if isinstance(node, ast.Import):
                used |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                used.add(node.module.split(".")[0])
    missing = sorted(m for m in used - std - set(PIP_ONLY) - set(BENCH_ONLY)
                     if key.get(m, m) not in deps)
    assert not missing, missing
    setup = open(os.path.join(ROOT, "setup.py")).read()
    test_extra = setup[setup.index('"test": ['):]
    test_extra = test_extra[:test_extra.index("]")]
    for module, package in BENCH_ONLY.items():
        assert f'"{package}' in test_extra and package not in deps, package
    docs = open(os.path.join(ROOT, "docs", "nodes.md")).read()
    pip_lines = [line for line in docs.splitlines() if line.strip().startswith("pip install")]
    for module, package in PIP_ONLY.items():
        assert module not in used or any(package in line for line in pip_lines), package


@pytest.mark.slow
def test_dev_sh_sets_up_a_fresh_checkout_for_the_demo_alone(tmp_path):
    """A new user's first `./dev.sh`: a fresh copy of the tracked files gets its .venv
    with uv (fetched into .venv/tools unless one is on PATH), the ROS extra and not
    the test tools, and runs the command; the second call installs nothing."""
    import subprocess
    import sys
    src = tmp_path / "checkout"
    subprocess.run(f"git -C {ROOT} ls-files -z | (cd {ROOT} && xargs -0 tar -cf -) | "
                   f"(mkdir -p {src} && tar -xf - -C {src})", shell=True, check=True)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("VIRTUAL_ENV", "PIEZO_STAGE_", "PYTHON"))}
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                  if not p.startswith(os.path.dirname(sys.executable)))
    r = subprocess.run(["./dev.sh", "--version"], cwd=src, env=env, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0 and r.stdout.strip() == "piezo-stage 0.1.0", r
    venv = src / ".venv"
    assert (venv / ".piezo_stage_install_stamp").read_text().split()[1] == "ros"
    import shutil
    assert shutil.which("uv", path=env["PATH"]) or (venv / "tools" / "bin" / "uv").exists()
    have = lambda m: subprocess.run([str(venv / "bin" / "python"), "-c", f"import {m}"],  # noqa: E731
                                    capture_output=True).returncode == 0
    assert have("rclpy") and have("piezo_stage.core.model.duhem")
    assert not have("pytest")  # the demo's set-up leaves the test tools out
    # what the package's processes use is compiled once here (piezo_stage.process.warm): the
    # bytecode of what they import, the kernels of the demo's set and of identify
    site = next((venv / "lib").glob("python3*/site-packages"))
    assert list((site / "rclpy" / "__pycache__").glob("node.*.pyc"))
    # installed as requirements.lock pins it (dev.sh's set-up used the lock)
    from importlib.metadata import distributions

    from packaging.utils import canonicalize_name
    got = {canonicalize_name(d.metadata["Name"]): d.version
           for d in distributions(path=[str(site)])}
    pins = _lock_pins()
    assert {n: got.get(n) for n in pins} == pins
    kernels = {p.name.split(".")[1].rsplit("-", 1)[0]
               for p in (src / "piezo_stage" / "core").glob("*/__pycache__/_kernels.*.nbi")}
    assert {"plant_run", "stage_inverse_step", "stage_inverse_ahead",
            "duhem_regressors"} <= kernels, kernels
    stamp = (venv / ".piezo_stage_install_stamp").stat().st_mtime
    again = subprocess.run(["./dev.sh", "--version"], cwd=src, env=env, capture_output=True,
                           text=True, timeout=120)
    assert again.returncode == 0 and again.stderr == ""
    assert (venv / ".piezo_stage_install_stamp").stat().st_mtime == stamp
    # a lock not of this setup.py (a requirement changed, ./dev.sh lock not run) is left
    # aside: uv resolves setup.py, which the installed tqdm satisfies (the stale lock's
    # older release of it, installed, would replace it)
    lock = (src / "requirements.lock").read_text()
    (src / "requirements.lock").write_text(
        lock.replace("# setup.py sha256 ", "# setup.py sha256 0").replace(
            f"tqdm=={pins['tqdm']}", "tqdm==4.66.1"))
    stale = subprocess.run(["./dev.sh", "--version"], cwd=src, env=env,
                           capture_output=True, text=True, timeout=600)
    assert stale.returncode == 0 and stale.stdout.strip() == "piezo-stage 0.1.0", stale
    assert (venv / ".piezo_stage_install_stamp").stat().st_mtime > stamp
    tqdm = subprocess.run([str(venv / "bin" / "python"), "-c",
                           "import importlib.metadata as m; print(m.version('tqdm'))"],
                          capture_output=True, text=True)
    assert tqdm.stdout.strip() == pins["tqdm"], tqdm


def _lock_pins():
    """requirements.lock's pins for this Python: {normalized name: version}."""
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name
    pins = {}
    with open(os.path.join(ROOT, "requirements.lock")) as fh:
        for line in fh:
            if line.strip() and not line.startswith("#"):
                r = Requirement(line.strip())
                if r.marker is None or r.marker.evaluate():
                    (spec,) = r.specifier
                    assert spec.operator == "==", line
                    pins[canonicalize_name(r.name)] = spec.version
    return pins


def test_the_lock_is_setup_py_s_and_pins_each_of_its_requirements():
    """requirements.lock (dev.sh installs it for the demo and the commands) names the
    setup.py it was written from, and pins a release within each of that file's
    requirements and its ROS extra's: a setup.py changed without ``./dev.sh lock``
    fails here before a user's install falls back to resolving it."""
    import hashlib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name
    with open(os.path.join(ROOT, "setup.py"), "rb") as fh:
        digest = hashlib.sha256(fh.read()).hexdigest()
    with open(os.path.join(ROOT, "requirements.lock")) as fh:
        head = fh.read(1000)
    assert f"# setup.py sha256 {digest}\n" in head, "requirements.lock: run ./dev.sh lock"
    tree = ast.parse(open(os.path.join(ROOT, "setup.py")).read())
    kws = {kw.arg: kw.value for node in ast.walk(tree) if isinstance(node, ast.Call)
           for kw in node.keywords}
    wanted = ast.literal_eval(kws["install_requires"]) + \
        ast.literal_eval(kws["extras_require"])["ros"]
    pins = _lock_pins()
    for req in map(Requirement, wanted):
        name = canonicalize_name(req.name)
        assert name in pins, f"requirements.lock has no {name}"
        assert req.specifier.contains(pins[name], prereleases=True), (req, pins[name])
    assert "piezo-stage" not in pins and "pytest" not in pins  # (the tests' tools: no)


def test_warm_up_takes_one_known_part():
    """``python -m piezo_stage.process.warm`` (run by dev.sh) refuses anything but its parts."""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "piezo_stage.process.warm", "everything"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "modules, stage, inverse" in r.stderr, r
