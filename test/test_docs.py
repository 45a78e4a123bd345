"""The README and docs/ stay true to the tree: links resolve, commands exist, the
parameter blocks they show are what the nodes declare, the README stays short."""

import os
import re

import pytest
import yaml

from conftest import ROOT

DOCS = os.path.join(ROOT, "docs")
PAGES = ["README.md"] + [os.path.join("docs", f) for f in sorted(os.listdir(DOCS))
                         if f.endswith(".md")]


def _text(page):
    return open(os.path.join(ROOT, page), encoding="utf-8").read()


def _anchors(text):
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
            for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}


def test_readme_is_short_and_links_every_docs_page():
    readme = _text("README.md")
    assert len(readme.splitlines()) <= 150
    for page in PAGES[1:]:
        assert f"]({page})" in readme, page


@pytest.mark.parametrize("page", PAGES)
def test_links_resolve_to_files_and_headings(page):
    text = _text(page)
    base = os.path.dirname(os.path.join(ROOT, page))
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if target.startswith(("http://", "https://")):
            continue
        path, _, anchor = target.partition("#")
        full = os.path.normpath(os.path.join(base, path)) if path else \
            os.path.join(ROOT, page)
        assert os.path.exists(full), (page, target)
        if anchor:
            assert anchor in _anchors(open(full, encoding="utf-8").read()), (page, target)


@pytest.mark.parametrize("page", PAGES)
def test_every_command_named_exists(page):
    """`piezo-stage WORD` and `bench WORD` in the docs name real subcommands."""
    from benchmarks import BENCHMARKS
    from piezo_stage.cli import COMMANDS
    text = _text(page)
    for word in re.findall(r"piezo-stage ([a-z]+)\b", text):
        assert word in COMMANDS, (page, word)
    for words in re.findall(r"(?:piezo-stage )?bench ((?:[a-z]+\|)*[a-z]+)", text):
        for word in words.split("|"):
            assert word in BENCHMARKS, (page, word)


def test_the_parameter_blocks_shown_are_declared_and_typed_as_declared(tmp_path):
    """The daq block of docs/hardware.md and config/realtime.yaml pass the launcher's
    check, and every value has the declared default's shape (a list where it is one)."""
    from piezo_stage.core.params import defaults as declared
    from piezo_stage.drivers.daq import DAQ_PARAMS
    from piezo_stage.launcher.launcher import read_parameters
    block = re.search(r"```yaml\n(.*?)```", _text("docs/hardware.md"), flags=re.S).group(1)
    path = tmp_path / "daq.yaml"
    path.write_text(block)
    params = read_parameters(str(path))["stage_driver"]
    assert params["backend"] == "daq"
    defaults = declared(DAQ_PARAMS)
    for name, value in params.items():
        if name in defaults:
            assert type(value) is type(defaults[name]), name
            if isinstance(value, list):
                assert len(value) == len(defaults[name]), name
    rt = read_parameters(os.path.join(ROOT, "config", "realtime.yaml"))
    assert rt == {"stage_driver": {"mode": "realtime"}}
    assert yaml.safe_load(block)
