"""The docs site builds with `mkdocs build --strict` (broken links, missing pages or API
objects fail), and docstrings cite files that exist."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("mkdocs", path=str(Path(sys.executable).parent)) is None,
                    reason="needs the docs extra (mkdocs-material, mkdocstrings)")  # fmt: skip
def test_mkdocs_build_strict(tmp_path):
    exe = shutil.which("mkdocs", path=str(Path(sys.executable).parent))
    proc = subprocess.run([exe, "build", "--strict", "-d", str(tmp_path / "site")], cwd=ROOT,
                          capture_output=True, text=True, timeout=300,
                          env={"NO_MKDOCS_2_WARNING": "1", "PATH": str(Path(exe).parent)})  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    configs = (tmp_path / "site" / "reference" / "configs" / "index.html").read_text()
    assert "task=tmaze_extinction" in configs and "agent=dyna_q" in configs
    assert (
        "cobelrun.api.run" in (tmp_path / "site" / "reference" / "api" / "index.html").read_text()
    )


def test_docstrings_cite_files_that_exist():
    """Every ``*.md`` file named in the package, the configs or the figure specs is in the
    repository (a bare name such as ``FACTS.md`` would point outside it)."""
    cited = set()
    sources = [*(ROOT / "cobelrun").rglob("*.py"), *(ROOT / "conf").rglob("*.yaml"),
               *(ROOT / "experiments").rglob("*.py")]  # fmt: skip
    for path in sources:
        cited |= set(re.findall(r"(?<![\w/.-])([\w./-]+\.md)\b", path.read_text()))
    missing = sorted(c for c in cited if not (ROOT / c).is_file())
    assert not missing, missing
    assert "docs/paper-settings.md" in cited  # the pattern finds the citations
