"""Checks that keep a run from writing where it must not or allocating what the machine lacks.

All of them run before any output folder exists (``cobel run``'s up-front validation and
:func:`cobelrun.runner.build_task`), and each problem is one :class:`~cobelrun.errors.CobelError`
line:

* :func:`check_name`: task names become folder names, so they are limited to a safe character
  set (``task.name=../../x`` is refused);
* :func:`results_root` / :func:`check_inside` / :func:`check_folder`: the output root is
  non-empty (``COBEL_RESULTS=""`` is refused rather than writing to ``/``), absolute after
  resolution and never the file system's root (a symlink to ``/`` is refused), and a run folder
  must stay inside it, also through symlinks (one named with ``hydra.run.dir`` may be anywhere
  but ``/``);
* :func:`estimate_memory` / :func:`check_memory`: what a task's largest batch of trial records
  would allocate, refused with the estimate and the limit when it exceeds the memory available;
* :func:`check_allocation`: the same for a component's own large arrays (a world's transition
  matrix, a network's weights, a replay memory, a cell population), called by the component
  with its estimate *before* it allocates them. While :func:`memory_plan` is active (the
  up-front validation of a run) the estimates add up, so the run's total is checked too.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import re
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError, ConfigError

__all__ = [
    "BYTES_PER_STEP",
    "SAFE_NAME",
    "available_memory",
    "check_allocation",
    "check_folder",
    "check_inside",
    "check_memory",
    "check_name",
    "estimate_memory",
    "format_bytes",
    "memory_plan",
    "results_root",
]

#: task and run names: letters, digits, ``_``, ``-`` and ``.``, starting with a letter or digit
SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,99}")
#: the environment variable that sets the results root
RESULTS_ENV = "COBEL_RESULTS"
#: bytes held per simulated step of a phase's trial batch: the agent's step records (state,
#: action, next state, reward: 4 x 8 B, allocated for trials x max_steps by compiled agents,
#: then copied), the poses (3 x 8 B) and the steps table's columns before they are written
BYTES_PER_STEP = 128
#: share of the available memory a run may plan to use for one batch
MEMORY_SHARE = 0.8


def check_name(where: str, name: Any) -> str:
    """``name`` if it is a safe folder name, else a one-line ConfigError naming ``where``."""
    if not isinstance(name, str) or SAFE_NAME.fullmatch(name) is None:
        shown = repr(name) if len(repr(name)) <= 60 else repr(name)[:57] + "..."
        raise ConfigError(
            f"{where} must be a name of letters, digits, '_', '-' and '.' (starting with a "
            f"letter or digit, at most 100 characters), got {shown}"
        )
    return name


def results_root(environ: Mapping[str, str] | None = None) -> Path:
    """The results root: ``$COBEL_RESULTS`` or ``./results``, absolute and resolved.

    ``COBEL_RESULTS`` set to an empty (or blank) string is refused: it used to put results
    under ``/``.
    """
    env = os.environ if environ is None else environ
    raw = env.get(RESULTS_ENV)
    if raw is not None and not raw.strip():
        raise CobelError(
            f"{RESULTS_ENV} is set but empty; unset it (results go to ./results) or name a folder"
        )
    root = Path(raw if raw is not None else "results").expanduser().absolute().resolve()
    if root == Path(root.anchor):
        shown = f"{RESULTS_ENV}={raw}" if raw is not None else "./results"
        raise CobelError(
            f"the results root ({shown}) resolves to {root}, the file system's root; "
            f"refusing to write there (name a folder of its own, e.g. {RESULTS_ENV}=~/results)"
        )
    return root


def check_folder(path: Path, what: str = "the run folder") -> Path:
    """``path`` made absolute and resolved (symlinks followed); a CobelError if that is the
    file system's root (``hydra.run.dir=/``, or a symlink to ``/``)."""
    resolved = Path(path).expanduser().absolute().resolve()
    if resolved == Path(resolved.anchor):
        raise CobelError(
            f"{what} {path} resolves to {resolved}, the file system's root; refusing to write "
            "there (name a folder of its own)"
        )
    return resolved


def check_inside(path: Path, root: Path, what: str = "the run folder") -> Path:
    """``path`` made absolute and resolved (symlinks followed); a CobelError if that is not
    inside ``root`` (resolved too), e.g. through ``..`` or a symlink that points elsewhere."""
    resolved = Path(path).expanduser().absolute().resolve()
    base = Path(root).expanduser().absolute().resolve()
    if resolved != base and not resolved.is_relative_to(base):
        raise CobelError(
            f"{what} {path} resolves to {resolved}, outside the results root {base}; "
            "refusing to write there (a '..' in a name or a symlink that leaves the root)"
        )
    return resolved


# -- memory ---------------------------------------------------------------------------------


#: seconds :func:`available_memory` reuses what it read from ``/proc`` and the cgroup
MEMORY_READ_TTL = 1.0
_MEMORY_READ: list[Any] = [-math.inf, []]  # (monotonic time of the read, values found)


def _system_memory() -> list[int]:
    """``MemAvailable`` and the cgroup limit (bytes; those that can be read), read at most
    once per :data:`MEMORY_READ_TTL` seconds: agents call :func:`check_allocation` once or
    twice each, and a 20,000-run job would otherwise read these files 40,000 times (~0.3 ms
    per agent, and each read lets a busy writer thread take the GIL)."""
    now = time.monotonic()
    if now - _MEMORY_READ[0] < MEMORY_READ_TTL:
        return list(_MEMORY_READ[1])
    found: list[int] = []
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found.append(int(line.split()[1]) * 1024)
                    break
    except (OSError, ValueError, IndexError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 2**60:
            found.append(int(text))
        break
    _MEMORY_READ[:] = [now, found]
    return list(found)


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (``MemAvailable``, capped by a cgroup
    limit and ``RLIMIT_AS``), or None where that cannot be read. ``/proc/meminfo`` and the
    cgroup are read at most once a second; ``RLIMIT_AS`` and ``COBEL_MEMORY_LIMIT`` always."""
    found = _system_memory()
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY and soft > 0:
            found.append(int(soft))
    except (ImportError, OSError, ValueError):
        pass
    if os.environ.get("COBEL_MEMORY_LIMIT", "").strip():
        found.append(_parse_bytes(os.environ["COBEL_MEMORY_LIMIT"]))
    return min(found) if found else None


def _parse_bytes(text: str) -> int:
    m = re.fullmatch(r"\s*([0-9.]+)\s*([KMGT]?)i?B?\s*", text, re.IGNORECASE)
    if m is None:
        raise CobelError(f"COBEL_MEMORY_LIMIT must be a size like 8G or 512M, got {text!r}")
    scale = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}[m.group(2).upper()]
    return int(float(m.group(1)) * scale)


def format_bytes(n: float) -> str:
    """``12.3 GiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover


def estimate_memory(protocol: Any) -> tuple[int, str]:
    """(bytes, what) of the largest batch of trial records a protocol's phases allocate.

    A phase's trials run as one batch whose step records are held until it is recorded;
    compiled agents allocate ``trials x max_steps`` steps up front. ``protocol`` is a
    :class:`cobelrun.schema.ProtocolSpec` (or anything with ``max_steps`` and ``phases``).
    """
    worst, what = 0, ""
    for i, phase in enumerate(protocol.phases):
        steps = int(phase.max_steps or protocol.max_steps)
        need = int(phase.trials) * steps * BYTES_PER_STEP
        if need > worst:
            worst = need
            what = (
                f"task.protocol.phases[{i}] ({phase.name!r}: {int(phase.trials):,} trials x "
                f"{steps:,} max_steps x {BYTES_PER_STEP} B)"
            )
    return worst, what


def check_memory(protocol: Any, limit: int | None = None) -> None:
    """Refuse a protocol whose largest trial batch would not fit the memory available."""
    need, what = estimate_memory(protocol)
    check_allocation(what, need, "its trial records",
                     "lower the trials or max_steps, or split the phase into several",
                     limit=limit)  # fmt: skip


#: bytes planned so far by the components of the run being validated (see memory_plan)
_PLAN: list[int] | None = None


@contextlib.contextmanager
def memory_plan() -> Iterator[None]:
    """Add up the estimates of :func:`check_allocation` made inside (one run's components:
    its trial records, world, agent, monitors); each new one is checked with the total."""
    global _PLAN
    outer, _PLAN = _PLAN, [0]
    try:
        yield
    finally:
        _PLAN = outer


def check_allocation(
    where: str, nbytes: float, what: str, fix: str = "", limit: int | None = None
) -> None:
    """Refuse, before anything is allocated, an allocation of about ``nbytes`` for ``what``
    (set by the config key ``where``) that exceeds the share of memory a run may use.

    One line: the estimate, the limit, and ``fix`` (what to lower). Inside :func:`memory_plan`
    the run's earlier estimates count too.
    """
    need = max(0, int(nbytes)) if math.isfinite(nbytes) else 2**63
    planned = _PLAN[0] if _PLAN is not None else 0
    limit = available_memory() if limit is None else limit
    if limit is not None and need + planned > MEMORY_SHARE * limit:
        total = f" (with the {format_bytes(planned)} planned before it)" if planned else ""
        raise ConfigError(
            f"{where} would allocate about {format_bytes(need)} for {what}{total}, more than "
            f"the {format_bytes(MEMORY_SHARE * limit)} this run may use "
            f"({int(MEMORY_SHARE * 100)}% of {format_bytes(limit)} available)"
            + (f"; {fix}" if fix else "")
        )
    if _PLAN is not None:
        _PLAN[0] += need


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


def trim_memory() -> None:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim``, as Dask's
    workers do; a no-op elsewhere). Runs leave small freed blocks between long-lived ones
    (the recorder's buffers), which glibc keeps: by the end of 1,000 Fig. 6B runs ~30 MB."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
