"""Planning a sweep: the jobs of ``cobel run -m`` expanded from Hydra overrides, in Hydra's
basic sweeper's order, with a bound on their number and the id that names the sweep folder.

Pure functions over override strings (no files): the composer (:mod:`cobelrun.compose`), the
sweep launcher (:mod:`cobelrun.hydra_app`), cobel's own sweeper plugin and figures' run planning
use them. The folder the jobs are written to is :mod:`cobelrun.io.sweep_folder`.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from cobelrun.errors import CobelError


def override_key(override: Any) -> str:
    """Column name for a parsed Hydra override (``agent.epsilon``, ``seed``, ``agent``)."""
    key = str(override.key_or_group)
    return f"{key}@{override.package}" if override.package else key


def is_hydra_key(key: str) -> bool:
    k = key.lstrip("+~")
    return k == "hydra" or k.startswith(("hydra.", "hydra/"))


def plan(overrides: Sequence[str], extra: Sequence[str] = ()) -> tuple[list[str], list[dict]]:
    """Expand sweep overrides into jobs: (swept keys, [{job, overrides, params}, ...]).

    Jobs come in Hydra's BasicSweeper order (cartesian product, last key fastest); ``params``
    holds each job's value of every swept key, typed (int, float, str, bool, None, list, dict).
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    parsed = parser.parse_overrides([*extra, *overrides])
    check_job_count(parsed)
    swept = []
    for o in parsed:
        if o.is_sweep_override() and not is_hydra_key(o.key_or_group):
            swept.append(override_key(o))
    combos = cartesian(parsed)
    jobs = []
    for i, combo in enumerate(combos):
        params: dict[str, Any] = {}
        for o in parser.parse_overrides(list(combo)):
            key = override_key(o)
            if key in swept:
                params[key] = _plain_value(o.value())
        jobs.append({"job": i, "overrides": list(combo), "params": params})
    return swept, jobs


#: the environment variable that raises (or lowers) the largest sweep cobel expands
MAX_JOBS_ENV = "COBEL_MAX_JOBS"
#: default largest number of jobs of one sweep (each job is a folder and a row of sweep.json)
MAX_JOBS = 100_000


def max_jobs() -> int:
    """The largest sweep cobel expands: ``$COBEL_MAX_JOBS`` or :data:`MAX_JOBS`."""
    raw = os.environ.get(MAX_JOBS_ENV, "").strip()
    if not raw:
        return MAX_JOBS
    if not raw.isdigit() or int(raw) < 1:
        raise CobelError(f"{MAX_JOBS_ENV} must be a positive whole number, got {raw!r}")
    return int(raw)


def _n_values(o: Any) -> int:
    """How many values a parsed sweep override takes, counted without listing them."""
    import math as _math

    value = o.value()
    if type(value).__name__ == "RangeSweep":  # hydra.core.override_parser.types.RangeSweep
        start, stop, step = value.start, value.stop, value.step or 1
        return max(0, _math.ceil((stop - start) / step))
    items = getattr(value, "list", None)
    if isinstance(items, list):
        return len(items)
    return 1  # a glob over a config group: a handful of files


def check_job_count(parsed: Sequence[Any]) -> int:
    """The number of jobs of a sweep, counted from its parsed overrides before anything is
    expanded; above :func:`max_jobs` a one-line CobelError names the largest swept key and
    how to raise the limit (``COBEL_MAX_JOBS``)."""
    counts: dict[str, int] = {}
    for o in parsed:
        if o.is_sweep_override() and o.is_discrete_sweep():
            counts[o.get_key_element()] = _n_values(o)
        else:
            counts.pop(o.get_key_element(), None)
    total = 1
    for n in counts.values():
        total *= n
    limit = max_jobs()
    if total > limit:
        key = max(counts, key=lambda k: counts[k])
        raise CobelError(
            f"this sweep has {total:,} jobs ({' x '.join(f'{k}: {n:,}' for k, n in counts.items())}"
            f"), more than the {limit:,} cobel expands; sweep fewer values of {key} or raise the "
            f"limit with {MAX_JOBS_ENV}={total}"
        )
    return total


def cartesian(parsed: Sequence[Any]) -> list[list[str]]:
    """Every job's overrides for parsed Hydra overrides, as Hydra's basic sweeper makes them.

    The cartesian product of the swept values (``a=1,2``, ``range(...)``, ``choice(...)``),
    the last key varying fastest; a key given twice keeps its first position and its last
    value. Only the public ``Override`` API is used (Hydra 1.3's ``BasicSweeper`` lives in a
    private module); ``tests/test_sweep.py`` checks the order against Hydra's.
    """
    import itertools

    from cobelrun.errors import ConfigError

    values: dict[str, list[str]] = {}
    for o in parsed:
        key = o.get_key_element()
        if not o.is_sweep_override():
            values[key] = [f"{key}={o.get_value_element_as_str()}"]
        elif o.is_discrete_sweep():
            values[key] = [f"{key}={v}" for v in o.sweep_string_iterator()]
        else:
            raise ConfigError(
                f"cannot sweep {o.input_line!r} with cobel's sweeper: it takes lists (a=1,2), "
                "range(...) and choice(...); an interval needs a sampling sweeper such as "
                "hydra/sweeper=optuna"
            )
    return [list(c) for c in itertools.product(*values.values())]


def _plain_value(value: Any) -> Any:
    from omegaconf import OmegaConf

    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value)
    if isinstance(value, Mapping):
        return {str(k): _plain_value(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain_value(v) for v in value]
    return value


def sweep_id(jobs: Iterable[Mapping[str, Any]]) -> str:
    """A short hash naming a sweep: the same jobs (overrides, order) give the same id.

    Hydra settings (``hydra.*``, ``hydra/launcher=...``) are left out, so changing the launcher or
    the number of workers resumes the same sweep.
    """
    norm = [sorted(o for o in j["overrides"] if not is_hydra_key(o.split("=", 1)[0])) for j in jobs]
    return hashlib.sha256(json.dumps(norm).encode()).hexdigest()[:10]
