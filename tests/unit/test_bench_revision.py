"""A bench row names the code it measured: the commit, and ``+edits`` when the checkout differs
from it (figures of uncommitted code were once labelled with the commit before them); a section
names the machine's Python speed in that hour (a VM's drifts)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from hil.bench import python_loop_s, tree_revision, write_section


def _git(repo: Path, *args: str) -> str:
    out = subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@localhost", *args],
        cwd=repo,
        capture_output=True,
        text=True,
        check=True,
    )
    return out.stdout.strip()


def test_a_checkout_with_edits_is_labelled_so(tmp_path: Path) -> None:
    plain = tmp_path / "not-a-checkout"
    plain.mkdir()
    assert tree_revision(str(plain)) == "not-a-checkout"  # no commit to name: the folder
    tmp_path = tmp_path / "repo"
    tmp_path.mkdir()
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    _git(tmp_path, "add", "a.py")
    _git(tmp_path, "commit", "-q", "-m", "one")
    head = _git(tmp_path, "rev-parse", "--short", "HEAD")
    (tmp_path / "notes.txt").write_text("untracked files do not count\n")
    assert tree_revision(str(tmp_path)) == head
    (tmp_path / "a.py").write_text("x = 2\n")
    assert tree_revision(str(tmp_path)) == f"{head}+edits"


def test_a_section_names_the_machines_python_speed(tmp_path: Path) -> None:
    doc = write_section("probe", "| a | b |", "hil bench probe", tmp_path / "benchmarks.md")
    line = next(ln for ln in doc.read_text().splitlines() if ln.startswith("Machine: "))
    m = re.search(r", a fixed Python loop (\d+\.\d\d) s$", line)
    assert m, line
    # taken once per process: every section of one bench run names the same figure
    assert float(m.group(1)) == round(python_loop_s(), 2) > 0
