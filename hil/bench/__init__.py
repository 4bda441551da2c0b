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
from datetime import UTC, datetime
from pathlib import Path

DEFAULT_DOC = Path("docs/benchmarks.md")

_HEADER = """# Benchmarks

Every section below was written by the command it names, on the machine it names. Re-run the
command to refresh it; nothing here is typed by hand.
"""


def machine_line() -> str:
    """Where the figures came from, so a reader can compare like with like."""
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"{datetime.now(UTC).strftime('%Y-%m-%d')}"
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
