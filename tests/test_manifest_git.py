"""The manifest's git state: one set of ``git`` calls per repository, none outside one."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from cobelrun.io import manifest

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(cwd: Path, *args: str) -> str:
    out = subprocess.run(
        ["git", "-c", "user.email=t@example.org", "-c", "user.name=t", *args],
        cwd=cwd, capture_output=True, text=True, check=True,
    )  # fmt: skip
    return out.stdout.strip()


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[list[str], Path]]:
    """The ``git`` calls the manifest makes (they still run), with a fresh per-process cache."""
    seen: list[tuple[list[str], Path]] = []
    real = manifest._git

    def counted(args: list[str], cwd: Path) -> str | None:
        seen.append((args, cwd))
        return real(args, cwd)

    monkeypatch.setattr(manifest, "_git", counted)
    for name in manifest._GIT_ENV:
        monkeypatch.delenv(name, raising=False)
    manifest._git_info.cache_clear()
    yield seen
    manifest._git_info.cache_clear()


@pytest.fixture
def repo(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    (root / "sub" / "deeper").mkdir(parents=True)
    _git(root, "init", "-q")
    (root / "a.txt").write_text("one\n")
    _git(root, "add", "a.txt")
    _git(root, "commit", "-q", "-m", "first")
    return root


def test_one_set_of_calls_per_repository(repo: Path, calls: list) -> None:
    head = _git(repo, "rev-parse", "HEAD")
    top = _git(repo, "rev-parse", "--show-toplevel")
    a = manifest.git_info(repo / "sub" / "deeper")
    b = manifest.git_info(repo)
    assert a == b == {"commit": head, "dirty": False, "root": top}
    assert len(calls) == 3  # rev-parse HEAD, status, --show-toplevel: once for both folders
    a["commit"] = "changed"  # callers get their own copy
    assert manifest.git_info(repo)["commit"] == head


def test_dirty_and_same_answer_as_git_from_the_folder(repo: Path, calls: list) -> None:
    (repo / "a.txt").write_text("two\n")
    info = manifest.git_info(repo / "sub")
    assert info is not None and info["dirty"] is True
    # what git itself says when started in the subfolder
    assert info["commit"] == _git(repo / "sub", "rev-parse", "HEAD")
    assert info["root"] == _git(repo / "sub", "rev-parse", "--show-toplevel")


def test_no_repository_no_git_process(tmp_path: Path, calls: list) -> None:
    plain = tmp_path / "plain" / "inner"
    plain.mkdir(parents=True)
    assert manifest.git_info(plain) is None
    assert calls == []
    assert manifest.git_info(tmp_path / "missing") is None  # not a folder
    assert calls == []


def test_git_environment_asks_git(
    tmp_path: Path, repo: Path, calls: list, monkeypatch: pytest.MonkeyPatch
) -> None:
    plain = tmp_path / "elsewhere"
    plain.mkdir()
    monkeypatch.setenv("GIT_DIR", str(repo / ".git"))  # git finds the repository from anywhere
    info = manifest.git_info(plain)
    assert calls and calls[0][1] == plain
    assert info is not None and info["commit"] == _git(repo, "rev-parse", "HEAD")
