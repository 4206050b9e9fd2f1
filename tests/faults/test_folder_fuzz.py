"""Fuzz every file of a real run folder and a real sweep folder with hypothesis (issue 31,
acceptance): truncated and byte-flipped files, JSON and YAML values of the wrong type, huge
and negative numbers, agent archives whose shapes lie, files and folders replaced by links
that point outside the folder, and ``_target_`` entries that name a callable which would
write a canary file (``uuid._get_command_stdout`` running ``touch``, ``shutil.copyfile``).

Each example mutates one file of a fresh copy, then runs one reader in-process: ``cobel
status``, ``plot`` (the task's figure, ``--kind occupancy``, ``trajectories``, ``latency``),
``collect``, ``export nwb``, :func:`cobel.load` and its tables, :func:`cobel.load_sweep`, a
saved agent checked for ``+agent.load_from``, and a rerun's config composed and built
(:func:`cobelrun.api.rerun_config` + :func:`cobelrun.runner.build_task`, what ``cobel rerun``
does before it writes). Every example must end in success or a clean
:class:`~cobelrun.errors.CobelError` (the CLI's one ``cobel: error:`` line), never a traceback;
no canary may appear; nothing outside the copied folder may change (its parent is compared
before and after).

The default suite runs ``COBEL_FOLDER_FUZZ_EXAMPLES`` examples (default 30); the slow test runs
1,000. ``COBEL_FUZZ_LOG=FILE`` writes the counts there after every example.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import zipfile
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cobelrun.errors import CobelError
from tests.faults.folders import TINY, copy_folder, invoke

EXAMPLES = int(os.environ.get("COBEL_FOLDER_FUZZ_EXAMPLES", "30"))
SLOW_EXAMPLES = 1000

FIGURES: Counter = Counter()
_N = itertools.count()

RUN_COMMANDS = (
    "status", "plot", "plot-occupancy", "plot-trajectories", "plot-latency", "export-nwb",
    "load", "load-from", "rerun-config",
)  # fmt: skip
SWEEP_COMMANDS = ("status", "collect", "plot", "load-sweep", "load-job")


#: callables that run a program or write a file, named where a config builds things
def _targets(canary: Path) -> list[dict[str, Any]]:
    return [
        {"_target_": "uuid._get_command_stdout", "_args_": ["touch", str(canary)]},
        {"_target_": "shutil.copyfile", "src": "/etc/hostname", "dst": str(canary)},
        {"_target_": "pathlib.Path.touch", "self": str(canary)},
        {"_target_": "os.system", "_args_": [f"touch {canary}"]},
    ]


JSON_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([0, -1, 1e308, -1e308, 10**400, 1e-320, "nan", "inf", "", "x" * 10_000,
                     "../../etc/passwd", [], {}, [[1, 2, 3]], [[]], {"a": {"b": [None]}}]),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.lists(st.integers(-5, 5), max_size=4),
)  # fmt: skip


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node[:8]):
            out += _paths(v, (*prefix, i))
    return out


def _set(node: Any, path: tuple, value: Any) -> Any:
    if not path:
        return value
    node[path[0]] = _set(node[path[0]], path[1:], value)
    return node


def _dict_paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix] if isinstance(node, dict) else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _dict_paths(v, (*prefix, k))
    return out


def _get(node: Any, path: tuple) -> Any:
    for p in path:
        node = node[p]
    return node


def mutate(data: Any, path: Path, box: Path, canary: Path) -> str:
    """Change the file (or folder) ``path`` in one drawn way; returns what was done."""
    kinds = ["truncate", "flip", "empty", "garbage", "delete", "link-outside", "link-root",
             "link-dev-zero", "link-dangling", "fifo"]  # fmt: skip
    if path.suffix == ".json":
        kinds += ["json-value"] * 4 + ["json-target"] * 2
    if path.suffix == ".yaml":
        kinds += ["yaml-value"] * 2 + ["yaml-target"] * 4
    if path.suffix == ".npz":
        kinds += ["npz-shape"] * 4
    if path.is_dir():
        kinds = ["delete", "link-outside", "link-root", "link-dangling", "fifo"]
    kind = data.draw(st.sampled_from(kinds), label="mutation")
    if kind in ("truncate", "flip", "empty", "garbage") and path.is_dir():
        kind = "delete"
    raw = path.read_bytes() if path.is_file() else b""
    if kind == "truncate":
        path.write_bytes(raw[: data.draw(st.integers(0, max(0, len(raw) - 1)), label="keep")])
    elif kind == "flip":
        buf = bytearray(raw)
        for _ in range(data.draw(st.integers(1, 8), label="flips")):
            if buf:
                i = data.draw(st.integers(0, len(buf) - 1), label="at")
                buf[i] ^= data.draw(st.integers(1, 255), label="bits")
        path.write_bytes(bytes(buf))
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "garbage":
        path.write_bytes(data.draw(st.binary(min_size=1, max_size=64), label="garbage"))
    elif kind == "delete":
        shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
    elif kind == "fifo":  # a named pipe: a reader that opens it waits forever
        shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
        os.mkfifo(path)
    elif kind.startswith("link-"):
        if kind == "link-outside":  # a copy of the real file, outside the folder
            target = box / "outside" / path.name
            if path.is_dir():
                shutil.copytree(path, target, symlinks=True)
            else:
                target.write_bytes(raw)
        else:
            target = {"link-root": Path("/"), "link-dev-zero": Path("/dev/zero"),
                      "link-dangling": box / "nowhere" / path.name}[kind]  # fmt: skip
        shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
        path.symlink_to(target)
    elif kind in ("json-value", "json-target"):
        doc = json.loads(raw)
        if kind == "json-value":
            where = data.draw(st.sampled_from(_paths(doc)), label="key")
            doc = _set(doc, where, data.draw(JSON_VALUES, label="value"))
        else:
            spots = _dict_paths(doc)
            where = data.draw(st.sampled_from(spots), label="node")
            _get(doc, where).update(data.draw(st.sampled_from(_targets(canary)), label="target"))
        path.write_text(json.dumps(doc))
    elif kind in ("yaml-value", "yaml-target"):
        doc = yaml.safe_load(raw) or {}
        if kind == "yaml-value" or not _dict_paths(doc):
            where = data.draw(st.sampled_from(_paths(doc)), label="key")
            doc = _set(doc, where, data.draw(JSON_VALUES, label="value"))
        else:
            where = data.draw(st.sampled_from(_dict_paths(doc)), label="node")
            _get(doc, where).update(data.draw(st.sampled_from(_targets(canary)), label="target"))
        path.write_text(yaml.safe_dump(doc))
    elif kind == "npz-shape":  # a shape table that lies: negative, huge, wrong rows
        import io

        import numpy as np

        rows = data.draw(st.lists(st.lists(st.integers(-(2**40), 2**62), min_size=0, max_size=3),
                                  min_size=1, max_size=2).filter(
                                      lambda r: len({len(x) for x in r}) == 1),
                         label="shapes")  # fmt: skip
        with zipfile.ZipFile(path) as zin:
            members = {n: zin.read(n) for n in zin.namelist()}
        shapes = [n for n in members if n.endswith(".shape.npy")]
        victim = data.draw(st.sampled_from(shapes), label="member")
        b = io.BytesIO()
        np.lib.format.write_array(b, np.array(rows, np.int64).reshape(len(rows), -1))
        members[victim] = b.getvalue()
        with zipfile.ZipFile(path, "w") as zout:
            for n, v in members.items():
                zout.writestr(n, v)
    return kind


def snapshot(box: Path, folder: Path) -> dict[str, tuple]:
    """Every path under ``box`` outside ``folder``: (type, size, mtime) without following links."""
    out = {}
    for p in box.rglob("*"):
        if p == folder or folder in p.parents:
            continue
        st_ = p.lstat()
        out[str(p)] = (st_.st_mode, st_.st_size, st_.st_mtime_ns)
    return out


def run_reader(command: str, folder: Path, box: Path) -> str:
    """Run one reader on ``folder``; 'ok' or 'error' (a clean CobelError). Anything else raises."""
    cli = {
        "status": ("status", str(folder)),
        "plot": ("plot", str(folder)),
        "plot-occupancy": ("plot", str(folder), "--kind", "occupancy"),
        "plot-trajectories": ("plot", str(folder), "--kind", "trajectories"),
        "plot-latency": ("plot", str(folder), "--kind", "latency"),
        "export-nwb": ("export", "nwb", str(folder)),
        "collect": ("collect", str(folder)),
    }
    if command in cli:
        code, out, exc = invoke(*cli[command])
        if exc is not None:
            raise AssertionError(f"traceback from cobel {' '.join(cli[command])}: {exc!r}\n{out}")
        if code == 0:
            return "ok"
        errors = [ln for ln in out.splitlines() if ln.startswith("cobel: error:")]
        if command == "status" and code == 1 and not errors:
            return "error"  # a run or sweep reported as not (cleanly) done
        assert errors, f"exit {code} without an error line: {out}"
        return "error"
    try:
        if command == "load":
            import cobelrun as cobel

            run = cobel.load(folder)
            run.manifest, run.trials, run.summary(), run.config
        elif command == "load-sweep":
            import cobelrun as cobel

            cobel.load_sweep(folder)
        elif command == "load-job":
            from cobelrun.results import load_jobs

            load_jobs(folder)
        elif command == "load-from":
            from cobelrun.agents.base import check_load_from

            check_load_from(_agent(), str(folder), 1)
        elif command == "rerun-config":
            from cobelrun.api import rerun_config
            from cobelrun.runner import build_task

            build_task(rerun_config(folder, ["task.runs=1"]))
        else:  # pragma: no cover
            raise AssertionError(command)
    except CobelError:
        return "error"
    return "ok"


_AGENT: list[Any] = []


def _agent() -> Any:
    """The tiny task's agent (built once): the schema saved agents are checked against."""
    if not _AGENT:
        from cobelrun.hydra_app import composer
        from cobelrun.runner import build_task

        with composer() as compose:
            cfg = compose(list(TINY))
        _AGENT.append(build_task(cfg).make_agent(seed=0))
    return _AGENT[0]


def _files(folder: Path) -> list[str]:
    """Every file and folder of a run or sweep folder, relative (``.lock`` left out: it is the
    launcher's, never read)."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name != ".lock")


def _log() -> None:
    if os.environ.get("COBEL_FUZZ_LOG"):
        Path(os.environ["COBEL_FUZZ_LOG"]).write_text(json.dumps(dict(FIGURES), indent=1))


def fuzz_one(data: Any, real_run: Path, real_sweep: Path, base: Path) -> None:
    kind = data.draw(st.sampled_from(["run", "sweep"]), label="folder")
    src = real_run if kind == "run" else real_sweep
    box = base / f"ex{next(_N)}"
    (box / "outside").mkdir(parents=True)
    (box / "outside" / "secret.txt").write_text("not cobel's")
    folder = copy_folder(src, box / kind)
    canary = box / "CANARY"
    rel = data.draw(st.sampled_from(_files(folder)), label="file")
    what = mutate(data, folder / rel, box, canary)
    commands = RUN_COMMANDS if kind == "run" else SWEEP_COMMANDS
    if what.endswith("-target") and kind == "run":  # what would build it: a rerun, mostly
        commands = ("rerun-config", "rerun-config", "plot", "load")
    command = data.draw(st.sampled_from(commands), label="command")
    before = snapshot(box, folder)
    old_results = os.environ.get("COBEL_RESULTS")
    os.environ["COBEL_RESULTS"] = str(folder / "results")
    FIGURES["examples"] += 1
    import signal

    def hung(signum: int, frame: Any) -> None:
        raise TimeoutError(f"{command} hung on {what} of {rel}")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(120)  # a reader that blocks (a pipe opened) fails the example, not the suite
    try:
        outcome = run_reader(command, folder, box)
    except BaseException:
        FIGURES["tracebacks"] += 1
        _log()
        raise
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        if old_results is None:
            os.environ.pop("COBEL_RESULTS", None)
        else:
            os.environ["COBEL_RESULTS"] = old_results
    FIGURES["clean_errors" if outcome == "error" else "successes"] += 1
    FIGURES[f"mutation:{what}"] += 1
    FIGURES[f"command:{command}"] += 1
    if canary.exists() or Path("/tmp/pwned").exists():
        FIGURES["canaries"] += 1
        _log()
        raise AssertionError(f"canary written: {what} of {rel}, then {command}")
    after = snapshot(box, folder)
    if after != before:
        FIGURES["written_outside"] += 1
        _log()
        changed = sorted(set(after.items()) ^ set(before.items()))[:3]
        raise AssertionError(f"written outside the folder: {changed} ({what} of {rel}, {command})")
    _log()
    shutil.rmtree(box, ignore_errors=True)


@pytest.fixture(scope="module")
def fuzz_base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("folder-fuzz")


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                 HealthCheck.function_scoped_fixture])  # fmt: skip
@given(data=st.data())
def test_fuzzed_folder_files_fail_cleanly(data, real_run, real_sweep, fuzz_base):
    fuzz_one(data, real_run, real_sweep, fuzz_base)


@pytest.mark.slow
@settings(max_examples=SLOW_EXAMPLES, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                 HealthCheck.function_scoped_fixture])  # fmt: skip
@given(data=st.data())
def test_fuzzed_folder_files_fail_cleanly_1000(data, real_run, real_sweep, fuzz_base):
    fuzz_one(data, real_run, real_sweep, fuzz_base)


@pytest.mark.parametrize("which", range(3))
def test_canary_targets_do_write_when_built(tmp_path, which):
    """The injected targets are live: built without cobel's gate (Hydra's own instantiate),
    each writes its canary, so a canary-free fuzz run means the gate held."""
    from hydra.utils import instantiate

    canary = tmp_path / "CANARY"
    node = _targets(canary)[which]
    instantiate(node)
    assert canary.exists()
