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

from cobelrun.config import GROUPS, builtin_conf_dir, user_conf_dir
from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest
from cobelrun.targets import check_config, check_target

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
            cfg = compose(config_name, overrides=overrides,
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
        check_config(cfg)  # the instantiation gate: every _target_, before anything is built
        return cfg

    from cobelrun.config import builtin_after_main, register_resolvers

    register_resolvers()  # ${cobel.id:} in hydra.run.dir
    user = config_dir if config_dir is not None else user_conf_dir()
    if user is not None and user.resolve() != builtin_conf_dir().resolve():
        check_yaml_folder(user)  # bounded before Hydra reads any of its files
        announce_shadows(user)
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
    if multirun:  # a swept _target_: every value through the gate, not only the first job's
        for o in _parse(overrides):
            if o.is_sweep_override() and o.key_or_group.split(".")[-1] == "_target_":
                for value in o.sweep_string_iterator():
                    check_target(o.key_or_group, value)
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


def load_config(path: Path) -> DictConfig:
    """A config file from a run or config folder (``RUN/config.yaml``), as data: YAML aliases
    bounded (:func:`check_yaml_size`) and a syntax error as one line naming the file."""
    check_yaml_size(path)
    try:
        cfg = OmegaConf.load(path)
    except Exception as exc:
        msg = yaml_error(exc)
        lines = str(exc).strip().splitlines()
        raise ConfigError(
            msg or f"cannot read {path}: {lines[0] if lines else type(exc).__name__}"
        ) from None
    if not isinstance(cfg, DictConfig):
        raise ConfigError(f"{path} must hold a mapping of config keys, got a {type(cfg).__name__}")
    return cfg


#: the most nodes a config file may hold once its YAML aliases are expanded (a config of the
#: paper's tasks has a few hundred; "billion laughs" files expand to 10^9 and more)
YAML_NODE_LIMIT = 1_000_000
#: the most YAML files of a user's config folder that are checked (a -cd at a huge folder)
YAML_FILE_LIMIT = 5_000
_YAML_CHECKED: dict[tuple[str, int, int], None] = {}


def check_yaml_size(path: Path, limit: int | None = None) -> None:
    """Refuse a YAML file whose aliases expand beyond :data:`YAML_NODE_LIMIT` nodes.

    OmegaConf (and so Hydra) copies every alias out into a tree, so a file of nested aliases
    ("billion laughs", a few hundred bytes) would take hours and all memory. The file is
    composed into PyYAML's node graph, where an alias is a shared node, and the expanded size
    is counted with each shared node counted once per use (memoised, so this takes
    milliseconds). A file that does not parse is left to the loader's own one-line error.
    """
    import yaml

    limit = YAML_NODE_LIMIT if limit is None else limit
    try:
        stat = path.stat()
    except OSError:
        return
    key = (str(path), stat.st_mtime_ns, stat.st_size)
    if key in _YAML_CHECKED:
        return
    try:
        with open(path, encoding="utf-8") as f:
            docs = list(yaml.compose_all(f, Loader=yaml.SafeLoader))
    except (yaml.YAMLError, OSError, UnicodeDecodeError, RecursionError):
        return  # reported by the loader that reads it
    sizes: dict[int, int] = {}

    def size(node: Any) -> int:
        known = sizes.get(id(node))
        if known is not None:
            return known
        sizes[id(node)] = 1  # a recursive alias counts once
        total = 1
        if isinstance(node, yaml.MappingNode):
            total += sum(size(k) + size(v) for k, v in node.value)
        elif isinstance(node, yaml.SequenceNode):
            total += sum(size(v) for v in node.value)
        sizes[id(node)] = total
        return total

    try:
        total = sum(size(doc) for doc in docs if doc is not None)
    except RecursionError:
        total = limit + 1
    if total > limit:
        raise ConfigError(
            f"{path}: its YAML aliases (&anchor / *alias) expand to more than {limit:,} "
            f"nodes; refusing to load it (a config needs far fewer; is it a 'billion laughs' file?)"
        )
    _YAML_CHECKED[key] = None


def check_yaml_folder(folder: Path) -> None:
    """:func:`check_yaml_size` on the YAML files of a user's config folder (``./conf``, a
    ``-cd`` folder) before Hydra reads any; at most :data:`YAML_FILE_LIMIT` entries of the
    folder are looked at (a ``-cd`` at a home folder is not walked whole)."""
    import os

    seen = 0
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            seen += 1
            if seen > YAML_FILE_LIMIT:
                return
            if name.endswith((".yaml", ".yml")):
                check_yaml_size(Path(root) / name)
        seen += len(dirs)


#: shadowing files already announced in this process (the composer runs several times)
_ANNOUNCED: set[str] = set()


def shadows(user: Path) -> list[tuple[Path, Path]]:
    """(user file, built-in file) of every option of a user's config folder that has the
    name of a built-in one (``./conf/env/tmaze_paper.yaml`` replaces the built-in
    ``env=tmaze_paper``; the folder's own ``config.yaml`` is its primary config, no shadow)."""
    builtin = builtin_conf_dir()
    found = []
    for path in sorted(builtin.rglob("*.yaml")):
        rel = path.relative_to(builtin)
        if len(rel.parts) < 2:
            continue  # config.yaml: the primary config, not a group option
        mine = user / rel
        if mine.is_file() and mine.resolve() != path.resolve():
            found.append((mine, path))
    return found


def announce_shadows(user: Path) -> None:
    """One line on stderr per user config file that replaces a built-in option (once per
    process), so a checked-out ``./conf`` cannot change a plain ``cobel run`` silently."""
    import sys

    for mine, theirs in shadows(user):
        if str(mine) in _ANNOUNCED:
            continue
        _ANNOUNCED.add(str(mine))
        rel = theirs.relative_to(builtin_conf_dir()).with_suffix("")
        group, name = rel.parent.as_posix(), rel.name
        print(f"cobel: note: {mine} replaces the built-in {group}={name} ({theirs})",
              file=sys.stderr)  # fmt: skip
