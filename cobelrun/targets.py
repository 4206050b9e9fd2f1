"""The instantiation gate: which ``_target_``\\ s a config may name.

Configs are data. A ``_target_`` names a Python callable that cobel (or Hydra) calls with the
node's values, so a config that could name any callable could run any code: Hydra's own
blocklist stops ``os.system`` and ``subprocess.*`` but not ``shutil.copyfile`` or a helper
that runs a shell. cobel therefore builds only targets on an allowlist, checked on the dotted
string *before* anything is imported (importing a module runs its code):

* cobel's own classes and functions that configs are meant to build (:data:`BUILTIN`: envs,
  world and topology builders, observation modules, agents, monitors, objectives, task jobs)
  and the Hydra launchers, sweepers and callbacks that Hydra and its installed plugins name
  in their own configs (:data:`HYDRA`);
* those registered by installed packages through the entry-point group ``cobel.targets``
  (:data:`ENTRY_POINT_GROUP`): each entry point's value names a module (everything defined in
  it is allowed) or one callable (``module:Name``); reading them imports nothing;
* those the user names: ``--allow-target PATTERN`` on the command line or the environment
  variable ``COBEL_ALLOW_TARGETS`` (:data:`ENV_VAR`), never a file inside a run or config
  folder.

A pattern is a dotted path (``mypkg.envs.MyEnv``) or a package with ``.*`` (``mypkg.envs.*``:
everything under it). A wildcard never matches a part that starts with ``_``
(``mypkg._private``, ``Cls.__init__``), and once imported, the object must be defined inside the
allowed package (:func:`check_object`), so ``mypkg.envs.*`` does not reach ``mypkg.envs.os.system``.

Hydra's logging configs (``hydra.job_logging``, ``hydra.hydra_logging``) name classes too
(``class:`` and ``():`` keys, ``ext://`` objects, for :func:`logging.config.dictConfig`); they
are checked against :data:`LOGGING`.

This module is part of the library layer: it imports nothing of cobel's orchestration.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

from cobelrun.errors import ConfigError

__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "ENV_VAR",
    "HYDRA",
    "LOGGING",
    "allow",
    "allowed",
    "check_config",
    "check_object",
    "check_target",
    "is_allowed",
    "parse_patterns",
]

#: the entry-point group through which installed packages allow their own targets
ENTRY_POINT_GROUP = "cobel.targets"
#: the environment variable with the user's own patterns (separated by ``,`` or ``:``)
ENV_VAR = "COBEL_ALLOW_TARGETS"

_TD_CONTROL = ("Sarsa", "QLambda", "SarsaLambda", "MCControl", "TabularActorCritic",
               "DynaActorCritic")  # fmt: skip
_ENVS = ("GridWorldEnv", "DiscreteGridWorldEnv", "TopologyEnv", "TwoAFCEnv", "Continuous2DEnv",
         "BanditEnv", "SequenceEnv")  # fmt: skip
_WORLDS = ("from_layout", "open_field", "t_maze", "tmaze_paper", "blodgett")
_AGENTS = ("DynaQ", "PMA", "SFMA", "SRMB", "SRTD", "SRDyna", "ValueIteration", "DQNAgent",
           "DynaDQN", "DynaDSR", "MFEC", "RescorlaWagner", "TDConditioning",
           *_TD_CONTROL)  # fmt: skip
_MONITORS = ("RewardMonitor", "EscapeLatencyMonitor", "ResponseMonitor", "TrajectoryMonitor")

#: cobel's own targets: the classes and functions its configs are meant to build (exact
#: names, as exported by the package and where they are defined). Nothing that writes files
#: or runs other code (``cobelrun.io.*``, the runner, the CLI) is on it.
BUILTIN: tuple[str, ...] = (
    # environments (cobelrun.envs exports them; gymnasium ids use the defining modules)
    *(f"cobelrun.envs.{name}" for name in _ENVS),
    "cobelrun.envs.gridworld.GridWorldEnv",
    "cobelrun.envs.gridworld.DiscreteGridWorldEnv",
    "cobelrun.envs.topology_env.TopologyEnv",
    "cobelrun.envs.choice.TwoAFCEnv",
    "cobelrun.envs.continuous.Continuous2DEnv",
    "cobelrun.envs.bandit.BanditEnv",
    "cobelrun.envs.sequence.SequenceEnv",
    # worlds and topologies (env.world, env.topology)
    *(f"cobelrun.envs.{name}" for name in _WORLDS),
    *(f"cobelrun.envs.world.{name}" for name in _WORLDS),
    "cobelrun.envs.world.World",
    "cobelrun.envs.world.keys_and_doors",
    *(
        f"cobelrun.envs.topology.{name}"
        for name in (
            "grid",
            "hexagonal",
            "delaunay",
            "manual",
            "from_world",
            "from_layout",
            "tmaze_paper",
        )
    ),
    "cobelrun.revaluation.revaluation_world",
    # observation modules (env.observation)
    *(
        f"cobelrun.envs.observations.{name}"
        for name in (
            "PoseObservation",
            "ImageObservation",
            "NoisyObservation",
            "MultiSensoryObservation",
        )
    ),
    "cobelrun.render.benchmark.NoRenderObservation",
    # agents
    *(f"cobelrun.agents.{name}" for name in _AGENTS),
    "cobelrun.agents.actor_critic.ActorCritic",
    "cobelrun.agents.dyna_q.DynaQ",
    "cobelrun.agents.pma.PMA",
    "cobelrun.agents.sfma.SFMA",
    *(f"cobelrun.agents.successor.{name}" for name in ("SRMB", "SRTD", "SRDyna", "ValueIteration")),
    "cobelrun.agents.dqn.DQNAgent",
    "cobelrun.agents.dyna_dqn.DynaDQN",
    "cobelrun.agents.dyna_dsr.DynaDSR",
    "cobelrun.agents.mfec.MFEC",
    "cobelrun.agents.conditioning.RescorlaWagner",
    "cobelrun.agents.conditioning.TDConditioning",
    "cobelrun.agents.conditioning.PearceHall",
    *(f"cobelrun.agents.td_control.{name}" for name in _TD_CONTROL),
    # monitors
    *(f"cobelrun.monitors.{name}" for name in _MONITORS),
    *(f"cobelrun.monitors.trials.{name}" for name in _MONITORS if name != "TrajectoryMonitor"),
    "cobelrun.monitors.trajectory.TrajectoryMonitor",
    "cobelrun.monitors.activity.ActivityMonitor",
    "cobelrun.monitors.maps.ActivityMapMonitor",
    "cobelrun.monitors.probe.GreedyProbeMonitor",
    "cobelrun.monitors.replay.ReplayMonitor",
    "cobelrun.monitors.watermaze.WaterMazeMonitor",
    "cobelrun.monitors.choice.ChoiceMonitor",
    "cobelrun.monitors.conditioning.ConditioningMonitor",
    # objectives (task.objective) and task jobs (task.job)
    "cobelrun.objectives.TrialMean",
    "cobelrun.objectives.ChoiceNLL",
    "cobelrun.revaluation.RevaluationJob",
    "cobelrun.recover.RecoveryJob",
    "cobelrun.render.benchmark.FrameTimeBenchmark",
    # cobel's sweeper (conf/hydra/sweeper/cobel.yaml)
    "hydra_plugins.cobel_sweeper.cobel_sweeper.CobelSweeper",
)

#: the launchers, sweepers, samplers and callbacks of Hydra's plugins (as their own configs
#: name them: ``hydra/launcher=joblib|submitit_local|submitit_slurm|ray``,
#: ``hydra/sweeper=optuna|ax|nevergrad``, ``hydra.callbacks``), whether installed or not;
#: the installed ones, Hydra's basic launcher and sweeper included, are also read from Hydra's
#: config store (:func:`hydra_targets`)
HYDRA: tuple[str, ...] = (
    "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher",
    "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher",
    "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher",
    "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher",
    "hydra_plugins.hydra_ray_launcher.ray_aws_launcher.RayAWSLauncher",
    "hydra_plugins.hydra_rq_launcher.rq_launcher.RQLauncher",
    "hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper",
    "hydra_plugins.hydra_ax_sweeper.ax_sweeper.AxSweeper",
    "hydra_plugins.hydra_nevergrad_sweeper.nevergrad_sweeper.NevergradSweeper",
    *(
        f"optuna.samplers.{name}"
        for name in (
            "TPESampler",
            "RandomSampler",
            "CmaEsSampler",
            "NSGAIISampler",
            "NSGAIIISampler",
            "MOTPESampler",
            "GridSampler",
            "QMCSampler",
        )
    ),
    "hydra.experimental.callbacks.LogJobReturnCallback",
    "hydra.experimental.callbacks.PickleJobInfoCallback",
)

#: classes (``class:``, ``():``) and objects (``ext://``) that Hydra's logging configs may
#: name: the standard library's handlers that write a stream or a file, its formatter and
#: filter, and colorlog's formatter (``hydra/job_logging=colorlog``)
LOGGING: tuple[str, ...] = (
    "logging.StreamHandler",
    "logging.FileHandler",
    "logging.NullHandler",
    "logging.Formatter",
    "logging.Filter",
    "logging.handlers.RotatingFileHandler",
    "logging.handlers.TimedRotatingFileHandler",
    "logging.handlers.WatchedFileHandler",
    "colorlog.ColoredFormatter",
    "sys.stdout",
    "sys.stderr",
)

_IDENT = r"[A-Za-z_][A-Za-z0-9_]*"
#: a ``_target_``: a dotted path of at least two parts
_DOTTED = re.compile(rf"{_IDENT}(\.{_IDENT})+")
#: a pattern: a dotted path, or a package followed by ``.*``
_PATTERN = re.compile(rf"{_IDENT}(\.{_IDENT})*(\.\*)?")


def parse_patterns(text: str | Iterable[str], source: str) -> list[str]:
    """Patterns from ``text`` (separated by ``,``, ``:`` or whitespace) or a list of them;
    a malformed one is a one-line ConfigError naming ``source``."""
    items = re.split(r"[,:\s]+", text) if isinstance(text, str) else list(text)
    out = []
    for item in (str(i).strip() for i in items):
        if not item:
            continue
        if _PATTERN.fullmatch(item) is None:
            raise ConfigError(
                f"{source}: {item!r} is not a target pattern; give a dotted path "
                "(mypkg.envs.MyEnv) or a package followed by .* (mypkg.envs.*)"
            )
        out.append(item)
    return out


@functools.cache
def _hydra_store_targets() -> tuple[str, ...]:
    return tuple(hydra_targets())


@functools.cache
def _entry_point_patterns() -> list[tuple[str, str]]:
    """(pattern, source) of every entry point of :data:`ENTRY_POINT_GROUP` (nothing imported;
    read once per process)."""
    from importlib.metadata import entry_points

    found = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        module, _, attr = ep.value.partition(":")
        module, attr = module.strip(), attr.strip()
        dist = getattr(getattr(ep, "dist", None), "name", None) or "?"
        source = f"entry point {ep.name!r} of {dist}"
        pattern = f"{module}.{attr}" if attr else f"{module}.*"
        if _PATTERN.fullmatch(pattern) is None:
            continue  # a malformed entry point allows nothing
        found.append((pattern, source))
    return found


#: the config-store groups whose options name launchers, sweepers and samplers
_HYDRA_GROUPS = ("hydra/launcher", "hydra/sweeper", "hydra/sweeper/sampler")


def hydra_targets() -> list[str]:
    """The ``_target_`` of every launcher, sweeper and sampler option that Hydra and its
    installed plugins register in Hydra's config store (``hydra/launcher=basic`` and the
    like), read through Hydra's public ``ConfigStore`` after its plugin discovery."""
    from hydra.core.config_store import ConfigStore
    from hydra.core.plugins import Plugins

    Plugins.instance()  # the plugins' modules register their configs when discovered
    store = ConfigStore.instance()
    found = []
    for group in _HYDRA_GROUPS:
        try:
            names = store.list(group)
        except Exception:  # the group does not exist: no such plugin installed
            continue
        for name in names:
            if not name.endswith(".yaml"):
                continue
            node = store.load(f"{group}/{name}").node
            target = node.get("_target_") if hasattr(node, "get") else None
            if isinstance(target, str):
                found.append(target)
    return found


def _patterns(environ: Mapping[str, str] | None = None) -> Iterator[tuple[str, str]]:
    env = os.environ if environ is None else environ
    yield from ((p, "cobel") for p in BUILTIN)
    yield from ((p, "hydra") for p in HYDRA)
    yield from _entry_point_patterns()
    yield from ((p, ENV_VAR) for p in parse_patterns(env.get(ENV_VAR, ""), ENV_VAR))
    # last, as reading Hydra's config store may run its plugin discovery (~1 s when nothing
    # has composed a config yet): only a target no other pattern allows gets here
    yield from ((p, "hydra") for p in _hydra_store_targets())


def allowed(environ: Mapping[str, str] | None = None) -> list[tuple[str, str]]:
    """Every allowed pattern with where it comes from: cobel, Hydra (and the launchers and
    sweepers in Hydra's config store), installed plugins (entry points), the user
    (``COBEL_ALLOW_TARGETS``, which ``--allow-target`` extends)."""
    return list(_patterns(environ))


def _matches(path: str, pattern: str) -> bool:
    if not pattern.endswith(".*"):
        return path == pattern
    prefix = pattern[:-1]  # "mypkg.envs."
    if not path.startswith(prefix) or len(path) == len(prefix):
        return False
    # a wildcard never reaches private or dunder parts (mypkg._x, Cls.__init__.__globals__)
    return not any(part.startswith("_") for part in path[len(prefix) :].split("."))


def _allowing(path: str, environ: Mapping[str, str] | None = None) -> str | None:
    for pattern, _ in _patterns(environ):
        if _matches(path, pattern):
            return pattern
    return None


def is_allowed(path: str, environ: Mapping[str, str] | None = None) -> bool:
    """Whether the dotted ``path`` is on the allowlist (checked on the string: nothing is
    imported)."""
    return isinstance(path, str) and _allowing(path, environ) is not None


def _refusal(where: str, path: Any, what: str = "target", name: str | None = None) -> ConfigError:
    shown = repr(path) if len(repr(path)) <= 120 else repr(path)[:117] + "..."
    name = name if name is not None else path if isinstance(path, str) else ""
    name = name if _PATTERN.fullmatch(name) else "MODULE.NAME"
    return ConfigError(
        f"{where} {shown} is not an allowed {what} (configs build only cobel's own classes, "
        f"those of installed plugins (entry points '{ENTRY_POINT_GROUP}') and those you "
        f"allow); if you trust it: --allow-target {name} or {ENV_VAR}={name}"
    )


def check_target(where: str, path: Any, environ: Mapping[str, str] | None = None) -> str:
    """``path`` if it is an allowed target, else a one-line ConfigError naming ``where`` (the
    key, e.g. ``env._target_``) and how to allow it. Nothing is imported."""
    if not isinstance(path, str) or _DOTTED.fullmatch(path) is None:
        raise ConfigError(
            f"{where} must name a class or function as a dotted path (package.module.Name), "
            f"got {path!r}"
        )
    if not is_allowed(path, environ):
        raise _refusal(where, path)
    return path


def check_object(where: str, path: str, obj: Any, environ: Mapping[str, str] | None = None) -> None:
    """After import: the object ``path`` resolved to is defined where its pattern allows.

    An exact pattern names the object itself. A wildcard (``mypkg.envs.*``) allows objects
    defined in ``mypkg.envs`` or below it, so a module that ``mypkg.envs`` merely imports
    (``mypkg.envs.os.system``) stays out of reach.
    """
    pattern = _allowing(path, environ)
    if pattern is None:
        raise _refusal(where, path)
    if not pattern.endswith(".*"):
        return
    package = pattern[:-2]
    module = getattr(obj, "__module__", None) or getattr(obj, "__name__", None)
    if not isinstance(module, str) or not (module == package or module.startswith(package + ".")):
        raise ConfigError(
            f"{where} {path!r} is defined in {module or 'an unknown module'}, not in "
            f"{package}, which --allow-target {pattern} allows; allow it by its own name "
            f"if you trust it"
        )


def _walk(node: Any, where: str) -> Iterator[tuple[str, Any, Any]]:
    """(key path, key, value) of every entry of nested mappings and lists."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(node, DictConfig | ListConfig):
        node = OmegaConf.to_container(node, resolve=False)
    if isinstance(node, Mapping):
        for key, value in node.items():
            child = f"{where}.{key}" if where else str(key)
            yield child, key, value
            yield from _walk(value, child)
    elif isinstance(node, list | tuple):
        for i, value in enumerate(node):
            child = f"{where}[{i}]"
            yield child, i, value
            yield from _walk(value, child)


#: where Hydra's logging configs live (given to logging.config.dictConfig)
_LOGGING_NODES = ("hydra.job_logging", "hydra.hydra_logging")

#: environment variables a config may not set through ``hydra.job.env_set``: they decide which
#: code a process loads (Python's search path and start-up file, the dynamic linker's preloads
#: and library path, the shell's start-up file, the command search path) or widen this gate
ENV_SET_REFUSED = frozenset({
    "PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PYTHONUSERBASE", "PYTHONEXECUTABLE",
    "PYTHONINSPECT", "PYTHONBREAKPOINT", "LD_PRELOAD", "LD_LIBRARY_PATH", "LD_AUDIT",
    "BASH_ENV", "ENV", "PATH", ENV_VAR,
})  # fmt: skip


def check_config(
    node: Any,
    where: str = "",
    environ: Mapping[str, str] | None = None,
    *,
    resolve: bool = False,
) -> None:
    """Check every ``_target_`` anywhere in ``node`` (mappings and lists, ``hydra.launcher``,
    ``hydra.sweeper`` and ``hydra.callbacks`` included), and the classes of Hydra's logging
    configs, before anything is built. The first refused one is a one-line ConfigError.

    ``resolve``: also import each allowed target and check where the object is defined
    (:func:`check_object`), as just before Hydra builds the node: a wildcard pattern must not
    reach, through a nested node, what its package merely imports."""
    for key_path, key, value in _walk(node, where):
        if key == "_target_":
            check_target(key_path, value, environ)  # an interpolation (${...}) is refused too
            if resolve:
                from hydra.utils import get_object

                try:
                    obj = get_object(value)
                except Exception as exc:  # Hydra reports it as it builds: one line there
                    raise ConfigError(f"{key_path} {value!r} cannot be imported: {exc}") from None
                check_object(key_path, value, obj, environ)
        elif key_path.startswith("hydra.job.env_set.") and key_path.count(".") == 3:
            if str(key).upper() in ENV_SET_REFUSED or str(key).upper().startswith("LD_"):
                raise ConfigError(
                    f"{key_path}: a config may not set {key} (it decides which code the job "
                    "loads); set it in your shell before cobel if you mean it"
                )
        elif key_path.startswith(_LOGGING_NODES):
            if key in ("class", "()") and isinstance(value, str):
                if value not in LOGGING and not is_allowed(value, environ):
                    raise _refusal(key_path, value, "logging class")
            elif isinstance(value, str) and value.startswith("ext://"):
                obj = value.removeprefix("ext://")
                if obj not in LOGGING and not is_allowed(obj, environ):
                    raise _refusal(key_path, value, "logging object", obj)


def allow(patterns: Iterable[str], source: str = "--allow-target") -> None:
    """Add the user's ``patterns`` (``--allow-target``) to :data:`ENV_VAR` of this process, so
    that the processes it starts (a sweep's workers) allow them too."""
    new = parse_patterns(list(patterns), source)
    if not new:
        return
    old = parse_patterns(os.environ.get(ENV_VAR, ""), ENV_VAR)
    os.environ[ENV_VAR] = ",".join(dict.fromkeys([*old, *new]))
