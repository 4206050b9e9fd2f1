"""Run manifest: what ran, where, with which versions, and how it ended.

``manifest.json`` is written atomically (temporary file + ``os.replace``), so a reader never sees
a half-written file, even if the run is killed while writing it.
"""

from __future__ import annotations

import copy
import datetime as _dt
import functools
import hashlib
import importlib.metadata
import json
import math
import os
import platform
import socket
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from cobelrun._version import __version__

__all__ = [
    "MANIFEST_NAME",
    "STATUSES",
    "Manifest",
    "config_hash",
    "git_info",
    "package_versions",
]

MANIFEST_NAME = "manifest.json"
#: Final statuses accepted by :meth:`Manifest.finish`.
STATUSES = ("completed", "interrupted", "failed")

#: Distributions whose versions are recorded when installed (never imported to find out).
_PACKAGES = (
    "numpy",
    "numba",
    "pandas",
    "pyarrow",
    "mcap",
    "zstandard",
    "hydra-core",
    "omegaconf",
    "gymnasium",
    "scipy",
    "torch",
    "stable-baselines3",
    "pybullet",
)
_GIT_TIMEOUT_S = 2.0


from cobelrun.io.run_folder import DONE_MARKER  # noqa: E402, F401 (re-exported)


def _plain(obj: Any) -> Any:
    """Convert configs (dicts, OmegaConf containers, numpy values, paths) to JSON-able data."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, str | bytes):
        return obj.decode() if isinstance(obj, bytes) else obj
    if isinstance(obj, Sequence | set | frozenset):
        items = sorted(obj, key=repr) if isinstance(obj, set | frozenset) else obj
        return [_plain(v) for v in items]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "tolist") and hasattr(obj, "dtype"):  # numpy scalars and arrays
        return _plain(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return repr(obj)  # 'nan', 'inf': canonical text instead of invalid JSON
    return obj


def canonical_json(config: Mapping[str, Any]) -> str:
    """Canonical JSON text of a config: sorted keys, no whitespace, UTF-8 kept."""
    return json.dumps(
        _plain(config), sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=str
    )


def config_hash(config: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of the canonical JSON of a resolved config.

    Equal configs give equal hashes whatever their key order or container type (dict or
    OmegaConf ``DictConfig``); any changed value changes the hash.

    Parameters
    ----------
    config : Mapping
        The resolved config.

    Returns
    -------
    str
        64 hex characters.
    """
    return hashlib.sha256(canonical_json(config).encode("utf-8")).hexdigest()


def package_versions() -> dict[str, str]:
    """Versions of Python and the key packages that are installed (via importlib.metadata).

    Looked up once per process (~20 ms; a sweep worker runs many jobs): what a process has
    imported does not change while it runs.
    """
    return dict(_package_versions())


@functools.cache
def _package_versions() -> dict[str, str]:
    versions = {"python": platform.python_version(), "cobelrun": __version__}
    for name in _PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return versions


def _git(args: list[str], cwd: Path) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=_GIT_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def git_info(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """Commit and dirty flag of the git repository containing ``path``, or None.

    Asked once per process and repository (three ``git`` calls, ~10 ms; none for a folder
    outside any repository, :func:`_repository_folder`): a sweep worker's jobs record the
    state of the repository when the worker started, i.e. of the code it runs.

    Parameters
    ----------
    path : str or Path
        A folder inside the repository.

    Returns
    -------
    dict or None
        ``{"commit": <sha>, "dirty": bool, "root": <top-level folder>}``; None when ``path`` is
        not in a git repository, git is missing, or git does not answer within 2 s.
    """
    folder = Path(path).absolute()
    if not folder.is_dir():
        return None
    if any(name in os.environ for name in _GIT_ENV):
        key: str | None = str(folder)  # git's discovery is steered from outside: ask git itself
    else:
        key = _repository_folder(folder)
        if key is None:
            return None  # no repository above it: git would say so, at the cost of a process
    return copy.deepcopy(_git_info(key))


#: environment variables that change where git looks for a repository
_GIT_ENV = ("GIT_DIR", "GIT_WORK_TREE", "GIT_CEILING_DIRECTORIES",
            "GIT_DISCOVERY_ACROSS_FILESYSTEM", "GIT_COMMON_DIR")  # fmt: skip


def _repository_folder(folder: Path) -> str | None:
    """The folder at which git's own search for a repository stops when started in
    ``folder``, or None when it finds none: the nearest folder, ``folder`` itself first (its
    physical path, as git's working directory is), that holds ``.git`` or is a git directory
    itself (a bare repository), not crossing into another file system (git stops there too).

    Every folder inside one repository gives the same answer, so the run folder's and
    cobel's git state, when both lie in one repository, take one set of ``git`` calls, and a
    folder outside any repository takes none (issue 38: each call is a process).
    """
    try:
        start = folder.resolve()
        device = start.stat().st_dev
        for candidate in (start, *start.parents):
            if candidate.stat().st_dev != device:
                return None
            if (candidate / ".git").exists() or (
                (candidate / "HEAD").is_file()
                and (candidate / "objects").is_dir()
                and (candidate / "refs").is_dir()
            ):
                return str(candidate)
    except OSError:
        return str(folder)  # not readable here: let git decide
    return None


@functools.cache
def _git_info(path: str) -> dict[str, Any] | None:
    cwd = Path(path)
    if not cwd.is_dir():
        return None
    commit = _git(["rev-parse", "HEAD"], cwd)
    if not commit:
        return None
    status = _git(["status", "--porcelain", "--untracked-files=no"], cwd)
    root = _git(["rev-parse", "--show-toplevel"], cwd)
    return {"commit": commit, "dirty": bool(status) if status is not None else None, "root": root}


def _now() -> _dt.datetime:
    return _dt.datetime.now(_dt.UTC)


def _write_json_atomic(path: Path, data: Mapping[str, Any]) -> None:
    """Write ``data`` as JSON to ``path`` through a temporary file and a rename.

    On a full disk (ENOSPC/EDQUOT) the temporary copy may not fit next to the old file; then
    the old file is overwritten in place with compact JSON (its blocks are reused), so that a
    run on a full disk can still record why it failed.
    """
    import errno

    text = json.dumps(_plain(data), indent=2, ensure_ascii=False, default=str) + "\n"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT) or not path.is_file():
            raise
        if tmp.exists():
            tmp.unlink()  # give its blocks back first
        # compact (no indentation: ~40 % smaller), so that it fits in the blocks the old file
        # holds when the new one is longer (an error message added)
        text = json.dumps(_plain(data), separators=(",", ":"), ensure_ascii=False, default=str)
        with open(path, "r+", encoding="utf-8") as f:
            f.write(text + "\n")
            f.truncate()
            f.flush()
            os.fsync(f.fileno())
    finally:
        if tmp.exists():
            tmp.unlink()


class Manifest:
    """The ``manifest.json`` of one run folder.

    Parameters
    ----------
    run_dir : Path
        The run folder (created if missing).

    Examples
    --------
    >>> m = Manifest(run_dir)  # doctest: +SKIP
    >>> m.start(config=cfg, seed=3, task="tmaze_extinction")  # doctest: +SKIP
    >>> m.finish("completed", n_trials=200)  # doctest: +SKIP
    """

    def __init__(self, run_dir: str | os.PathLike[str]) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / MANIFEST_NAME
        self.data: dict[str, Any] = {}
        self._t0: float | None = None

    def start(
        self,
        *,
        config: Mapping[str, Any],
        seed: int,
        task: str,
        extra: Mapping[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Write the manifest of a starting run (status ``"running"``).

        Parameters
        ----------
        config : Mapping
            The resolved config (stored, and hashed into ``config_hash``).
        seed : int
            The run's root seed.
        task : str
            Task name.
        extra : Mapping, optional
            More top-level fields (e.g. ``{"job": "3"}``); may not replace the standard ones.

        Returns
        -------
        dict
            The manifest as written.
        """
        self.run_dir.mkdir(parents=True, exist_ok=True)
        started = _now()
        self._t0 = time.monotonic()
        cwd = Path.cwd()
        src = Path(__file__).resolve().parents[1]  # the cobelrun package
        data: dict[str, Any] = {
            "status": "running",
            "task": task,
            "seed": int(seed),
            "config_hash": config_hash(config),
            "cobelrun_version": __version__,
            "versions": package_versions(),
            "git": {"cwd": git_info(cwd), "cobelrun": git_info(src)},
            "hostname": socket.gethostname(),
            "platform": platform.platform(),
            "pid": os.getpid(),
            "cwd": str(cwd),
            "command": list(sys.argv),
            "started_at": started.isoformat(),
            "config": _plain(config),
        }
        if extra:
            clash = sorted(set(extra) & set(data))
            if clash:
                raise ValueError(f"manifest extra fields {clash} would replace standard fields")
            data.update(_plain(extra))
        self.data = data
        _write_json_atomic(self.path, data)
        return data

    def finish(self, status: str, **extra: Any) -> dict[str, Any]:
        """Record how the run ended.

        Parameters
        ----------
        status : {"completed", "interrupted", "failed"}
            Final status.
        **extra
            More fields, e.g. ``error="ValueError: ..."`` for failed runs or ``n_trials=200``.

        Returns
        -------
        dict
            The manifest as written.
        """
        if status not in STATUSES:
            raise ValueError(f"manifest status must be one of {list(STATUSES)}, got {status!r}")
        if not self.data and self.path.exists():
            self.data = self.read()
        ended = _now()
        data = dict(self.data)
        data["status"] = status
        data["ended_at"] = ended.isoformat()
        if self._t0 is not None:
            data["duration_s"] = round(time.monotonic() - self._t0, 6)
        elif "started_at" in data:
            started = _dt.datetime.fromisoformat(data["started_at"])
            data["duration_s"] = round((ended - started).total_seconds(), 6)
        data.update(_plain(extra))
        self.data = data
        self.run_dir.mkdir(parents=True, exist_ok=True)
        _write_json_atomic(self.path, data)
        return data

    def read(self) -> dict[str, Any]:
        """Read ``manifest.json`` from disk."""
        with open(self.path, encoding="utf-8") as f:
            return json.load(f)

    def __repr__(self) -> str:
        return f"Manifest({str(self.path)!r}, status={self.data.get('status')!r})"
