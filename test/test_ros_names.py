"""ROS namespaces as typed (core/ros_names.py): "stage2" is /stage2, as docs/realtime.md's
second stage is given; a name ROS would refuse is one line and exit 2, where rcl only
logged "Failed to parse global arguments" for each node and the set died."""

import subprocess
import sys

import pytest

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.ros_names import fully_qualified_namespace


@pytest.mark.parametrize("text, ns", [("stage2", "/stage2"), ("/stage", "/stage"),
                                      ("lab/stage_2", "/lab/stage_2"), ("/", "/")])
def test_a_namespace_is_fully_qualified(text, ns):
    assert fully_qualified_namespace(text) == ns


@pytest.mark.parametrize("text", ["2stage", "stage-2", "/stage/", "a//b", "st age", ""])
def test_a_namespace_ros_refuses_is_refused_by_name(text):
    with pytest.raises(ConfigError, match="namespace"):
        fully_qualified_namespace(text)


def test_the_launch_command_takes_a_relative_namespace_and_refuses_a_bad_one(tmp_path):
    from piezo_stage.launcher.launcher import Launch, LaunchOptions
    from piezo_stage.paths import default_config
    launch = Launch(default_config("stage.yaml"), LaunchOptions(namespace="stage2"))
    assert launch.ns == "/stage2"
    r = subprocess.run([sys.executable, "-m", "piezo_stage", "launch", "--namespace",
                        "stage-2", "--duration", "1"], capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].endswith(
        "argument --namespace: namespace stage-2: stage-2 is no ROS name (letters, digits "
        "and _, not starting with a digit, parts separated by single /)")
