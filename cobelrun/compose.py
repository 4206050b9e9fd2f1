r"""Compose a config as ``cobel run`` does and validate it into a task, before anything is written.

The one composer of cobel's configs (used by ``cobel run``'s up-front validation, ``cobel
rerun``, ``cobel show``, the Python API, ``cobel render-cache`` and ``cobel figure``): the
config search path (``./conf`` or a ``-cd``/``-cp`` folder, then the built-in configs),
overrides parsed and checked with close-match suggestions, typos in keys explained, YAML
errors as one line. Everything here raises one-line :class:`~cobelrun.errors.ConfigError`\ s and
writes nothing.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from cobelrun.config import GROUPS, builtin_conf_dir
from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest

__all__ = [
    "composer",
    "foreign_sweeper",
    "user_config_dir",
    "validate",
    "yaml_error",
]


def _check_choices(parsed: list[Any], config_dir: Path | None = None) -> None:
    from cobelrun.config import group_options

    for o in parsed:
        key = o.key_or_group
        if key not in GROUPS or o.package:
            continue
        options = group_options(key, config_dir)
        values = list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.value()]
        for value in values:
            if value is None:
                raise ConfigError(
                    f"{key} must name a config, got null; allowed: {allowed_list(options)} "
                    f"(see `cobel list {key}`)"
                )
            if not isinstance(value, str) or value not in options:
                raise ConfigError(
                    f"unknown {key} {value!r}{suggest(str(value), options)}; "
                    f"allowed: {allowed_list(options)} (see `cobel list {key}`)"
                )


_STRUCT_KEY = re.compile(r"Key '([^']+)' is not in struct")
_COULD_NOT_OVERRIDE = re.compile(r"Could not (?:override|append to config) '([^']+)'")


def _explain_compose_error(exc: Exception, cfg_for_keys: DictConfig | None) -> str:
    text = str(exc)
    m = _COULD_NOT_OVERRIDE.search(text)
    if m and _STRUCT_KEY.search(text + str(exc.__cause__ or "")):
        full = m.group(1)
        parts = full.split(".")
        # the first part of the path that does not exist (a misspelled group such as
        # task.monitors.map.every names 'map', not 'every'), and the keys next to it
        node: Any = cfg_for_keys
        at = len(parts) - 1
        for i, part in enumerate(parts[:-1]):
            if not (isinstance(node, DictConfig) and part in node):
                at = i
                break
            node = node[part]
        allowed: list[str] = []
        if isinstance(node, DictConfig):
            allowed = [str(k) for k in node.keys() if not str(k).startswith("_")]
        leaf = parts[at]
        where = ""
        if at < len(parts) - 1:
            where = f": {'.'.join(parts[:at]) or 'the config'} has no '{leaf}'"
        hint = f"; allowed: {allowed_list(allowed)}" if allowed else ""
        return (
            f"unknown key '{full}'{where}{suggest(leaf, allowed)}{hint} "
            f"(use +{full}=... to add a new key)"
        )
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return first


def yaml_error(exc: BaseException) -> str | None:
    """One line naming the file, line and column of a YAML syntax error in ``exc`` (or its
    causes), or None when ``exc`` is not one."""
    import yaml

    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, yaml.YAMLError):
            mark = getattr(cur, "problem_mark", None) or getattr(cur, "context_mark", None)
            problem = getattr(cur, "problem", None) or str(cur).strip().splitlines()[0]
            context = getattr(cur, "context", None)
            what = f"{context}: {problem}" if context else str(problem)
            if mark is None:
                return f"YAML syntax error: {what}"
            return (
                f"YAML syntax error in {mark.name}, line {mark.line + 1}, column "
                f"{mark.column + 1}: {what}"
            )
        cur = cur.__cause__ or cur.__context__
    return None


def _writable_root(path: Path) -> None:
    """Fail early if results cannot be written under ``path`` (probe with a temporary folder)."""
    import tempfile

    p = path if path.is_absolute() else Path.cwd() / path
    probe = p
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    hint = "choose another folder with hydra.run.dir=... or COBEL_RESULTS=..."
    if not probe.is_dir():
        raise CobelError(f"cannot write results under {path}: {probe} is not a folder; {hint}")
    try:
        tempfile.TemporaryDirectory(dir=probe, prefix=".cobel-probe-").cleanup()
    except OSError as exc:
        raise CobelError(
            f"cannot write results under {path}: {probe} is not writable ({exc.strerror}); {hint}"
        ) from None


def _parse(overrides: list[str]) -> list[Any]:
    """Hydra's parse of command-line overrides, a syntax error as a one-line ConfigError."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    try:
        return OverridesParser.create().parse_overrides(overrides)
    except OverrideParseException as exc:
        raise ConfigError(f"cannot parse override: {str(exc).splitlines()[0]}") from None


def user_config_dir(value: str | None) -> Path | None:
    """A ``-cd``/``-cp`` folder as an absolute path (relative to the working directory)."""
    if value is None:
        return None
    path = Path(value.removeprefix("file://")).expanduser().absolute()
    if not path.is_dir():
        raise ConfigError(f"config folder {value} does not exist (given with -cd/-cp)")
    return path


@contextlib.contextmanager
def composer(
    config_dir: Path | None = None, config_name: str = "config"
) -> Iterator[Callable[..., DictConfig]]:
    """Compose configs as ``cobel run`` does, with errors as one-line ConfigErrors.

    Yields ``compose(overrides, return_hydra_config=False)``: built-in configs (``./conf``
    searched first through ``hydra_plugins/cobel_searchpath``), overrides parsed, chosen
    task/env/agent/protocol names checked with close-match suggestions, typos in keys
    explained. With a user's ``config_dir`` (``-cd``/``-cp``) that folder is the primary one
    (its ``config.yaml`` wins) and the built-in configs are searched after it, so its configs
    can still pick built-in envs, agents and tasks. Used by ``cobel run``'s up-front
    validation, the Python API, ``cobel render-cache`` and ``cobel figure``.

    Hydra is set up with its public ``initialize_config_dir`` (job name ``cobel``); the
    built-in folder after a user's one is added by cobel's search-path plugin
    (:func:`cobelrun.config.builtin_after_main`).
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException, MissingConfigException

    def _compose(overrides: list[str], return_hydra_config: bool = False) -> DictConfig:
        _check_choices(_parse(overrides), config_dir)
        try:
            return compose(config_name, overrides=overrides,
                           return_hydra_config=return_hydra_config)  # fmt: skip
        except MissingConfigException as exc:
            raise ConfigError(str(exc).strip().splitlines()[0]) from None
        except HydraException as exc:
            yaml_msg = yaml_error(exc)
            if yaml_msg is not None:
                raise ConfigError(yaml_msg) from None
            base_cfg = None
            try:  # the config without the bad override, to list the keys that are allowed
                plain = [o for o in overrides if o.split("=", 1)[0] in GROUPS]
                base_cfg = compose(config_name, overrides=plain)
            except HydraException:
                pass
            raise ConfigError(_explain_compose_error(exc, base_cfg)) from None
        except Exception as exc:  # YAML syntax errors, Hydra's ValueErrors on odd overrides
            msg = yaml_error(exc)
            if msg is None:
                lines = str(exc).strip().splitlines()
                msg = f"cannot compose the config: {lines[0] if lines else type(exc).__name__}"
            raise ConfigError(msg) from None

    from cobelrun.config import builtin_after_main, register_resolvers

    register_resolvers()  # ${cobel.id:} in hydra.run.dir
    GlobalHydra.instance().clear()
    try:
        with builtin_after_main(config_dir is not None):
            init = initialize_config_dir(str(config_dir or builtin_conf_dir()), job_name="cobel",
                                         version_base="1.3")  # fmt: skip
        with init:
            yield _compose
    finally:
        GlobalHydra.instance().clear()


def validate(
    overrides: list[str],
    multirun: bool,
    config_dir: Path | None = None,
    config_name: str = "config",
) -> tuple[DictConfig, list[dict]]:
    """Compose (first sweep combination) and build everything once; raise one-line errors.

    Returns the composed config of the first combination, ``hydra`` node included, and for a
    sweep its jobs (``cobelrun.sweep.plan``; empty for a single run).
    """
    from cobelrun.runner import build_task
    from cobelrun.sweep import plan

    first, jobs = overrides, []
    if multirun and foreign_sweeper(overrides):
        # another sweeper (Optuna, ...) expands its own search space: check one job's config
        # with the swept keys left at their defaults
        first = [o.input_line for o in _parse(overrides) if not o.is_sweep_override()]
    elif multirun:
        _check_choices(
            _parse(overrides), config_dir
        )  # every swept value, not only the first combination's
        _, jobs = plan(overrides)
        first = jobs[0]["overrides"] if jobs else overrides
    with composer(config_dir, config_name) as compose:
        cfg = compose(first, return_hydra_config=True)
    if not multirun:
        try:
            out = OmegaConf.select(cfg, "hydra.run.dir")
        except Exception as exc:  # interpolation errors in the output folder pattern
            raise ConfigError(f"cannot resolve hydra.run.dir: {exc}") from None
        if not str(out or "").strip():
            raise ConfigError("hydra.run.dir must name a folder, got an empty string")
        _writable_root(Path(str(out)))
    job_cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    try:
        build_task(job_cfg, probe_agent=True)
    except CobelError:
        raise
    except Exception as exc:  # a value no check anticipated: still one line, nothing written
        lines = str(exc).strip().splitlines()
        raise ConfigError(
            f"invalid config: {type(exc).__name__}: {lines[0] if lines else ''}".rstrip(": ")
        ) from exc
    return cfg, jobs


def foreign_sweeper(overrides: list[str]) -> str | None:
    """The sweeper chosen with ``hydra/sweeper=NAME`` when it is not cobel's own."""
    for o in overrides:
        key, _, value = o.partition("=")
        if key.lstrip("+~") == "hydra/sweeper" and value not in ("", "cobel"):
            return value
    return None
