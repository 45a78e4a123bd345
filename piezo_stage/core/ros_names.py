"""ROS names as a lab types them: a namespace without its leading slash is the one with
it, as a ROS 2 launch file's namespace is; anything ROS would refuse is refused here in
one line (rcl only logs "Failed to parse global arguments" for each node it starts)."""

from __future__ import annotations

import re

from piezo_stage.core.errors import ConfigError, printable

# rcl's rule for a namespace's tokens: a letter or underscore, then letters, digits and
# underscores; tokens separated by single slashes, none at the end
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def fully_qualified_namespace(text: str) -> str:
    """``text`` as a fully qualified namespace ("stage2" -> "/stage2"); ConfigError
    naming what is wrong where ROS would refuse it."""
    if not text:
        raise ConfigError("namespace '': give one, /stage for example")
    ns = text if text.startswith("/") else "/" + text
    if ns == "/":
        return ns
    tokens = ns[1:].split("/")
    bad = next((t for t in tokens if not _TOKEN.fullmatch(t)), None)
    if bad is not None:
        what = ("an empty part (a doubled or trailing /)" if bad == "" else
                f"{printable(bad, 40)!s}")
        raise ConfigError(f"namespace {printable(text, 60)!s}: {what} is no ROS name "
                          "(letters, digits and _, not starting with a digit, parts "
                          "separated by single /)")
    return ns
