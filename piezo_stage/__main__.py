"""``python -m piezo_stage`` and the ``piezo-stage`` command's entry: the stop signals
are taken before the command's imports (see stopping.py), then the command runs."""

import sys

from piezo_stage import stopping


def main():
    stopping.install()
    from piezo_stage.cli import main as command
    return command()


if __name__ == "__main__":
    sys.exit(main())
