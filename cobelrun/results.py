"""Load run folders written by ``cobel run``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd

from cobelrun.errors import CobelError


def _run_dir(path: str | Path) -> Path:
    p = Path(path)
    if not p.is_dir():
        raise CobelError(f"run folder {p} does not exist")
    if not (p / "trials.parquet").is_file():
        raise CobelError(f"{p} is not a cobel run folder (no trials.parquet)")
    return p


def load_trials(path: str | Path) -> pd.DataFrame:
    """The ``trials`` table of a run folder."""
    p = _run_dir(path) / "trials.parquet"
    try:
        return pd.read_parquet(p)
    except Exception as exc:
        raise CobelError(f"cannot read {p}: {exc}") from None


def load_steps(path: str | Path) -> pd.DataFrame:
    """The ``steps`` table of a run folder."""
    p = _run_dir(path) / "steps.parquet"
    if not p.is_file():
        raise CobelError(f"{p.parent} has no steps.parquet (steps were not recorded)")
    return pd.read_parquet(p)


def load_manifest(path: str | Path) -> dict[str, Any]:
    """The run's ``manifest.json``."""
    p = _run_dir(path) / "manifest.json"
    if not p.is_file():
        raise CobelError(f"{p.parent} has no manifest.json")
    return json.loads(p.read_text())
