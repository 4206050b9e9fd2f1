"""``cobel edit``'s config files: reading a gridworld env config into a
:class:`~cobelrun.web.grid_design.GridDesign`, and writing ``env/NAME.yaml`` (and
``task/NAME.yaml``) into the user's config folder in the form of the built-in configs.

Configs are data: a file is size-checked (:func:`cobelrun.compose.check_yaml_size`) before it is
parsed, parsed with ruamel.yaml's round-trip loader (which builds no Python objects from tags),
and its world is built only through cobel's instantiation gate
(:func:`cobelrun.config.instantiate`). Saving keeps every key and comment of the loaded file
that the editor does not own (ruamel.yaml's round trip); an unchanged env is written back
byte for byte. Nothing is written outside the chosen config folder.
"""

from __future__ import annotations

import io
import os
import re
import tempfile
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest
from cobelrun.web.grid_design import OWNED_KEYS, PASS_KEYS, GridDesign, check_size

__all__ = [
    "TEMPLATES",
    "Loaded",
    "check_name",
    "env_names",
    "load",
    "load_template",
    "save",
]

#: what a config name may be: a letter, then letters, digits, ``_`` or ``-`` (64 at most)
NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,63}")
#: env targets the editor edits
GRID_ENVS = (
    "cobelrun.envs.GridWorldEnv",
    "cobelrun.envs.DiscreteGridWorldEnv",
    "cobelrun.envs.gridworld.GridWorldEnv",
    "cobelrun.envs.gridworld.DiscreteGridWorldEnv",
)
LAYOUT_BUILDERS = ("cobelrun.envs.world.from_layout", "cobelrun.envs.from_layout")
#: world builders whose worlds the editor converts into a layout (their size is known up front)
BUILDERS = (*LAYOUT_BUILDERS, "cobelrun.envs.world.open_field", "cobelrun.envs.open_field",
            "cobelrun.envs.world.t_maze", "cobelrun.envs.t_maze",
            "cobelrun.envs.world.tmaze_paper", "cobelrun.envs.tmaze_paper",
            "cobelrun.envs.world.blodgett", "cobelrun.envs.blodgett")  # fmt: skip
#: built-in envs to start from: name -> (label, the built-in task whose protocol comes along)
TEMPLATES: dict[str, tuple[str, str]] = {
    "open_field": ("open field", "gridworld"),
    "tmaze_paper": ("T-maze (paper; acquisition, extinction)", "tmaze_extinction"),
    "tmaze": ("T-maze (stem and arms)", "gridworld"),
    "blodgett_onehot": ("Blodgett maze (latent learning)", "latent_learning"),
    "dyna_maze": ("Dyna maze", "dyna_maze"),
    "linear_track": ("linear track", "linear_track"),
    "gridworld_layout": ("small layout", "gridworld"),
}
MARK = "made with cobel edit"


def _yaml() -> Any:
    try:
        from ruamel.yaml import YAML
    except ImportError:
        raise CobelError("cobel edit needs ruamel.yaml: pip install 'ruamel.yaml>=0.18'") from None
    y = YAML(typ="rt")
    y.indent(mapping=2, sequence=4, offset=2)
    y.width = 100
    y.preserve_quotes = True
    return y


def plain(value: Any) -> Any:
    """ruamel's round-trip containers as plain dicts, lists and scalars."""
    if isinstance(value, dict):
        return {plain(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    for kind in (bool, int, float, str):  # ruamel's ScalarFloat, ScalarInt, ... as builtins
        if isinstance(value, kind):
            return kind(value)
    return value


def read_yaml(path: Path) -> Any:
    """A config file as ruamel round-trip data: size and aliases bounded first, a syntax error
    as one line naming the file; it must hold a mapping."""
    from cobelrun.compose import check_yaml_size

    if not path.is_file():
        raise ConfigError(f"{path} does not exist")
    check_yaml_size(path)
    try:
        doc = _yaml().load(path.read_text(encoding="utf-8"))
    except Exception as exc:  # ruamel's errors: first line
        lines = str(exc).strip().splitlines()
        raise ConfigError(
            f"cannot read {path}: {lines[0] if lines else type(exc).__name__}"
        ) from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{path} is not an env config: it holds no mapping of config keys")
    return doc


def dump(doc: Any) -> str:
    buf = io.StringIO()
    _yaml().dump(doc, buf)
    return buf.getvalue()


def check_name(name: Any) -> str:
    """``name`` if it is a valid config name; else one line saying what is allowed."""
    if not isinstance(name, str) or not NAME_RE.fullmatch(name):
        raise ConfigError(
            f"{name!r} is not a valid config name; use a letter then letters, digits, '_' or '-' "
            "(at most 64), like my_maze"
        )
    return name


@dataclass
class Loaded:
    """An env config as the editor holds it.

    Attributes
    ----------
    design : GridDesign
        What is painted (and the protocol's phases).
    doc : ruamel mapping
        The env file's data, comments included (the editor changes only ``world``).
    source : Path or None
        The file it came from (None: a built-in template).
    text : str
        The file's text as read (written back unchanged when nothing changed).
    task_doc : ruamel mapping or None
        The task that came with it (a built-in task, or ``task/NAME.yaml`` of the folder).
    origin : str
        Where it came from, for messages (``template tmaze_paper``, a file path).
    """

    design: GridDesign
    doc: Any
    source: Path | None
    text: str
    task_doc: Any = None
    origin: str = ""
    task_source: Path | None = None
    loaded: GridDesign | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.loaded is None:
            self.loaded = self.design.copy()


def _builtin() -> Path:
    from cobelrun.config import builtin_conf_dir

    return builtin_conf_dir()


def _declared_size(builder: str, node: dict[str, Any]) -> tuple[int, int] | None:
    """A builder's grid size from its keys, before anything is built (None: fixed small)."""
    name = builder.rsplit(".", 1)[-1]
    try:
        if name == "from_layout":
            rows = textwrap.dedent(str(node["layout"]).expandtabs()).strip("\n").split("\n")
            return max(len(r.rstrip()) for r in rows), len(rows)
        if name == "open_field":
            return int(node["width"]), int(node["height"])
        if name == "t_maze":
            return 2 * int(node["arm_length"]) + 1, int(node["stem_length"]) + 1
    except (KeyError, TypeError, ValueError):
        return None  # the builder's own one-line error follows
    return None


def design_of(doc: Any, where: str) -> GridDesign:
    """The design of an env config's data (``_target_`` a gridworld env, ``world`` a known
    builder); the world is built through cobel's gate, after its size is checked."""
    from cobelrun.config import instantiate

    target = doc.get("_target_")
    if target is None and doc.get("defaults"):
        raise ConfigError(
            f"{where} is composed from other configs (defaults: {plain(doc['defaults'])}); "
            "cobel edit opens env files that stand alone: open the one it builds on"
        )
    if target not in GRID_ENVS:
        raise ConfigError(
            f"{where} is not a gridworld env config (its _target_ is {target!r}); cobel edit "
            f"edits envs built by {allowed_list(GRID_ENVS[:2])}, topology graphs "
            "(cobelrun.envs.TopologyEnv with a topology node) and 2D arenas "
            "(cobelrun.envs.Continuous2DEnv)"
        )
    world = doc.get("world")
    builder = world.get("_target_") if isinstance(world, dict) else None
    if builder not in BUILDERS:
        raise ConfigError(
            f"{where}: its world is built by {builder!r}, which cobel edit cannot draw; it "
            f"edits worlds of {allowed_list(sorted({b.rsplit('.', 1)[-1] for b in BUILDERS}))} "
            "(edit the YAML instead)"
        )
    node = plain(world)
    size = _declared_size(builder, node)
    if size is not None:
        try:
            check_size(*size)
        except CobelError as exc:
            raise type(exc)(f"{where}: {exc}") from None
    built = instantiate("env.world", node)
    extra = {k: node[k] for k in PASS_KEYS if k in node} if builder in LAYOUT_BUILDERS else {}
    design = GridDesign.from_world(built, extra=extra)
    if builder in LAYOUT_BUILDERS:
        design.goal_reward = float(node.get("goal_reward", 1.0))
    design.env_target = str(target)
    design.env_extra = {k: v for k, v in plain(doc).items() if k not in ("_target_", "world")}
    return design


def _task_protocol(task_doc: Any, folders: list[Path]) -> dict[str, Any] | None:
    """``task.protocol`` of a task file: its ``override /protocol`` option (first folder that
    has it) with the task's own ``task.protocol`` keys over it."""
    proto: dict[str, Any] = {}
    for entry in task_doc.get("defaults") or []:
        if isinstance(entry, dict):
            for k, v in entry.items():
                if str(k).strip() in ("override /protocol", "/protocol"):
                    for folder in folders:
                        f = folder / "protocol" / f"{v}.yaml"
                        if f.is_file():
                            proto = plain(read_yaml(f))
                            break
    inline = (task_doc.get("task") or {}).get("protocol")
    if isinstance(inline, dict):
        proto.update(plain(inline))
    return proto or None


def _with_task(design: GridDesign, task_doc: Any, folders: list[Path]) -> None:
    proto = _task_protocol(task_doc, folders) if task_doc is not None else None
    if proto:
        design.phases = [dict(p) for p in proto.get("phases") or [] if isinstance(p, dict)]
        design.max_steps = int(proto.get("max_steps", 100))


def load_template(name: str) -> Loaded:
    """A built-in env (one of :data:`TEMPLATES`, or any built-in gridworld env) and the
    protocol of the built-in task that uses it."""
    path = _builtin() / "env" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"template {name!r} is unknown{suggest(name, TEMPLATES)}; templates: "
                          f"{allowed_list(TEMPLATES)}")  # fmt: skip
    doc = read_yaml(path)
    design = design_of(doc, f"built-in env {name}")
    task = TEMPLATES.get(name, ("", "gridworld"))[1]
    task_doc = read_yaml(_builtin() / "task" / f"{task}.yaml")
    _with_task(design, task_doc, [_builtin()])
    loaded = Loaded(design=design, doc=doc, source=None, text=path.read_text(encoding="utf-8"),
                    task_doc=task_doc, origin=f"template {name}")  # fmt: skip
    return loaded


def load(folder: Path, name: str) -> Loaded:
    """``env/NAME.yaml`` of ``folder`` (with ``task/NAME.yaml``'s protocol where there is one),
    or, if the folder has none, the built-in env ``NAME``."""
    check_name(name)
    path = folder / "env" / f"{name}.yaml"
    if not path.exists():
        if (_builtin() / "env" / f"{name}.yaml").is_file():
            return load_template(name)
        known = env_names(folder)
        raise ConfigError(f"env {name!r} is neither in {folder / 'env'} nor built in"
                          f"{suggest(name, known)}; start from a template or pick one of "
                          f"{allowed_list(known)}")  # fmt: skip
    doc = read_yaml(path)
    design = design_of(doc, str(path))
    task_path = folder / "task" / f"{name}.yaml"
    task_doc = read_yaml(task_path) if task_path.is_file() else None
    if task_doc is not None:
        _with_task(design, task_doc, [folder, _builtin()])
    return Loaded(design=design, doc=doc, source=path, text=path.read_text(encoding="utf-8"),
                  task_doc=task_doc, origin=str(path),
                  task_source=task_path if task_doc is not None else None)  # fmt: skip


def env_names(folder: Path) -> list[str]:
    """The env configs of ``folder`` (``env/*.yaml``) by name."""
    d = folder / "env"
    return sorted(p.stem for p in d.glob("*.yaml")) if d.is_dir() else []


# ---------------------------------------------------------------------- writing
def _flow(seq: list[Any]) -> Any:
    from ruamel.yaml.comments import CommentedSeq

    out = CommentedSeq(seq)
    out.fa.set_flow_style()
    return out


def world_node(design: GridDesign, old: Any | None) -> Any:
    """``env.world`` for ``design``: the old node updated in place where it was a from_layout
    node (its other keys and comments kept), else a new from_layout node."""
    from ruamel.yaml.comments import CommentedMap
    from ruamel.yaml.scalarstring import LiteralScalarString

    kwargs = design.world_kwargs()
    if isinstance(old, dict) and old.get("_target_") in LAYOUT_BUILDERS:
        node = old
    else:
        node = CommentedMap()
        node["_target_"] = "cobelrun.envs.world.from_layout"
    for key in OWNED_KEYS:
        if key not in kwargs:
            node.pop(key, None)
            continue
        value = kwargs[key]
        if key == "layout":
            value = LiteralScalarString(value)
        elif key in ("walls", "one_way", "starts"):
            outer = _flow([_flow(list(p)) for p in value])
            value = outer if len(value) <= 8 else _block([_flow(list(p)) for p in value])
        elif key == "places":
            value = _block_map({k: _flow(list(v)) for k, v in value.items()})
        elif key == "rewards":
            value = _block_map(value)
        node[key] = value
    return node


def _block(items: list[Any]) -> Any:
    from ruamel.yaml.comments import CommentedSeq

    return CommentedSeq(items)


def _block_map(d: dict[Any, Any]) -> Any:
    from ruamel.yaml.comments import CommentedMap

    return CommentedMap(d)


def env_text(loaded: Loaded, design: GridDesign) -> str:
    """The text ``env/NAME.yaml`` gets: the loaded file unchanged where the env is unchanged,
    else its data with ``world`` rewritten (other keys and comments kept)."""
    if _env_part(design) == _env_part(loaded.loaded):  # type: ignore[arg-type]
        return loaded.text
    doc = loaded.doc
    doc["world"] = world_node(design, doc.get("world"))
    if loaded.source is None and MARK not in loaded.text:  # from a template: say so on top
        doc.yaml_set_start_comment(f"Gridworld {MARK} from the built-in env "
                                   f"{loaded.origin.removeprefix('template ')}.")  # fmt: skip
    return dump(doc)


def _env_part(design: GridDesign) -> Any:
    d = design.copy()
    d.phases, d.max_steps = [], 0
    return d


def task_file_text(task_doc: Any, name: str) -> str:
    """A task file: ``task_doc`` (a task's data, comments kept) with ``override /env: NAME``
    and ``task.name: NAME``."""
    from ruamel.yaml.comments import CommentedMap

    defaults = task_doc.get("defaults")
    if defaults is None:
        defaults = task_doc["defaults"] = _block([])
    for entry in defaults:
        if isinstance(entry, dict) and "override /env" in entry:
            entry["override /env"] = name
            break
    else:
        defaults.insert(0, CommentedMap({"override /env": name}))
    task = task_doc.get("task")
    if task is None:
        task = task_doc["task"] = CommentedMap()
    task["name"] = name
    text = dump(task_doc)
    return text if text.startswith("# @package _global_") else "# @package _global_\n" + text


def task_text(loaded: Loaded, design: GridDesign, name: str) -> str:
    """``task/NAME.yaml``: the task that came with the env (a built-in one, or the folder's)
    with ``env`` set to NAME and the edited protocol inline; everything else kept."""

    doc = loaded.task_doc
    if doc is None:
        doc = read_yaml(_builtin() / "task" / "gridworld.yaml")
    return protocol_task_text(doc, name, design, loaded.loaded)


def protocol_task_text(task_doc: Any, name: str, design: Any, before: Any | None) -> str:
    """``task/NAME.yaml`` from ``task_doc`` (:func:`task_file_text`) and, where the design's
    phases differ from ``before``'s (the design as loaded), the edited protocol inline as
    ``task.protocol`` (``max_steps`` and ``phases``), as the built-in tasks give theirs; the
    ``override /protocol`` default stays, its phases replaced. Any design with ``phases`` and
    ``max_steps`` (gridworld, graph, arena)."""
    from ruamel.yaml.comments import CommentedMap

    if design.phases and (before is None or (design.phases, design.max_steps)
                          != (before.phases, before.max_steps)):  # fmt: skip
        task = task_doc.get("task")
        if task is None:
            task = task_doc["task"] = CommentedMap({"name": name})
        task["protocol"] = CommentedMap(
            {"max_steps": int(design.max_steps), "phases": [_phase_map(p) for p in design.phases]}
        )
    return task_file_text(task_doc, name)


def _phase_map(phase: dict[str, Any]) -> Any:
    """A phase as YAML: its rewards, terminals (flow mappings) and starts (a flow list) on
    one line each, as in conf/protocol/*.yaml."""
    from ruamel.yaml.comments import CommentedMap

    out = CommentedMap()
    for k, v in phase.items():
        if k in ("rewards", "terminals") and isinstance(v, dict):
            m = CommentedMap(v)
            m.fa.set_flow_style()
            out[k] = m
        elif k == "starts" and isinstance(v, list):
            out[k] = _flow([_flow(list(x)) if isinstance(x, list | tuple) else x for x in v])
        else:
            out[k] = v
    return out


def _inside(folder: Path, path: Path) -> Path:
    """``path`` if it stays inside ``folder`` (no symlinked folder or file leads out)."""
    root = folder.resolve()
    parent = path.parent.resolve()
    if parent != root and root not in parent.parents:
        raise CobelError(f"{path} would be written outside the config folder {folder}; refusing")
    if path.is_symlink():
        raise CobelError(f"{path} is a symbolic link; cobel edit writes only plain files")
    if path.exists() and not path.is_file():
        raise CobelError(f"{path} exists and is not a file")
    return parent / path.name


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save(folder: Path, name: str, loaded: Loaded, design: GridDesign, *,
         with_task: bool = False, overwrite: bool = False) -> list[Path]:  # fmt: skip
    """Write ``env/NAME.yaml`` (and ``task/NAME.yaml``) into ``folder``, after the design
    passes the checks ``cobel run`` makes; returns the files written.

    Raises
    ------
    CobelError
        A bad name, a design ``cobel run`` would refuse (its message), a file that exists and
        is not the one loaded (unless ``overwrite``), a path leading outside ``folder``.
    """
    check_name(name)
    problems = design.problems()
    if problems:
        raise ConfigError(f"not saved: {problems[0].message}")
    env_path = _inside(folder, folder / "env" / f"{name}.yaml")
    outputs = [(env_path, env_text(loaded, design))]
    if with_task:
        outputs.append((_inside(folder, folder / "task" / f"{name}.yaml"),
                        task_text(loaded, design, name)))  # fmt: skip
    sources = (loaded.source, loaded.task_source)
    write_configs(folder, [(path, text, sources) for path, text in outputs], env_path,
                  overwrite=overwrite)  # fmt: skip
    return [p for p, _ in outputs]


def write_configs(
    folder: Path,
    outputs: Sequence[tuple[Path, str, Sequence[Path | None]]],
    env_path: Path,
    *,
    overwrite: bool = False,
) -> None:
    """Write an editor page's config files, all or none: each ``(path, text, sources)`` text
    must pass ``cobel run``'s check of an env (``path == env_path``) or task config, and a
    file that exists with other text is refused in one line unless it is one the page loaded
    (``sources``) or ``overwrite``."""
    from cobelrun.targets import check_config

    for path, text, loaded_from in outputs:
        ours = any(src is not None and path.resolve() == src.resolve() for src in loaded_from)
        if (
            path.exists()
            and not ours
            and not overwrite
            and path.read_text(encoding="utf-8") != text
        ):
            raise CobelError(f"{path} exists; pick another name (or load it to edit it)")
        check_config(plain(_yaml().load(text)), "env" if path == env_path else "task")
    if not folder.exists():
        folder.mkdir(parents=True)
    for path, text, _ in outputs:
        _write(path, text)
