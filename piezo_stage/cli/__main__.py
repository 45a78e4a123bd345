"""``python -m piezo_stage.cli``: the ``piezo-stage`` command (``python -m piezo_stage``
also takes stop signals during the command's imports)."""


from piezo_stage.process import teardown
from piezo_stage.process.blas import one_thread_unless_set

one_thread_unless_set()  # before numpy loads (see piezo_stage/process/blas.py)
from piezo_stage.cli import main  # noqa: E402

try:
    code = main()
except SystemExit as e:  # its one line said (cli/_common.py die)
    code = e.code
teardown.end(code)  # as piezo_stage.__main__
