"""Files: inputs that must be regular and bounded, YAML files read bounded, atomic
writing (a temporary file beside the target, then a rename)."""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile

from piezo_stage.core.errors import DataError, ModelError, printable
from piezo_stage.core.yaml_text import MAX_YAML_BYTES, parse_yaml

MAX_INPUT_BYTES = 2 * 1024 ** 3  # a 5 kHz two-axis CSV of 24 h is about 0.5 GB


def check_input(path, max_bytes: int = MAX_INPUT_BYTES, what: str = "input") -> None:
    """DataError unless ``path`` is a regular file of at most ``max_bytes`` (a device
    such as /dev/zero never ends, a FIFO may never answer)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise DataError(f"{printable(path)}: no such file") from None
    except OSError as e:
        raise DataError(f"{printable(path)}: cannot read ({type(e).__name__})") from None
    if stat.S_ISDIR(st.st_mode):
        raise DataError(f"{printable(path)}: is a directory, not a {what} file")
    if not stat.S_ISREG(st.st_mode):
        raise DataError(f"{printable(path)}: not a regular file (a device or a pipe); "
                        f"give the {what} as a file")
    if st.st_size > max_bytes:
        raise DataError(f"{printable(path)}: {st.st_size} bytes, more than the "
                        f"{max_bytes} accepted")


def check_output(path) -> None:
    """DataError if ``path`` exists and is not a regular file: renaming a temporary
    file over a device (/dev/null, run as root) would replace the device."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISREG(st.st_mode):
        raise DataError(f"{printable(path)}: exists and is not a regular file; outputs "
                        "are written to a temporary file and renamed over the target")


@contextlib.contextmanager
def atomic_write(path, mode="w", **kw):
    """Open a temporary file next to ``path``; on success rename it over ``path``.

    On any exception the temporary file is removed and ``path`` is left untouched, so
    a reader never sees a half-written output.
    """
    path = os.fspath(path)
    check_output(path)
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=d)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual file mode
    try:
        with os.fdopen(fd, mode, **kw) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def load_yaml(path, what="file"):
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_YAML_BYTES + 1)
    except FileNotFoundError:
        raise ModelError(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise ModelError(f"{what} is a directory: {path}") from None
    except PermissionError:
        raise ModelError(f"{what} not readable: {path}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ModelError(f"{what} is not UTF-8 text: {path}") from None
    return parse_yaml(text, f"{what} {path}")
