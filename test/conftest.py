import os
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = os.path.join(ROOT, "config")
sys.path.insert(0, ROOT)


@pytest.fixture(scope="session")
def stage_model():
    from piezo_stage.io.model_file import load_model
    return load_model(os.path.join(CONFIG, "stage_model.yaml"))[0]


@pytest.fixture(scope="session")
def plant_config_path():
    return os.path.join(CONFIG, "sim_stage.yaml")


def sine_v(freq, fs, cycles, lo=0.0, hi=150.0, phase=0.0):
    t = np.arange(int(round(cycles * fs / freq))) / fs
    return t, lo + (hi - lo) / 2 * (1 - np.cos(2 * np.pi * freq * t + phase))
