"""A bench row names the code it measured: the commit, and ``+edits`` when the checkout differs
from it (figures of uncommitted code were once labelled with the commit before them)."""

from __future__ import annotations

import subprocess
from pathlib import Path

from hil.bench import tree_revision


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
