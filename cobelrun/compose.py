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
    "YAML_NODE_LIMIT",
    "announce_shadows",
    "check_yaml_folder",
    "check_yaml_size",
    "composer",
    "config_args",
    "foreign_sweeper",
    "load_config",
    "shadows",
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


def _walk_to(cfg: Any, parts: list[str]) -> tuple[Any, int]:
    """The node at ``parts`` of ``cfg`` (list indices included) and how many parts exist."""
    from omegaconf import ListConfig

    node: Any = cfg
    for i, part in enumerate(parts):
        if isinstance(node, DictConfig) and part in node:
            node = node[part]
        elif isinstance(node, ListConfig) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            return node, i
    return node, len(parts)


#: the schema model of each fixed place of a composed config (``phases.N``: each phase)
def _schema_at(path: list[str]) -> type | None:
    from cobelrun.schema import PhaseSpec, ProtocolSpec, RecordSpec, RunSpec, TaskSpec

    if len(path) == 4 and path[:3] == ["task", "protocol", "phases"] and path[3].isdigit():
        return PhaseSpec
    return {(): RunSpec, ("task",): TaskSpec, ("task", "protocol"): ProtocolSpec,
            ("task", "record"): RecordSpec}.get(tuple(path))  # fmt: skip


#: arguments the runner gives a target itself (``cobelrun.runner.build_task``), not a config
_PROVIDED = {"agent": ("env", "seed")}


def _node_keys(path: list[str], node: Any) -> tuple[list[str], str, bool]:
    """(keys a node takes, what the node is, whether a key outside them may be added) for the
    node at ``path``: a schema model's fields, a ``_target_``'s parameters, or the keys the node
    has."""
    model = _schema_at(path)
    if model is not None:
        names = [n for n in model.model_fields if not n.startswith("_")]
        extra = model.model_config.get("extra") != "forbid"
        if model.__name__ == "PhaseSpec":
            phase = node.get("name") if isinstance(node, DictConfig) else None
            label = f"phase {path[3]}" + (f" ({phase!r})" if isinstance(phase, str) else "")
            return names, label, extra
        return names, ".".join(path) or "the config", extra
    if isinstance(node, DictConfig):
        target = node.get("_target_")
        params = _target_params(str(target)) if isinstance(target, str) else None
        if params is not None:
            names, kwargs = params
            given = _PROVIDED.get(".".join(path), ())
            return [n for n in names if n not in given], f"{'.'.join(path)} ({target})", kwargs
        return [str(k) for k in node.keys() if not str(k).startswith("_")], ".".join(path), True
    return [], ".".join(path), True


def _target_signature(target: str) -> dict[str, Any] | None:
    """A target's parameters (``inspect.Parameter`` by name), or None if it cannot be looked
    at. The gate decides first: nothing unallowed is imported."""
    from cobelrun.config import target_parameters
    from cobelrun.targets import is_allowed

    if not is_allowed(target):
        return None
    try:
        from hydra.utils import get_object

        params, _ = target_parameters(get_object(target))
    except Exception:  # an import error is reported when the target is built
        return None
    return params


def _target_params(target: str) -> tuple[list[str], bool] | None:
    """A target's keyword parameters and whether it takes ``**kwargs``."""
    import inspect

    params = _target_signature(target)
    if params is None:
        return None
    kinds = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
    names = [n for n, p in params.items() if p.kind not in kinds]
    kwargs = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    return names, kwargs


def _failed_key(exc: Exception) -> str | None:
    text = str(exc)
    m = _COULD_NOT_OVERRIDE.search(text)
    if m and _STRUCT_KEY.search(text + str(exc.__cause__ or "")):
        return m.group(1)
    return None


def _declared_keys(
    exc: Exception, overrides: list[str], cfg_for_keys: DictConfig | None
) -> list[str] | None:
    """``overrides`` with ``KEY=VALUE`` made ``++KEY=VALUE`` where Hydra refused a key that the
    config's YAML does not set but its schema model or its ``_target_`` takes (a phase's
    ``max_steps``; ``env.world.goal_reward`` of a world function with that argument); None when
    the refused key is not such a key."""
    full = _failed_key(exc)
    if full is None or cfg_for_keys is None:
        return None
    parts = full.split(".")
    node, found = _walk_to(cfg_for_keys, parts[:-1])
    if found < len(parts) - 1:
        return None
    names, _, _ = _node_keys(parts[:-1], node)
    if parts[-1] not in names:
        return None
    out, changed = [], False
    for o in overrides:
        key = o.split("=", 1)[0]
        if key.lstrip("+") == full and not key.startswith("++") and "=" in o:
            out.append("++" + o.lstrip("+"))
            changed = True
        else:
            out.append(o)
    return out if changed else None


def _check_deletions(parsed: list[Any], cfg: DictConfig) -> None:
    """Refuse ``~KEY`` that deletes a setting the run uses (a schema field or a target's
    argument with a value): the code's default would replace the config's value without a
    word (``~task.runs`` ran 1 run). Deleting what is optional (a monitor, a key whose default
    is null) stays allowed, and so does a key set again by a later override."""
    import inspect

    for o in parsed:
        if not o.is_delete():
            continue
        parts = o.key_or_group.split(".")
        node, found = _walk_to(cfg, parts[:-1])
        if found < len(parts) - 1 or (isinstance(node, DictConfig) and parts[-1] in node):
            continue
        leaf, default = parts[-1], None
        model = _schema_at(parts[:-1])
        if model is not None and leaf in model.model_fields:
            field = model.model_fields[leaf]
            default = "required" if field.is_required() else field.default
        elif isinstance(node, DictConfig) and isinstance(node.get("_target_"), str):
            params = _target_signature(str(node.get("_target_")))
            if params is None or leaf not in params:
                continue  # not looked at (the gate reports a refused target), or no argument
            empty = params[leaf].default is inspect.Parameter.empty
            default = "required" if empty else params[leaf].default
        if default is None or default == {} or default == []:
            continue
        what = (
            "a required key" if default == "required" else f"a setting (its default: {default!r})"
        )
        raise ConfigError(
            f"{o.input_line} deletes {o.key_or_group}, {what} that the run uses; set it "
            f"instead ({o.key_or_group}=VALUE)"
        )


_MERGING = re.compile(r"Error merging override (\S+?)=")


def _explain_compose_error(exc: Exception, cfg_for_keys: DictConfig | None) -> str:
    from omegaconf import ListConfig

    from cobelrun.schema import PhaseSpec

    text = str(exc)
    full = _failed_key(exc)
    merging = _MERGING.search(text)
    if full is None and merging is not None and cfg_for_keys is not None:
        # Hydra's bare "Error merging override": a list index past the end, usually
        key = merging.group(1).lstrip("+~")
        parts = key.split(".")
        node, found = _walk_to(cfg_for_keys, parts)
        if found < len(parts) and isinstance(node, ListConfig):
            where = ".".join(parts[:found])
            if where == "task.protocol.phases":
                names = [str(p.get("name")) if isinstance(p, DictConfig) else "?" for p in node]
                listed = ", ".join(f"{i} {n!r}" for i, n in enumerate(names))
                return (
                    f"{key}: there is no phase {parts[found]}; the protocol has {len(node)} "
                    f"phases ({listed}); add phases in a protocol config (protocol=NAME)"
                )
            return f"{key}: {where} has {len(node)} items (indices 0..{len(node) - 1})"
    if full is not None:
        parts = full.split(".")
        # the first part of the path that does not exist (a misspelled group such as
        # task.monitors.map.every names 'map', not 'every'), and the keys next to it
        node, at = _walk_to(cfg_for_keys, parts[:-1])
        allowed, label, extra = _node_keys(parts[:at], node)
        leaf = parts[at]
        if not allowed and label != ".".join(parts[:at]):  # a target without arguments
            return f"unknown key '{full}': {label} takes no arguments"
        where = ""
        if at < len(parts) - 1 or _schema_at(parts[:at]) is PhaseSpec:
            where = f": {label} has no '{leaf}'"
        hint = f"; allowed: {allowed_list(allowed)}" if allowed else ""
        add = f" (use +{full}=... to add a new key)" if extra else ""
        return f"unknown key '{full}'{where}{suggest(leaf, allowed)}{hint}{add}"
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


#: the config-folder flags ``cobel run`` takes (Hydra's), which ``show`` and ``list`` take too
_DIR_FLAGS = ("-cd", "--config-dir", "-cp", "--config-path")
_NAME_FLAGS = ("-cn", "--config-name")


def config_args(args: list[str]) -> tuple[Path | None, str, list[str]]:
    """``-cd/--config-dir``, ``-cp/--config-path`` and ``-cn/--config-name`` taken out of
    ``args`` (as ``cobel run`` reads them): (the user's config folder or None, the config's
    name, the other arguments). A flag without its value is a one-line ConfigError."""
    folder: str | None = None
    name = "config"
    rest: list[str] = []
    i = 0
    while i < len(args):
        arg = args[i]
        flag, eq, value = arg.partition("=")
        if flag in _DIR_FLAGS + _NAME_FLAGS:
            if not eq:
                if i + 1 >= len(args):
                    raise ConfigError(f"{flag} needs a value")
                value = args[i + 1]
                i += 1
            if flag in _DIR_FLAGS:
                folder = value
            else:
                name = value
        else:
            rest.append(arg)
        i += 1
    return user_config_dir(folder), name, rest


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
        parsed = _parse(overrides)  # once (~2 ms an override): both checks read it
        _check_choices(parsed, config_dir)
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
            declared = _declared_keys(exc, overrides, base_cfg)
            if declared is not None:  # a key the schema or the target takes: set it after all
                return _compose(declared, return_hydra_config)
            raise ConfigError(_explain_compose_error(exc, base_cfg)) from None
        except Exception as exc:  # YAML syntax errors, Hydra's ValueErrors on odd overrides
            msg = yaml_error(exc)
            if msg is None:
                lines = str(exc).strip().splitlines()
                msg = f"cannot compose the config: {lines[0] if lines else type(exc).__name__}"
            raise ConfigError(msg) from None
        _check_deletions(parsed, cfg)
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
    built: dict[str, Any] | None = None,
) -> tuple[DictConfig, list[dict]]:
    """Compose (first sweep combination) and build everything once; raise one-line errors.

    Returns the composed config of the first combination, ``hydra`` node included, and for a
    sweep its jobs (``cobelrun.sweep.plan``; empty for a single run). ``built``, when given,
    receives the task built from it (``built["task"]``), so a single run need not build it
    again.
    """
    from cobelrun.runner import build_task
    from cobelrun.startup import resume_gc
    from cobelrun.sweep_plan import plan

    if multirun:
        resume_gc()  # a sweep's launcher runs long: its garbage is collected as usual
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
    _check_hydra_paths(cfg)
    if multirun:
        announce_setup(cfg)
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
        task = build_task(job_cfg, probe_agent=True)
    except CobelError:
        raise
    except Exception as exc:  # a value no check anticipated: still one line, nothing written
        lines = str(exc).strip().splitlines()
        raise ConfigError(
            f"invalid config: {type(exc).__name__}: {lines[0] if lines else ''}".rstrip(": ")
        ) from exc
    if built is not None:
        built["task"] = task
    return cfg, jobs


#: how a log file's name must start: inside the job's output folder
_IN_OUTPUT = ("${hydra.runtime.output_dir}/", "${hydra:runtime.output_dir}/")


def _check_hydra_paths(cfg: DictConfig) -> None:
    """Files Hydra writes besides the run's own stay inside the run folder: its record of the
    job (``hydra.output_subdir``, relative, no ``..``) and log files of the logging configs
    (``filename`` under ``${hydra.runtime.output_dir}/``), so a config from elsewhere cannot
    make Hydra write, or truncate, a file outside it."""
    from pathlib import PurePosixPath

    sub = OmegaConf.select(cfg, "hydra.output_subdir", default=None)
    if sub is not None:
        parts = PurePosixPath(str(sub)).parts
        if str(sub).startswith("/") or ".." in parts or "${" in str(sub):
            raise ConfigError(
                f"hydra.output_subdir must be a folder name inside the run folder (like .hydra), "
                f"got {sub!r}"
            )
    for node_key in ("hydra.job_logging", "hydra.hydra_logging"):
        node = OmegaConf.select(cfg, node_key, default=None)
        if not isinstance(node, DictConfig):
            continue
        raw = OmegaConf.to_container(node, resolve=False)
        handlers = raw.get("handlers") if isinstance(raw, dict) else None
        for name, handler in (handlers or {}).items():
            name_ = handler.get("filename") if isinstance(handler, dict) else None
            if name_ is None:
                continue
            text = str(name_)
            inside = text.startswith(_IN_OUTPUT) and ".." not in PurePosixPath(text).parts
            here = "/" not in text and text.endswith(".log")  # hydra/hydra_logging=hydra_debug
            if not (inside or here):
                raise ConfigError(
                    f"{node_key}.handlers.{name}.filename must name a log file inside the run "
                    f"folder (${{hydra.runtime.output_dir}}/NAME.log), got {text!r}"
                )


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
#: the largest config file read (a task's config is a few KiB)
YAML_BYTES_LIMIT = 16 * 2**20
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
    import stat as stat_

    import yaml

    limit = YAML_NODE_LIMIT if limit is None else limit
    try:
        stat = path.stat()
    except OSError:
        return
    if not stat_.S_ISREG(stat.st_mode):
        raise ConfigError(f"{path} is not a regular file (a config must be one)")
    if stat.st_size > YAML_BYTES_LIMIT:
        raise ConfigError(
            f"{path} holds {stat.st_size:,} bytes; a config file may hold at most "
            f"{YAML_BYTES_LIMIT:,} (refusing to read it)"
        )
    key = (str(path), stat.st_mtime_ns, stat.st_size)
    if key in _YAML_CHECKED:
        return
    try:
        with open(path, encoding="utf-8") as f:
            docs = list(yaml.compose_all(f, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)))
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


def announce_setup(cfg: DictConfig) -> None:
    """One line on stderr naming the shell lines a launcher puts into every job's batch script
    (``hydra.launcher.setup`` of submitit's SLURM launcher): they are code by design, so a
    sweep says which lines it will run before it submits anything."""
    import sys

    try:
        setup = OmegaConf.select(cfg, "hydra.launcher.setup", default=None)
    except Exception:  # an unresolvable line: the launcher reports it
        return
    if setup:
        lines = "; ".join(repr(str(line)) for line in setup)
        print(f"cobel: note: hydra.launcher.setup runs these shell lines in every job: {lines}",
              file=sys.stderr)  # fmt: skip


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
