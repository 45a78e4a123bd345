"""Where the package's own files are: config/ (stage.yaml, sim_stage.yaml,
stage_model.yaml) in the source tree, or share/piezo_stage/config when installed.

Installed lookups go through the ament index (``ament_index_python``), as ``ros2 run``
and ``ros2 launch`` find a package; a plain pip install falls back to
``<prefix>/share/piezo_stage``.
"""

from __future__ import annotations

import os
import sys

PACKAGE = "piezo_stage"


def share_dir() -> str:
    """The package's share directory (the source tree's root when run from source)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if os.path.isfile(os.path.join(root, "package.xml")) and \
            os.path.isdir(os.path.join(root, "config")):
        return root
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        try:
            return get_package_share_directory(PACKAGE)
        except (PackageNotFoundError, KeyError, LookupError, EnvironmentError):
            pass
    except ImportError:
        pass
    return os.path.join(sys.prefix, "share", PACKAGE)


def config_dir() -> str:
    return os.path.join(share_dir(), "config")


def default_config(name: str) -> str:
    """A file of the package's config/ (stage.yaml, sim_stage.yaml, stage_model.yaml)."""
    return os.path.join(config_dir(), name)
