"""``python -m piezo_stage`` and the ``piezo-stage`` command's entry: the stop signals
are taken before the command's imports (see stopping.py), then the command runs."""

import sys

from piezo_stage.process import stopping


def main():
    stopping.install()
    from piezo_stage.process.blas import one_thread_unless_set
    one_thread_unless_set()  # before numpy loads
    from piezo_stage.cli import main as command
    from piezo_stage.process import teardown
    try:
        code = command()
    except KeyboardInterrupt:  # a stop that met the command's own end: said, exit 130
        stopping.hold()
        line, code = stopping.stopped_line()
        sys.stderr.write(line + "\n")
    except SystemExit as e:  # its one line said (cli/_common.py die)
        code = e.code
    teardown.end(code)  # (the console script's sys.exit(main()) is never reached)


if __name__ == "__main__":
    main()
