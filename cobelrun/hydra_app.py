"""Hydra glue for ``cobel run``: config search path, up-front validation, the job function.

Arguments reach Hydra unchanged. Before Hydra launches anything, the overrides are parsed, the
chosen task/env/agent/protocol names are checked (with close-match suggestions), the config is
composed and every part is built once, so bad input fails with one line before any output
folder is created.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from cobelrun.config import builtin_conf_dir, register_resolvers
from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest

CHOICE_GROUPS = ("task", "env", "agent", "protocol")


def _check_choices(parsed: list[Any]) -> None:
    from cobelrun.config import group_options

    for o in parsed:
        key = o.key_or_group
        if key not in CHOICE_GROUPS or o.package:
            continue
        options = group_options(key)
        values = list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.value()]
        for value in values:
            if value is None and key != "task":
                continue
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
        parent, _, leaf = full.rpartition(".")
        allowed: list[str] = []
        if cfg_for_keys is not None:
            node = OmegaConf.select(cfg_for_keys, parent) if parent else cfg_for_keys
            if isinstance(node, DictConfig):
                allowed = [str(k) for k in node.keys() if not str(k).startswith("_")]
        hint = f"; allowed: {allowed_list(allowed)}" if allowed else ""
        return (
            f"unknown key '{full}'{suggest(leaf, allowed)}{hint} (use +{full}=... to add a new key)"
        )
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return first


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


def validate(config_dir: Path, overrides: list[str], multirun: bool) -> DictConfig:
    """Compose (first sweep combination) and build everything once; raise one-line errors."""
    from hydra import compose, initialize_config_dir
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException, MissingConfigException, OverrideParseException

    from cobelrun.runner import build_task

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except OverrideParseException as exc:
        raise ConfigError(f"cannot parse override: {str(exc).splitlines()[0]}") from None
    _check_choices(parsed)
    first = overrides
    if multirun:
        combos = BasicSweeper.split_arguments(parsed, None)
        first = list(combos[0][0]) if combos and combos[0] else overrides
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            try:
                cfg = compose("config", overrides=first, return_hydra_config=True)
            except MissingConfigException as exc:
                raise ConfigError(str(exc).strip().splitlines()[0]) from None
            except HydraException as exc:
                base_cfg = None
                try:
                    plain = [o for o in first if o.split("=", 1)[0] in CHOICE_GROUPS]
                    base_cfg = compose("config", overrides=plain)
                except HydraException:
                    pass
                raise ConfigError(_explain_compose_error(exc, base_cfg)) from None
    finally:
        GlobalHydra.instance().clear()
    run_dir_key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    try:
        out = OmegaConf.select(cfg, run_dir_key)
    except Exception as exc:  # interpolation errors in the output folder pattern
        raise ConfigError(f"cannot resolve {run_dir_key}: {exc}") from None
    _writable_root(Path(str(out)))
    job_cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    build_task(job_cfg, probe_agent=True)
    return job_cfg


def job(cfg: DictConfig) -> str:
    """The Hydra task function: run one job into Hydra's output folder."""
    from hydra.core.hydra_config import HydraConfig

    from cobelrun.progress import run_progress
    from cobelrun.runner import run

    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = str(hc.mode) == "RunMode.MULTIRUN"
    try:
        with run_progress(f"{cfg.task.name}", enabled=not multirun) as progress:
            run(cfg, run_dir, progress=progress)
    except CobelError as exc:
        if multirun:
            raise
        print(f"cobel: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print(f"cobel: interrupted; partial results in {run_dir}", file=sys.stderr)
        sys.exit(130)
    if not multirun:
        print(run_dir)
    return str(run_dir)


def launch(args: list[str]) -> int:
    """Run Hydra on ``args`` (what follows ``cobel run``); return the exit code."""
    from hydra._internal.utils import _run_hydra, get_args_parser

    register_resolvers()
    parser = get_args_parser()
    parser.prog = "cobel run"
    parsed = parser.parse_args(args)
    # ./conf is put first on the search path by hydra_plugins/cobel_searchpath
    config_dir, overrides = builtin_conf_dir(), list(parsed.overrides)
    informational = (
        parsed.help or parsed.hydra_help or parsed.cfg or parsed.info or parsed.shell_completion
    )
    if not informational:
        validate(config_dir, overrides, bool(parsed.multirun))
    _run_hydra(
        args=parsed,
        args_parser=parser,
        task_function=job,
        config_path=str(config_dir),
        config_name="config",
    )
    return 0
