"""Figure titles: the task and the overrides a run was made with, never a folder's hash."""

from __future__ import annotations

from pathlib import Path

from cobelrun.errors import CobelError
from cobelrun.io.run_folder import RunFolder

__all__ = ["overrides_of", "run_title"]


def overrides_of(command: list[str] | None) -> list[str]:
    """The ``key=value`` overrides of a ``cobel run`` command line (``hydra.*`` left out)."""
    if not command:
        return []
    return [a for a in command[1:] if "=" in a and not a.lstrip("+~").startswith("hydra.")]


def run_title(run_dir: str | Path) -> str:
    """``task (swept/overridden keys)`` for a figure title: a sweep job's own overrides
    (``job.json``), else those of the ``cobel run`` command; never the folder's hash name
    when the manifest names the task."""
    from cobelrun.io.validate import read_json_or_none, read_manifest

    run_dir = Path(run_dir)
    folder = RunFolder(run_dir)
    if not folder.manifest.is_file():
        return run_dir.name
    try:
        m = read_manifest(folder.manifest)
    except CobelError:
        return run_dir.name
    job = (read_json_or_none(folder.job) or {}).get("overrides")
    given = [str(o) for o in job] if isinstance(job, list) else overrides_of(m.get("command"))
    keys = [
        o for o in given if not o.startswith("task=") and not o.lstrip("+~").startswith("hydra")
    ]
    task = str(m.get("task") or run_dir.name)
    return task + (f" ({', '.join(keys[:4])})" if keys else "")
