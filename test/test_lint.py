"""The linters, run by the test command (as ament_flake8 / ament_pep257 run in a ROS
package's tests): ruff with ruff.toml (pycodestyle and pyflakes at 99 columns, import
order, a docstring on every module), mypy on the whole package, and the first
docstring line of every module says
what the module holds (a sentence, not a title)."""

import ast
import os
import shutil
import subprocess
import sys

import pytest

from conftest import ROOT

PACKAGES = ("piezo_stage", "piezo_stage_msgs_adapters", "benchmarks")


def test_ruff_passes():
    ruff = shutil.which("ruff", path=os.path.dirname(sys.executable)) or shutil.which("ruff")
    assert ruff, "ruff is part of the test extra (pip install -e .[test])"
    r = subprocess.run([ruff, "check", "--no-cache", "."], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-1000:]


def test_the_type_checker_passes_on_the_layers_it_covers():
    """mypy over the files setup.cfg's [mypy] lists (both packages, every module): clean.
    Its cache goes to a temporary folder, not the tree."""
    import tempfile
    pytest.importorskip("mypy", reason="mypy is part of the test extra")
    with tempfile.TemporaryDirectory() as cache:
        r = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", cache], cwd=ROOT,
                           capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-1000:]
    assert "Success: no issues found" in r.stdout


def test_the_core_the_nodes_and_the_drivers_annotate_every_function():
    """setup.cfg holds the core, the nodes and the drivers to disallow_untyped_defs, so
    the run above fails on any function of theirs that does not say what it takes and
    gives."""
    import configparser
    cfg = configparser.ConfigParser()
    cfg.read(os.path.join(ROOT, "setup.cfg"))
    for layer in ("core", "nodes", "drivers"):
        assert cfg.getboolean(f"mypy-piezo_stage.{layer}.*", "disallow_untyped_defs"), layer


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


# -- the core's public API: typed, and numpydoc-valid --------------------------------

def _core_public_functions():
    """(module path, qualified name, FunctionDef, TYPE_CHECKING-only names) of every
    public function and method of the core's public modules and of its kernels."""
    core = os.path.join(ROOT, "piezo_stage", "core")
    for dirpath, _, files in os.walk(core):
        for f in sorted(files):
            if not f.endswith(".py") or (f.startswith("_") and f not in (
                    "__init__.py", "_jit.py", "_kernels.py")):
                continue
            path = os.path.join(dirpath, f)
            tree = ast.parse(open(path).read())
            checking = {a.asname or a.name.split(".")[0]
                        for n in ast.walk(tree) if isinstance(n, ast.If)
                        and "TYPE_CHECKING" in ast.dump(n.test)
                        for s in n.body if isinstance(s, (ast.Import, ast.ImportFrom))
                        for a in s.names}

            def visit(node, prefix, private):
                for n in ast.iter_child_nodes(node):
                    if isinstance(n, ast.ClassDef):
                        yield from visit(n, prefix + n.name + ".",
                                         private or n.name.startswith("_"))
                    elif isinstance(n, ast.FunctionDef):
                        dunder = n.name.startswith("__") and n.name.endswith("__")
                        if not private and (dunder or not n.name.startswith("_")):
                            yield path, prefix + n.name, n, checking
            yield from visit(tree, "", False)


def test_core_public_api_and_kernels_are_typed():
    """Every parameter and every result (dunders' results aside) is annotated, and
    every name an annotation uses exists in its module (or is imported for type
    checking only): a typo in a string annotation fails here."""
    import builtins
    import importlib
    missing, unknown = [], []
    for path, name, fn, checking in _core_public_functions():
        rel = os.path.relpath(path, ROOT)
        mod = importlib.import_module(rel[:-3].replace(os.sep, ".").removesuffix(".__init__"))
        a = fn.args
        params = [p for p in a.posonlyargs + a.args + a.kwonlyargs
                  + [x for x in (a.vararg, a.kwarg) if x] if p.arg not in ("self", "cls")]
        missing += [f"{rel}:{name}({p.arg})" for p in params if p.annotation is None]
        dunder = fn.name.startswith("__") and fn.name.endswith("__")
        if fn.returns is None and not dunder:
            missing.append(f"{rel}:{name} -> ?")
        for ann in [p.annotation for p in params] + [fn.returns]:
            for n in ast.walk(ann) if ann is not None else ():
                if isinstance(n, ast.Name) and not (hasattr(mod, n.id) or n.id in checking
                                                    or hasattr(builtins, n.id)):
                    unknown.append(f"{rel}:{name}: {n.id}")
    assert not missing, f"unannotated: {missing}"
    assert not unknown, f"annotations naming what the module does not have: {unknown}"


# numpydoc's checks that every docstring of ours must pass: a docstring with a summary
# starting with a capital letter and ending with a period, and Parameters / Returns
# sections, where a docstring has them, that name real parameters in order with a type
# and a description. Not required: a section for every parameter and result, examples,
# see-also, one-line summaries (PR01, RT01, EX01, SA01, ES01, SS06, GL02), and SS05,
# whose "no third person" heuristic flags noun summaries ("Voltages for ...").
NUMPYDOC_CHECKS = ("GL08", "SS01", "SS02", "SS03", "PR02", "PR03", "PR04", "PR05", "PR06",
                   "PR07", "PR08", "PR09", "PR10", "RT02", "RT03", "RT04", "RT05", "GL01")


def test_core_public_docstrings_pass_numpydoc():
    from numpydoc.validate import validate
    found = []
    names = set()
    for path, name, fn, _ in _core_public_functions():
        rel = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".").removesuffix(".__init__")
        if not name.split(".")[-1].startswith("__"):
            names.add(f"{rel}.{name}")
        if "." in name:  # the class itself
            names.add(f"{rel}.{name.rsplit('.', 1)[0]}")
        names.update(f"{rel}.{c.name}" for c in ast.parse(open(path).read()).body
                     if isinstance(c, ast.ClassDef) and not c.name.startswith("_"))
    for full in sorted(names):
        for code, msg in validate(full)["errors"]:
            if code in NUMPYDOC_CHECKS:
                found.append(f"{full}: {code} {msg}")
    assert len(names) > 150  # the walk found the API
    assert not found, "\n".join(found)


# -- the layout: no private name across modules, no import circle ------------------

def _module_path(name):
    """The file of a dotted module of ours (a package's __init__.py), or None."""
    base = os.path.join(ROOT, *name.split("."))
    for p in (base + ".py", os.path.join(base, "__init__.py")):
        if os.path.exists(p):
            return p
    return None


def _imports(path):
    """(line, module file, names) of every import of our packages in ``path``
    (function-level ones too)."""
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level \
                and node.module.split(".")[0] in PACKAGES:
            yield node.lineno, node.module, [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in PACKAGES:
                    yield node.lineno, a.name, []


def test_no_private_name_is_imported_across_modules():
    """A name with a leading underscore is its module's own: used elsewhere it is a
    public API nobody documented (private modules such as nodes/_params.py are fine:
    their public names are the package's internal API)."""
    bad = []
    for path in _modules():
        for line, module, names in _imports(path):
            for n in names:
                if n.startswith("_") and not n.startswith("__") and \
                        _module_path(f"{module}.{n}") is None:
                    bad.append(f"{os.path.relpath(path, ROOT)}:{line}: {module}.{n}")
    assert not bad, bad


def test_no_import_circle():
    """The modules' imports (function-level ones too) form no circle: each module sits
    on a floor above everything it uses."""
    graph = {}
    for path in _modules():
        deps = set()
        for _, module, names in _imports(path):
            target = _module_path(module)
            subs = [p for p in (_module_path(f"{module}.{n}") for n in names) if p]
            deps |= set(subs) or ({target} if target else set())
        graph[path] = deps - {path}
    index, low, stack, on, circles, counter = {}, {}, [], set(), [], [0]

    def strong(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(os.path.relpath(w, ROOT))
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(comp))
    for v in list(graph):
        if v not in index:
            strong(v)
    assert not circles, circles


# what each folder may import from ours: a layer uses only the layers below it
LAYERS = {
    "piezo_stage/core": set(),
    "piezo_stage_msgs_adapters": {"piezo_stage/core"},
    "piezo_stage/io": {"piezo_stage/core", "piezo_stage_msgs_adapters"},
    "piezo_stage/drivers": {"piezo_stage/core", "piezo_stage/io"},
    "piezo_stage/nodes": {"piezo_stage/core", "piezo_stage/io", "piezo_stage/drivers",
                          "piezo_stage_msgs_adapters"},
    "piezo_stage/launcher": {"piezo_stage/core", "piezo_stage/io", "piezo_stage/nodes"},
    "piezo_stage/apps": {"piezo_stage/core", "piezo_stage/io", "piezo_stage/nodes",
                         "piezo_stage/launcher", "piezo_stage_msgs_adapters"},
    # the workbench beside the package (never installed with it)
    "benchmarks": {"piezo_stage/core", "piezo_stage/io", "piezo_stage/drivers",
                   "piezo_stage/nodes", "piezo_stage/launcher", "piezo_stage/apps",
                   "piezo_stage_msgs_adapters", "piezo_stage/client"},
    # how a process starts, runs and ends (signals, BLAS threads, the first start's
    # compilation, which runs the simulated stage and the inverse to compile them)
    "piezo_stage/process": {"piezo_stage/core", "piezo_stage/io", "piezo_stage/drivers"},
    # the Python client of a running set (a module): rclpy and the adapters, the nodes'
    # QoS; the commands above use it
    "piezo_stage/client": {"piezo_stage/core", "piezo_stage/nodes",
                           "piezo_stage_msgs_adapters"},
}
# small helpers every layer above the core may use (paths, progress bars, the process's
# plumbing)
HELPERS = {"piezo_stage/paths.py", "piezo_stage/progress.py"}
PLUMBING = "piezo_stage/process/"


def _layer(path):
    rel = os.path.relpath(path, ROOT)
    return next((k for k in LAYERS if rel.startswith(k + "/") or rel == k + ".py"), None)


# the core by job: what a stage is, what a record says, what runs each sample; the
# shared pieces (errors, metrics, the compiled kernels) at its top
CORE_JOBS = {"model": set(), "estimation": {"model"}, "loop": {"model"}}


def test_the_core_s_jobs_use_only_the_model_and_the_shared_pieces():
    """core/model imports no other job; core/estimation and core/loop build on the
    model and never on each other, so the loop's per-sample code carries nothing of
    identification and the diagnosis nothing of the loop."""
    core = os.path.join(ROOT, "piezo_stage", "core")
    bad = []
    for path in _modules():
        rel = os.path.relpath(path, core)
        mine = rel.split(os.sep)[0]
        if mine not in CORE_JOBS:
            continue
        for line, module, _ in _imports(path):
            if module.startswith("piezo_stage.core."):
                job = module.split(".")[2]
                if job in CORE_JOBS and job != mine and job not in CORE_JOBS[mine]:
                    bad.append(f"core/{rel}:{line}: {module}")
    assert not bad, "\n".join(bad)
    assert sorted(d for d in os.listdir(core) if os.path.isdir(os.path.join(core, d))
                  and not d.startswith("__")) == sorted(CORE_JOBS)


def test_each_folder_uses_only_the_layers_below_it():
    """library (core; the adapters on it; io on both, for the ROS-free wire reading of
    the bag readers), drivers, nodes, launcher, applications,
    benchmarks, commands: each folder imports only from the folders below it (and the
    root's small helpers), so the tree reads from the bottom up."""
    bad = []
    for path in _modules():
        mine = _layer(path)
        if mine is None:
            continue
        for line, module, names in _imports(path):
            targets = [p for p in (_module_path(f"{module}.{n}") for n in names) if p] \
                or [_module_path(module)]
            for t in filter(None, targets):
                theirs, rel = _layer(t), os.path.relpath(t, ROOT)
                ok = theirs == mine or theirs in LAYERS[mine] or (
                    (rel in HELPERS or rel.startswith(PLUMBING)) and mine != "piezo_stage/core")
                if not ok and not t.endswith(os.path.join("piezo_stage", "__init__.py")):
                    bad.append(f"{os.path.relpath(path, ROOT)}:{line}: {module} ({rel})")
    assert not bad, "\n".join(bad)


def test_no_history_in_the_package_s_code():
    """A comment says why; what was measured, when, on which run, lives in the docs
    (docs/benchmarks.md, docs/realtime.md), generated. No date ("2026-...") and no
    "CI run" anecdote in the package's code."""
    import re
    pattern = re.compile(r"\b20\d\d-\d\d|CI run")
    found = []
    for base, _, files in os.walk(os.path.join(ROOT, "piezo_stage")):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(base, f)
                with open(path, encoding="utf-8") as fh:
                    for i, line in enumerate(fh, 1):
                        if pattern.search(line):
                            found.append(f"{os.path.relpath(path, ROOT)}:{i}: {line.strip()}")
    assert not found, "\n".join(found)


def _functions():
    """(path, function node) of every function and method of the product (the
    workbench, benchmarks/, aside)."""
    for path in _modules():
        if os.path.relpath(path, ROOT).startswith("benchmarks" + os.sep):
            continue
        for node in ast.walk(ast.parse(open(path).read())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield path, node


def test_constructors_take_named_options_not_long_argument_lists():
    """No constructor takes more than 8 parameters (self aside): a longer list is a
    dataclass of options built by keyword (LoopOptions, FeedforwardOptions,
    SearchOptions, LaunchOptions); and at most 3 functions run over 80 lines."""
    long_ctors, long_functions = [], []
    for path, f in _functions():
        a = f.args
        n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + bool(a.vararg) \
            + bool(a.kwarg) - (1 if a.args and a.args[0].arg in ("self", "cls") else 0)
        where = f"{os.path.relpath(path, ROOT)}:{f.lineno} {f.name}"
        if f.name == "__init__" and n > 8:
            long_ctors.append(f"{where}: {n} parameters")
        if f.end_lineno - f.lineno + 1 > 80:
            long_functions.append(f"{where}: {f.end_lineno - f.lineno + 1} lines")
    assert not long_ctors, "\n".join(long_ctors)
    assert len(long_functions) <= 3, "\n".join(long_functions)
