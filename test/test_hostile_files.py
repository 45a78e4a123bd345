"""Hostile and clumsy files and arguments: bounded parsing, strict validation of model
and plant files, outputs that never overwrite inputs, one line and exit 2."""

import os

import numpy as np
import pytest

from benchmarks.faults import ALIAS_BOMB, scaled_model
from conftest import CONFIG, cli, one_line_exit_2
from piezo_stage.core.errors import ModelError
from piezo_stage.io.model_file import load_model, parse_yaml

MODEL = os.path.join(CONFIG, "stage_model.yaml")
GOOD = open(MODEL).read()


BOMB = ALIAS_BOMB


def test_yaml_alias_bomb_is_refused_at_once(tmp_path):
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BOMB)
    with pytest.raises(ModelError, match="aliases"):  # refused, not expanded
        load_model(bomb)
    with pytest.raises(ModelError, match="bytes"):
        parse_yaml("x: 1\n" * 20000, "message", max_bytes=65536)


@pytest.mark.parametrize("edit, why", [
    (lambda t: t.replace("g: [0.36, 0.0006]", "g: [1.0e300, 0.0006]"), "um/V"),
    (lambda t: t.replace("voltage_limits_V: [0.0, 150.0]", "voltage_limits_V: [0, 150, 3]"),
     "min, max"),
    (lambda t: t.replace("voltage_limits_V: [0.0, 150.0]", "voltage_limits_V: [150, 0]"),
     "min < max"),
    (lambda t: t.replace("alpha: 0.030", "alpha: true"), "number"),
])
def test_model_files_are_validated(tmp_path, edit, why):
    assert "voltage_limits_V: [0.0, 150.0]" in GOOD
    bad = tmp_path / "bad.yaml"
    bad.write_text(edit(GOOD))
    with pytest.raises(ModelError, match=why):
        load_model(bad)


def test_a_polynomial_that_overflows_is_refused(tmp_path):
    import yaml
    doc = yaml.safe_load(GOOD)
    ax = doc["axes"]["x"]
    branch = ax["ascending"] if "ascending" in ax else ax
    branch.pop("f", None), branch.pop("g", None)
    branch["h"] = [1.0] * 2000
    bad = tmp_path / "big.yaml"
    bad.write_text(yaml.safe_dump(doc))
    with pytest.raises(ModelError, match="finite"):
        load_model(bad)


def test_outputs_never_overwrite_inputs_and_must_be_writable(tmp_path):
    volts = tmp_path / "v.csv"
    volts.write_text("t,vx,vy\n" + "".join(f"{k * 1e-3},{k % 50},{0}\n" for k in range(200)))
    before = volts.read_text()
    one_line_exit_2(cli("simulate", "--in", volts, "--out", volts))
    assert volts.read_text() == before
    one_line_exit_2(cli("invert", "--model", MODEL, "--in", volts, "--out", MODEL))
    one_line_exit_2(cli("identify", volts, "--out", volts))
    one_line_exit_2(cli("simulate", "--in", volts, "--out", tmp_path))  # a directory
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    if not os.access(locked, os.W_OK):  # (root may write anyway)
        one_line_exit_2(cli("simulate", "--in", volts, "--out", locked / "o.csv"))


def test_missing_axis_and_divergent_output_are_errors_not_silent(tmp_path):
    import yaml
    doc = yaml.safe_load(GOOD)
    del doc["axes"]["y"]
    xonly = tmp_path / "x.yaml"
    xonly.write_text(yaml.safe_dump(doc))
    target = tmp_path / "w.csv"
    target.write_text("t,wx,wy\n" + "".join(f"{k * 1e-3},10,10\n" for k in range(50)))
    r = cli("invert", "--model", xonly, "--in", target, "--out", tmp_path / "v.csv")
    one_line_exit_2(r)
    assert "axis y" in r.stderr and not (tmp_path / "v.csv").exists()


@pytest.mark.parametrize("line, why", [("internal_rate_hz: 1.0e9", "internal_rate_hz"),
                                       ("effects: {delay: {enabled: true, delay_s: 1.0e6}}",
                                        "delay_s"),
                                       ("effects: {delay: {enabled: 'yes'}}", "enabled")])
def test_plant_configs_are_range_checked(tmp_path, line, why):
    cfg = tmp_path / "plant.yaml"
    cfg.write_text(f"piezo_stage_plant: 1\nmodel: {MODEL}\n{line}\n")
    volts = tmp_path / "v.csv"
    volts.write_text("t,vx,vy\n0,0,0\n0.001,1,1\n0.002,2,2\n")
    r = cli("simulate", "--in", volts, "--out", tmp_path / "o.csv", "--config", cfg)
    one_line_exit_2(r)
    assert why in r.stderr


def test_csv_with_a_byte_order_mark_or_semicolons_reads(tmp_path):
    from piezo_stage.io.csv_table import read_table
    a = tmp_path / "bom.csv"
    a.write_bytes("\ufefft,vx,vy\n0,1,2\n0.001,1,2\n".encode("utf-8"))
    b = tmp_path / "semi.csv"
    b.write_text("t;vx;vy\n0;1;2\n0.001;1;2\n")
    for p in (a, b):
        cols = read_table(p, ["t", "vx", "vy"])
        np.testing.assert_array_equal(cols["vy"], [2.0, 2.0])


@pytest.mark.parametrize("effects, why", [
    ({"dynamics": {"f_hz": 1e-9, "zeta": -1}}, "unknown parameter"),
    ({"delay": {"delay_s": 1e9}}, "delay_s"),
    ({"dynamics": {"kind": "resonance", "fn_hz": 800, "zeta": -1}}, "zeta"),
    ({"creep": {"gamma": 0.03, "tau_s": [0.1] * 20}}, "time constants"),
    ({"warp": {}}, "unknown effect"),
    ({"delay": {"delay_s": 1e-3, "axes": ["z"]}}, "axes"),
])
def test_every_effect_key_and_range_is_checked(effects, why):
    import yaml

    from piezo_stage.core.errors import ModelError
    from piezo_stage.io.model_file import model_from_dict
    doc = yaml.safe_load(GOOD)
    doc["effects"] = effects
    with pytest.raises(ModelError, match=why):
        model_from_dict(doc)


@pytest.mark.parametrize("k", [0.001, -1.0, 2.5])
def test_an_implausible_model_change_is_refused(k):
    import yaml

    from piezo_stage.core.errors import ModelError
    from piezo_stage.core.model.duhem import check_model_change
    from piezo_stage.io.model_file import model_from_dict
    running, _ = model_from_dict(yaml.safe_load(GOOD))
    new, _ = model_from_dict(yaml.safe_load(scaled_model(GOOD, k)))
    with pytest.raises(ModelError, match="stroke"):
        check_model_change(new, running, 100.0)
    check_model_change(running, running, 100.0)  # the same stage again: fine
    same, _ = model_from_dict(yaml.safe_load(scaled_model(GOOD, 1.2)))
    check_model_change(same, running, 100.0)  # a refit 20 % off: fine


def test_deeply_nested_yaml_is_one_line_exit_2(tmp_path):
    deep = tmp_path / "deep.yaml"
    deep.write_text("[" * 20000 + "]" * 20000)
    inp = tmp_path / "v.csv"
    inp.write_text("t,vx,vy\n0,0,0\n0.001,1,1\n")
    out = tmp_path / "w.csv"
    for args in (["simulate", "--in", inp, "--out", out, "--model", deep],
                 ["simulate", "--in", inp, "--out", out, "--config", deep],
                 ["launch", deep, "--duration", "1"]):
        r = cli(*args)
        assert r.returncode == 2, (args, r.stderr[-300:])
        assert "nested deeper" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("args", [
    ["excite", "--rate", "0"], ["excite", "--rate", "-5"], ["excite", "--rate", "nan"],
    ["excite", "--rate", "inf"], ["excite", "--rate", "1e9"], ["loop", "--freq", "0"],
    ["loop", "--freq", "nan"], ["loop", "--cycles", "-1"], ["tune", "--latency", "inf"],
    ["launch", "--duration", "-1"], ["replay", "x", "--rate", "-0.5"],
])
def test_numeric_arguments_are_range_checked(args, tmp_path):
    out = ["--out", tmp_path / "o.csv"] if args[0] == "excite" else []
    r = cli(*args, *out, cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "outside" in r.stderr and "Traceback" not in r.stderr


def test_devices_are_neither_read_nor_replaced(tmp_path):
    import stat
    inp = tmp_path / "v.csv"
    inp.write_text("t,vx,vy\n0,0,0\n0.001,1,1\n")
    r = cli("simulate", "--in", "/dev/zero", "--out", tmp_path / "o.csv")
    assert r.returncode == 2 and "not a regular file" in r.stderr
    r = cli("simulate", "--in", inp, "--out", "/dev/null")
    assert r.returncode == 2 and "not a regular file" in r.stderr
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)  # still the device


def test_echoed_text_is_escaped_and_cut(tmp_path):
    esc = tmp_path / "esc.csv"
    esc.write_text("\x1b[31mtime\x1b[0m,vx,vy\n0,0,0\n")
    r = cli("simulate", "--in", esc, "--out", tmp_path / "o.csv")
    assert r.returncode == 2 and "\x1b" not in r.stderr and "\\x1b" in r.stderr
    binary = tmp_path / "bin.csv"
    binary.write_bytes(bytes(range(1, 256)) * 400)  # 100 kB, no newline
    r = cli("simulate", "--in", binary, "--out", tmp_path / "o.csv")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert len(r.stderr) < 700, len(r.stderr)


@pytest.mark.parametrize("plays, why", [
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1]}, "same length"),
    ({"thresholds_V": [-1, 10], "weights_um_per_V": [0.1, 0.1]}, ">= 0"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1, float("nan")]}, "not finite"),
    ({"thresholds_V": list(range(201)), "weights_um_per_V": [0.0] * 201}, "more than 200"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [1e4, 1e4]}, "weights sum"),
    ({"thresholds_V": [0, 10]}, "missing weights_um_per_V"),
    ({"thresholds_V": [0], "weights_um_per_V": [0.1], "start": 1}, "unknown key"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1, 0.1], "bands_V": [[0, 50]]},
     "one \\[low, high\\] pair per operator"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1, 0.1],
      "bands_V": [[0, 50], [60, 60]]}, "low < high"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1, 0.1],
      "bands_V": [[0, 50], [0, 50, 70]]}, "pair per operator"),
    ({"thresholds_V": [0, 10], "weights_um_per_V": [0.1, 0.1],
      "bands_V": [[0, 50], [0, "x"]]}, "bands_V\\[1\\]"),
])
def test_play_operators_in_a_model_file_are_checked(plays, why):
    """A model file's play operators (return-point memory) round-trip through the
    document, and a bad block is refused naming the key."""
    import yaml

    from piezo_stage.core.errors import ModelError
    from piezo_stage.io.model_file import model_from_dict, model_to_dict
    doc = yaml.safe_load(GOOD)
    doc["axes"]["x"]["play_operators"] = {"thresholds_V": [0.0, 20.0],
                                          "weights_um_per_V": [0.05, -0.01]}
    model, _ = model_from_dict(doc)
    p = model.plays["x"]
    assert list(p.initial_V) == [model.axes["x"].initial.v] * 2  # at rest by default
    again, _ = model_from_dict(yaml.safe_load(yaml.safe_dump(model_to_dict(model))))
    assert again.plays == model.plays and "y" not in again.plays
    # banded operators (a discretized Preisach law) keep their bands
    doc["axes"]["x"]["play_operators"]["bands_V"] = [[0.0, 50.0], [20.0, 40.0]]
    model, _ = model_from_dict(doc)
    again, _ = model_from_dict(yaml.safe_load(yaml.safe_dump(model_to_dict(model))))
    assert again.plays == model.plays and again.plays["x"].banded
    assert again.plays["x"].table[1:].tolist() == [[0.0, 20.0], [50.0, 40.0]]
    doc["axes"]["x"]["play_operators"] = plays
    with pytest.raises(ModelError, match=why):
        model_from_dict(doc)
