"""What a benchmark found, said once and printed two ways: as text for the terminal, or
as markdown for the benchmark page (``piezo-stage bench WHAT --markdown FILE``), where
every table's header names the date, the commit and the host it was measured on.

A benchmark builds one ``Report``: a title, tables (``table``, or ``figures`` for
name-value pairs), notes, and its targets, each met or not. Progress lines (one per run
or pair) go to the terminal only: the page keeps the figures.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
from collections.abc import Sequence

BEGIN, END = "<!-- bench {} -->", "<!-- /bench {} -->"


def provenance() -> str:
    """``date, commit C, host``: when, on which code and where a figure was measured
    (the commit marked ``+changes`` where the package's files differ from it)."""
    here = os.path.dirname(os.path.abspath(__file__))
    commit = "no git checkout"
    try:
        sha = subprocess.run(["git", "-C", here, "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, timeout=10)
        if sha.returncode == 0:
            dirty = subprocess.run(["git", "-C", here, "status", "--porcelain",
                                    "--untracked-files=no", "--", ".."],
                                   capture_output=True, text=True, timeout=10)
            commit = f"commit {sha.stdout.strip()}" + (
                "+changes" if dirty.returncode == 0 and dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass
    host = f"{os.cpu_count()} CPUs, {platform.machine()}, Python {platform.python_version()}"
    return f"{datetime.date.today().isoformat()}, {commit}, {host}"


def _cell(x: object, markdown: bool = True) -> str:
    text = str(x).replace("\n", " ")
    return text.replace("|", "\\|") if markdown else text


class Report:
    """One benchmark's findings (see the module's docstring).

    Parameters
    ----------
    what : str
        The benchmark's name (``plant``, ``loop``...): its section on the page.
    markdown : bool
        Gather markdown for the page instead of printing text as it comes.
    """

    def __init__(self, what: str, markdown: bool = False):
        self.what, self.markdown = what, bool(markdown)
        self.stamp = provenance() if self.markdown else ""
        self.blocks: list[str] = []
        self.targets: list[tuple[str, bool]] = []

    def _say(self, text: str) -> None:
        if self.markdown:
            self.blocks.append(text)
        else:
            print(text, flush=True)

    def title(self, text: str) -> None:
        """What the benchmark runs, in one sentence."""
        self._say(text if self.markdown else f"bench {self.what}: {text}")

    def progress(self, text: str) -> None:
        """A run's or a pair's line: on the terminal (stderr under ``markdown``)."""
        print(("  " if not self.markdown else f"bench {self.what}: ") + text,
              file=sys.stderr if self.markdown else sys.stdout, flush=True)

    def fail(self, text: str) -> None:
        """Why the benchmark could not measure (on stderr; it then returns 1)."""
        print(f"bench {self.what}: {text}", file=sys.stderr, flush=True)

    def note(self, text: str) -> None:
        """A sentence of findings that is no table's row."""
        self._say(text if self.markdown else "  " + text)

    def table(self, columns: Sequence[str], rows: Sequence[Sequence[object]],
              caption: str = "") -> None:
        """A table: ``columns`` named, ``rows`` of as many cells, ``caption`` above it."""
        cells = [[_cell(c, self.markdown) for c in r] for r in rows]
        if self.markdown:
            head = f"*{self.stamp}*" + (f": {caption}" if caption else "")
            lines = [head, "", "| " + " | ".join(_cell(c) for c in columns) + " |",
                     "|" + "---|" * len(columns)]
            lines += ["| " + " | ".join(r) + " |" for r in cells]
            self.blocks.append("\n".join(lines))
            return
        widths = [max([len(str(c))] + [len(r[i]) for r in cells if i < len(r)])
                  for i, c in enumerate(columns)]
        out = [f"\n  {caption}"] if caption else [""]
        out.append(("  " + "  ".join(str(c).ljust(w) for c, w in zip(columns, widths)))
                   .rstrip())
        out += [("  " + "  ".join(c.ljust(w) for c, w in zip(r, widths))).rstrip()
                for r in cells]
        print("\n".join(out), flush=True)

    def figures(self, rows: Sequence[tuple[str, object]], caption: str = "") -> None:
        """Name-value figures, as a two-column table."""
        self.table(("figure", "value"), rows, caption)

    def target(self, what: str, met: bool) -> None:
        """A target the benchmark judges: ``what`` it asks, whether it was met."""
        self.targets.append((what, bool(met)))

    def text(self) -> str:
        """The page's block: everything gathered, the targets last (markdown)."""
        blocks = list(self.blocks)
        if self.targets:
            rows = [(w, "met" if ok else "NOT met") for w, ok in self.targets]
            head = f"*{self.stamp}*: targets"
            blocks.append("\n".join([head, "", "| target | |", "|---|---|"]
                                    + [f"| {_cell(w)} | {m} |" for w, m in rows]))
        return "\n\n".join(blocks)

    def finish(self, page: str | None) -> None:
        """Print the targets (text), or write the block: to stdout (``page`` "-") or
        into ``page``'s section for this benchmark (replaced whole, or added at the end;
        written to a temp file, then renamed)."""
        if not self.markdown:
            for what, ok in self.targets:
                print(f"  target {what}: {'met' if ok else 'NOT met'}")
            return
        block = "\n".join([BEGIN.format(self.what), self.text(), END.format(self.what)])
        if page in (None, "-"):
            print(block)
            return
        assert page is not None
        old = open(page).read() if os.path.exists(page) else "# Benchmarks\n"
        write_page(page, splice(old, self.what, block))


def splice(page: str, what: str, block: str) -> str:
    """``page`` with its section for ``what`` replaced by ``block`` (or added at the end,
    under a heading of its name)."""
    begin, end = BEGIN.format(what), END.format(what)
    i = page.find(begin)
    if i >= 0:
        j = page.find(end, i)
        if j < 0:
            raise ValueError(f"the page has {begin} without {end}")
        return page[:i] + block + page[j + len(end):]
    return page.rstrip("\n") + f"\n\n## {what}\n\n{block}\n"


def write_page(path: str, text: str) -> None:
    """Write ``text`` to ``path`` whole: a temp file beside it, then renamed."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)
