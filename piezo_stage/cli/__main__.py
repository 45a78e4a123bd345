"""``python -m piezo_stage.cli``: the ``piezo-stage`` command (``python -m piezo_stage``
also takes stop signals during the command's imports)."""


from piezo_stage.process import stopping
from piezo_stage.process.blas import one_thread_unless_set

one_thread_unless_set()  # before numpy loads (see piezo_stage/process/blas.py)
from piezo_stage.cli import main  # noqa: E402

code = main()
stopping.hold()  # as piezo_stage.__main__: a stop after the end is ignored
stopping.exit_now(code)
