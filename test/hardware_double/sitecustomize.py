"""Loads the NI-DAQmx driver TEST DOUBLE (ni_driver_double.py) into node processes that
tests start with this folder on PYTHONPATH and PIEZO_STAGE_NI_DOUBLE set (JSON options
for ``install``). Without that variable it does nothing."""

import json
import os

if os.environ.get("PIEZO_STAGE_NI_DOUBLE"):
    import ni_driver_double

    ni_driver_double.install(**json.loads(os.environ["PIEZO_STAGE_NI_DOUBLE"] or "{}"))
