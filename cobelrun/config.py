"""Config helpers: where configs live, validated instantiation, run ids."""

from __future__ import annotations

import contextlib
import importlib
import inspect
import re
import secrets
import types
import typing
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest
from cobelrun.targets import check_config, check_object, check_target

#: config groups users pick an option of by name (``task=NAME``); listed by ``cobel list``
GROUPS = ("task", "env", "agent", "protocol")


def builtin_conf_dir() -> Path:
    """The built-in ``conf/`` folder: inside the installed wheel, or at the source checkout's root."""
    pkg = Path(__file__).resolve().parent
    for candidate in (pkg / "conf", pkg.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise ConfigError(f"cobel's built-in configs are missing (looked in {pkg / 'conf'})")


def user_conf_dir(cwd: Path | None = None) -> Path | None:
    """``./conf`` in the working directory, searched before the built-in configs."""
    path = (cwd or Path.cwd()) / "conf"
    return path if path.is_dir() else None


#: set by :func:`builtin_after_main`, read by ``hydra_plugins/cobel_searchpath``
BUILTIN_AFTER_MAIN = False


@contextlib.contextmanager
def builtin_after_main(on: bool = True) -> Iterator[None]:
    """While Hydra builds its config search path: search the built-in configs right after
    the primary config folder (a user's ``-cd``/``-cp`` folder), through cobel's public
    search-path plugin (``hydra_plugins/cobel_searchpath``)."""
    global BUILTIN_AFTER_MAIN
    before, BUILTIN_AFTER_MAIN = BUILTIN_AFTER_MAIN, on
    try:
        yield
    finally:
        BUILTIN_AFTER_MAIN = before


def search_dirs() -> list[Path]:
    """Config folders in search order (user first)."""
    user = user_conf_dir()
    return ([user] if user else []) + [builtin_conf_dir()]


def group_options(group: str, first: Path | None = None) -> dict[str, Path]:
    """Available options of a config group, name -> file (the first in search order wins).

    ``first`` is a user's config folder (``cobel run -cd DIR``) searched before the others.
    """
    found: dict[str, Path] = {}
    for root in [first] if first is not None else []:
        folder = root / group
        if folder.is_dir():
            for f in sorted(folder.rglob("*.yaml")):
                found.setdefault(f.relative_to(folder).with_suffix("").as_posix(), f)
    for root in search_dirs():
        folder = root / group
        if folder.is_dir():
            for f in sorted(folder.rglob("*.yaml")):
                name = f.relative_to(folder).with_suffix("").as_posix()
                found.setdefault(name, f)
    return found


def describe(path: Path) -> str:
    """The one-line description of a config file: its ``description:`` key or first comment."""
    try:
        cfg = OmegaConf.load(path)
    except Exception:  # a broken file is reported when it is used, not when listed
        return ""
    for node in (cfg, cfg.get("task") if isinstance(cfg, DictConfig) else None):
        if isinstance(node, DictConfig) and isinstance(node.get("description"), str):
            return " ".join(node["description"].split())
    for line in path.read_text().splitlines():
        line = line.strip()
        if line.startswith("#") and not line.startswith("# @package"):
            return line.lstrip("# ").strip()
    return ""


def new_run_id() -> str:
    """A short random id that makes run folders unique even within one second."""
    return secrets.token_hex(4)


def apply_overrides(cfg: DictConfig, parsed: Sequence[Any]) -> None:
    """Apply parsed Hydra value overrides to a composed config, as Hydra's composition does.

    ``key=value`` changes an existing key, ``+key=value`` adds a new one, ``++key=value`` adds
    or changes, ``~key`` (``~key=value``: only if it has that value) deletes. Errors are
    one-line ConfigErrors worded as Hydra's (also where Hydra lets a ValueError through). Hydra 1.3 has no public function for this (its
    own lives in a private module), so it is written here with OmegaConf's public API;
    ``tests/test_api.py`` checks it against Hydra's on the same overrides.
    """
    from omegaconf import open_dict
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError

    for o in parsed:
        key = o.key_or_group
        if o.package is not None:
            raise ConfigError(
                f"Override {o.input_line} looks like a config group override, but config "
                f"group '{key}' does not exist."
            )
        value = o.value()
        try:
            if o.is_delete():
                current = OmegaConf.select(cfg, key, throw_on_missing=False)
                if current is None:
                    raise ConfigError(f"Could not delete from config. '{key}' does not exist.")
                if value is not None and value != current:
                    raise ConfigError(f"Could not delete from config. The value of '{key}' is "
                                      f"{current} and not {value}.")  # fmt: skip
                parent, _, leaf = key.rpartition(".")
                with open_dict(cfg):
                    del (OmegaConf.select(cfg, parent) if parent else cfg)[leaf]
            elif o.is_add():
                if OmegaConf.select(cfg, key, throw_on_missing=False) is not None and not (
                    isinstance(value, dict | list)
                ):
                    raise ConfigError(f"Could not append to config. An item is already at '{key}'.")
                OmegaConf.update(cfg, key, value, merge=True, force_add=True)
            elif o.is_force_add():
                OmegaConf.update(cfg, key, value, merge=True, force_add=True)
            else:
                try:
                    OmegaConf.update(cfg, key, value, merge=True)
                except (ConfigAttributeError, ConfigKeyError):
                    raise ConfigError(f"Could not override '{key}'.") from None
        except ConfigError:
            raise
        except Exception:  # OmegaConf's errors, and a ValueError for a list index like a.x
            raise ConfigError(f"Error merging override {o.input_line}") from None


def register_resolvers() -> None:
    """Register cobel's OmegaConf resolvers (idempotent)."""
    if not OmegaConf.has_resolver("cobel.id"):
        OmegaConf.register_new_resolver("cobel.id", lambda: new_run_id(), use_cache=True)


# -- validated instantiation ------------------------------------------------------------------

_SCALARS = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


#: a ``_target_``: a dotted Python path (``package.module.Name``), nothing relative or empty
_TARGET_PATH = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)+")


def _target(where: str, node: Mapping[str, Any]) -> Any:
    path = node.get("_target_")
    if not isinstance(path, str) or not _TARGET_PATH.fullmatch(path):
        raise ConfigError(
            f"{where}._target_ must name a class or function as a dotted path "
            f"(package.module.Name), got {path!r}"
        )
    check_target(f"{where}._target_", path)  # the gate, on the string: nothing imported yet
    module, _, attr = path.rpartition(".")
    try:
        obj = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError, TypeError) as exc:
        raise ConfigError(f"{where}._target_ {path!r} cannot be imported: {exc}") from None
    check_object(f"{where}._target_", path, obj)
    return obj


def _check_type(where: str, value: Any, annotation: Any) -> None:
    if annotation is inspect.Parameter.empty or value is None:
        return
    if isinstance(value, (DictConfig, ListConfig)):
        return
    origin = typing.get_origin(annotation)
    options = (
        typing.get_args(annotation) if origin in (typing.Union, types.UnionType) else (annotation,)
    )
    scalars = [o for o in options if o in _SCALARS]
    if not scalars or len(scalars) != len(options):
        return  # only plain scalar annotations are checked here; targets check the rest
    for kind in scalars:
        if kind is bool and isinstance(value, bool):
            return
        if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return
        if kind is int and isinstance(value, int) and not isinstance(value, bool):
            return
        if kind is str and isinstance(value, str):
            return
    wanted = " or ".join(_SCALARS[k] for k in scalars)
    raise ConfigError(f"{where} must be {wanted}, got {value!r}")


def _check_null(where: str, annotation: Any, param: inspect.Parameter) -> None:
    """``null`` is allowed where the annotation admits None, the default is None, or nothing
    is declared; elsewhere it is one line naming the key (instead of a TypeError deep inside
    the target)."""
    if param.default is None or annotation in (inspect.Parameter.empty, Any, None, type(None)):
        return
    if isinstance(annotation, str):  # an unresolved forward reference: cannot tell
        return
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _check_null(where, typing.get_args(annotation)[0], param)
    if origin in (typing.Union, types.UnionType):
        if any(a is type(None) or a is Any for a in typing.get_args(annotation)):
            return
    raise ConfigError(f"{where} must not be null")


def target_parameters(target: Any) -> tuple[dict[str, inspect.Parameter], dict[str, Any]]:
    """A callable's parameters and type hints; for a class whose ``__init__`` passes
    ``**kwargs`` on to its base class, the base's parameters too (so they are checked)."""

    def hints_of(fn: Any) -> dict[str, Any]:
        try:
            return typing.get_type_hints(fn)
        except Exception:
            return {}

    if not inspect.isclass(target):
        sig = inspect.signature(target)
        return {n: p for n, p in sig.parameters.items()}, hints_of(target)
    params: dict[str, inspect.Parameter] = {}
    hints: dict[str, Any] = {}
    for cls in target.__mro__:
        init = cls.__dict__.get("__init__")
        if init is None:
            continue
        sig = inspect.signature(init)
        own = {n: p for n, p in sig.parameters.items() if n != "self"}
        kwargs = [n for n, p in own.items() if p.kind is inspect.Parameter.VAR_KEYWORD]
        for n, p in own.items():
            if n not in kwargs:
                params.setdefault(n, p)
        hints = {**hints_of(init), **hints}
        if not kwargs:
            return params, hints
    return params, hints  # every __init__ up to object took **kwargs


def validate_node(where: str, node: Mapping[str, Any], *, provided: Sequence[str] = ()) -> None:
    """Check a ``_target_`` node's keys and scalar types against the target's signature.

    Unknown keys (typos) and values of the wrong type become one-line ConfigErrors that name
    the key and what is allowed. Nested ``_target_`` nodes are checked too. A class whose
    ``__init__`` takes ``**kwargs`` is taken to pass them to its base class's ``__init__``,
    whose parameters are then the allowed extra keys.
    """
    target = _target(where, node)
    params, hints = target_parameters(target)
    takes_kwargs = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    allowed = [
        n for n, p in params.items()
        if p.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
        and n not in provided
    ]  # fmt: skip
    unknown = [k for k in node if not str(k).startswith("_") and (k not in params or k in provided)]
    if unknown and not takes_kwargs:
        if not allowed:
            raise ConfigError(f"unknown key '{where}.{unknown[0]}': {where} "
                              f"({node['_target_']}) takes no arguments")  # fmt: skip
        # a task's settings for its default agent stay when another agent is chosen: name
        # them all at once, with the overrides that drop them
        drop = " ".join(f"~{where}.{k}" for k in unknown)
        if len(unknown) == 1:
            other = (f"; if a config (e.g. the task) sets it for another agent, drop it with "
                     f"{drop}") if where == "agent" else ""  # fmt: skip
            raise ConfigError(f"unknown key '{where}.{unknown[0]}'{suggest(unknown[0], allowed)}"
                              f"; allowed: {allowed_list(allowed)}{other}")  # fmt: skip
        other = (f"; if a config (e.g. the task) sets them for another agent, drop them with "
                 f"{drop}") if where == "agent" else ""  # fmt: skip
        names = ", ".join(f"'{where}.{k}'" for k in unknown)
        raise ConfigError(f"unknown keys {names}; allowed: {allowed_list(allowed)}{other}")
    for key, value in node.items():
        if str(key).startswith("_") or key not in params or key in provided:
            continue  # unknown keys of a target that takes **kwargs: its own to check
        if isinstance(value, Mapping) and "_target_" in value:
            validate_node(f"{where}.{key}", value)
        elif value is None:
            _check_null(f"{where}.{key}", hints.get(key, params[key].annotation), params[key])
        else:
            _check_type(f"{where}.{key}", value, hints.get(key, params[key].annotation))


def factory(where: str, node: DictConfig | Mapping[str, Any]) -> Callable[[], Any]:
    """A function that builds a fresh object from a ``_target_`` node on every call, the node
    validated once (``make_env`` of a batched task builds one environment per run).

    A flat node (its values plain data, no nested ``_target_`` and no Hydra keys) calls its
    target directly with a copy of the values: 0.5 ms per object where :func:`instantiate`
    (validation and Hydra's own instantiation each call) takes ~10 ms. Other nodes go through
    :func:`instantiate` each call, so nested objects are never shared between builds.
    """
    import copy

    from hydra.utils import get_object

    plain = _target_node(where, node)
    check_config(plain, where)
    values = {k: v for k, v in plain.items() if k != "_target_"}
    if any(str(k).startswith("_") for k in values) or _has_target(values):
        return lambda: instantiate(where, plain)
    validate_node(where, plain)
    target = get_object(str(plain["_target_"]))

    def build() -> Any:
        try:
            return target(**copy.deepcopy(values))
        except (CobelError, MemoryError):
            raise
        except Exception as exc:  # as instantiate reports a constructor's error
            raise _build_error(where, exc, exc) from exc

    return build


def _has_target(value: Any) -> bool:
    if isinstance(value, Mapping):
        return "_target_" in value or any(_has_target(v) for v in value.values())
    if isinstance(value, list | tuple):
        return any(_has_target(v) for v in value)
    return False


def instantiate(where: str, node: DictConfig | Mapping[str, Any], **kwargs: Any) -> Any:
    """Validate then instantiate a ``_target_`` node; errors become one-line ConfigErrors."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate as hydra_instantiate

    plain = _target_node(where, node)
    check_config(plain, where, resolve=True)  # every nested _target_, strings first
    validate_node(where, plain, provided=list(kwargs))
    try:
        return hydra_instantiate(plain, **kwargs, _convert_="all")
    except InstantiationException as exc:
        cause = exc.__cause__
        while isinstance(cause, InstantiationException) and cause.__cause__ is not None:
            cause = cause.__cause__
        if isinstance(cause, CobelError | MemoryError):  # MemoryError: a missing estimate
            raise cause from None
        raise _build_error(where, cause or exc, exc) from exc


def _target_node(where: str, node: DictConfig | Mapping[str, Any]) -> Mapping[str, Any]:
    """``node`` as plain data (interpolations resolved); it must have a ``_target_``."""
    plain = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node
    if not isinstance(plain, Mapping) or "_target_" not in plain:
        raise ConfigError(f"{where} must be a config node with a _target_")
    return plain


def _build_error(where: str, cause: BaseException, exc: BaseException) -> ConfigError:
    """One line for a constructor's error: the last line of ``cause``'s message."""
    lines = str(cause).strip().splitlines()
    return ConfigError(f"cannot build {where}: {lines[-1] if lines else exc}")
