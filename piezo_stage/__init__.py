"""piezo_stage: Duhem-model identification and control of 2-axis piezo stages.

The numerical core (:mod:`piezo_stage.core`) is pure numpy/scipy and never imports
ROS; :mod:`piezo_stage.io` reads and writes records and model files; the ROS 2 nodes
in :mod:`piezo_stage.nodes` are thin shells over both.
"""

__version__ = "0.1.0"
