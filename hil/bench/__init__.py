"""Benchmarks: ``hil bench NAME`` runs ``hil.bench.NAME.main(argv)``.

Each benchmark prints its figures and writes them as one section of ``docs/benchmarks.md``
(between ``<!-- bench:NAME -->`` markers), always with the command that produced them, so the
file only ever holds numbers that a command measured.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

DEFAULT_DOC = Path("docs/benchmarks.md")

_HEADER = """# Benchmarks

Every section below was written by the command it names, on the machine it names. Re-run the
command to refresh it; nothing here is typed by hand. Sections written since 2026-12-07 also name
the machine's Python speed in that hour (a fixed loop, `hil.bench.python_loop_s`): this VM's
drifted 0.57-1.39 s in one day, so figures of different hours compare through it, and the ratios
of one run (`--versus`, alternating rounds) need no such help.
"""


_LOOP_S: float | None = None


def _loop_tenth_s() -> float:
    t0 = time.perf_counter()
    sum(i * i for i in range(1_000_000))
    return time.perf_counter() - t0


def python_loop_s() -> float:
    """This machine's Python speed, taken once per process when a section is written (the
    bench's load has ended by then): seconds for ``sum(i * i for i in range(10**7))``, ten times
    the best of five tenths. A VM's speed drifts from hour to hour (here 0.57-1.39 s in one day),
    so figures of different hours compare only through it; ratios within one run do not need it."""
    global _LOOP_S
    if _LOOP_S is None:
        _LOOP_S = 10 * min(_loop_tenth_s() for _ in range(5))
    return _LOOP_S


def machine_line() -> str:
    """Where the figures came from, so a reader can compare like with like."""
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"{datetime.now(UTC).strftime('%Y-%m-%d')}, a fixed Python loop {python_loop_s():.2f} s"
    )


def tree_revision(tree: str) -> str:
    """The short commit of a checkout, to label its rows; ``+edits`` when tracked files differ
    from it (the figures are then of code no commit holds yet)."""
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=tree, capture_output=True, text=True)
    rev = out.stdout.strip()
    if not rev:
        return os.path.basename(os.path.abspath(tree))
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"], cwd=tree, capture_output=True, text=True
    )
    return f"{rev}+edits" if dirty.stdout.strip() else rev


def write_section(name: str, body_md: str, command: str, doc: Path = DEFAULT_DOC) -> Path:
    """Replace (or append) the section ``name`` of the benchmarks document."""
    doc.parent.mkdir(parents=True, exist_ok=True)
    text = doc.read_text() if doc.exists() else _HEADER
    block = (
        f"<!-- bench:{name} -->\n## {name}\n\nCommand: `{command}`  \nMachine: {machine_line()}\n\n"
        f"{body_md.strip()}\n<!-- /bench:{name} -->"
    )
    pattern = re.compile(rf"<!-- bench:{re.escape(name)} -->.*?<!-- /bench:{re.escape(name)} -->", re.S)
    text = pattern.sub(lambda _m: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block
    doc.write_text(text.rstrip() + "\n")
    return doc


def command_line() -> str:
    """The command as the user typed it (``hil bench ...``)."""
    return (
        "hil " + " ".join(sys.argv[1:])
        if sys.argv and sys.argv[0].endswith("hil")
        else " ".join(["hil", *sys.argv[1:]])
    )
