"""Finish what a killed run left behind.

SIGKILL (or a crash of the machine) gives a run no chance to close its files: its tables are
still parts under ``.parts/``, its MCAP has no summary section, and its manifest says
``running``. :func:`repair_run` merges the parts into the tables, rewrites the MCAP so that
indexed readers open it, and marks the manifest ``interrupted`` with ``killed: true``. It never
touches a run whose process is still alive on this host. ``cobel status`` and
``cobel collect`` call it for every folder they read.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

from cobelrun.io.run_folder import RunFolder

__all__ = ["is_alive", "pid_alive", "repair_run"]


def is_alive(manifest: dict[str, Any]) -> bool:
    """True if the manifest's process still runs on this host (or on another host: unknown,
    so treated as alive)."""
    if manifest.get("hostname") != socket.gethostname():
        return True
    pid = manifest.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return False
    return pid == os.getpid() or pid_alive(pid)


def pid_alive(pid: int) -> bool:
    """True if process ``pid`` runs on this host (a zombie, killed but not yet reaped by its
    parent, does not count)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except (OSError, IndexError):
        return True


def repair_run(run_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Repair a run folder left by a killed process; returns what was done (empty if nothing).

    Keys: ``tables`` (name -> rows merged), ``mcap`` (True if rewritten), ``status`` (the
    manifest's new status).
    """
    from cobelrun.errors import CobelError
    from cobelrun.io.manifest import _write_json_atomic
    from cobelrun.io.parquet import merge_parts
    from cobelrun.io.validate import read_manifest

    folder = RunFolder(run_dir)
    done: dict[str, Any] = {}
    manifest: dict[str, Any] = {}
    if folder.manifest.is_file():
        try:
            manifest = read_manifest(folder.manifest)
        except CobelError:  # damaged: the readers say so; nothing here rewrites it
            return done
    if manifest.get("status") == "running" and is_alive(manifest):
        return done
    links = [p for p in (folder.path / folder.PARTS, folder.agent_parts, folder.mcap)
             if p.is_symlink()]  # fmt: skip
    if links:
        raise CobelError(f"{links[0]} is a symbolic link; cobel does not repair through links "
                         "(a run writes no links)")  # fmt: skip
    tables = {t: merge_parts(folder.parts(t), folder.table(t)) for t in folder.unfinished_tables()}
    if tables:
        done["tables"] = tables
    if folder.agent_parts.is_dir():
        from cobelrun.io.agents_archive import merge_agent_parts

        done["agents"] = merge_agent_parts(folder.agent_parts, folder.agents_archive)
    if folder.mcap.is_file() and manifest.get("status") != "completed":
        from cobelrun.io.mcap_repair import repair_mcap

        try:  # a completed run closed its MCAP: a damaged one is reported, not rewritten
            if repair_mcap(folder.mcap):
                done["mcap"] = True
        except Exception as exc:  # not an MCAP file, or one broken beyond its last record
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise CobelError(f"{folder.mcap} cannot be repaired ({first})") from None
    if manifest.get("status") == "running":
        manifest.update(status="interrupted", killed=True,
                        error="the process was killed before it could close its files")  # fmt: skip
        _write_json_atomic(folder.manifest, manifest)
        done["status"] = "interrupted"
    return done
