"""Shared by the kill tests: seeded kill points, the processes of a stopped command's tree,
rows lost against an uninterrupted run, and a log of every kill point for the figures.

Set ``COBEL_FAULT_LOG=FILE`` to append one JSON line per kill point (kind, signal, seed,
outcome, rows kept and lost); ``python -m tests.faults.killpoints FILE`` sums them up.
"""

from __future__ import annotations

import json
import os
import sys
import time
import uuid
from pathlib import Path

import pandas as pd
import psutil

#: every process a stopped command started carries this variable with a fresh token, so the
#: check finds them all, also those started after the signal or re-parented when their parent
#: died (a snapshot of the tree at the signal misses both)
TOKEN_ENV = "COBEL_FAULT_TREE"


def tagged_env(env: dict[str, str]) -> tuple[dict[str, str], str]:
    token = uuid.uuid4().hex
    return {**env, TOKEN_ENV: token}, token


def tree_alive(token: str) -> list[psutil.Process]:
    """Every live (not zombie) process of this user whose environment carries ``token``."""
    found = []
    for proc in psutil.process_iter():
        try:
            if proc.environ().get(TOKEN_ENV) == token and proc.status() != psutil.STATUS_ZOMBIE:
                found.append(proc)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
    return found


def assert_tree_gone(token: str, within: float = 60.0) -> None:
    """No process of the stopped command's tree may outlive it (``within`` seconds to exit)."""
    deadline = time.time() + within
    alive = tree_alive(token)
    while alive and time.time() < deadline:
        time.sleep(0.2)
        alive = tree_alive(token)
    if alive:
        desc = []
        for p in alive:
            try:
                desc.append(f"pid {p.pid} (parent {p.ppid()}): {' '.join(p.cmdline())[:160]}")
            except psutil.Error:
                continue
        for p in alive:  # do not leave them running for the next test
            try:
                p.kill()
            except psutil.Error:
                pass
        raise AssertionError("orphaned processes: " + "; ".join(desc))


def rows_lost(found: pd.DataFrame, ref: pd.DataFrame, keys: list[str]) -> int:
    """Rows of ``ref`` (the uninterrupted run, in recorded order) up to the last row ``found``
    has that are missing from ``found`` or differ from it."""
    if found.empty:
        return 0
    ref = ref.reset_index(drop=True)
    pos = ref[keys].reset_index().merge(found[keys].drop_duplicates(), on=keys)["index"]
    prefix = ref.iloc[: int(pos.max()) + 1] if len(pos) else ref.iloc[:0]
    cols = list(ref.columns)
    matched = prefix.merge(found[cols].drop_duplicates(), on=cols, how="inner")
    return len(prefix) - len(matched)


def log(**fields: object) -> None:
    path = os.environ.get("COBEL_FAULT_LOG")
    if path:
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps(fields) + "\n")


def summarize(path: str | Path) -> dict[str, int]:
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    out = {"kill_points": len(rows), "faults_injected": 0, "survived": 0, "rows_lost": 0,
           "finished_before_signal": 0}  # fmt: skip
    for r in rows:
        if r["outcome"] == "finished_before_signal":
            out["finished_before_signal"] += 1
            continue
        out["faults_injected"] += 1
        out["survived"] += r["outcome"] == "survived"
        out["rows_lost"] += int(r.get("rows_lost", 0))
    for kind in sorted({r["kind"] for r in rows}):
        out[f"{kind}_kill_points"] = sum(r["kind"] == kind for r in rows)
    return out


if __name__ == "__main__":
    print(json.dumps(summarize(sys.argv[1]), indent=1))
