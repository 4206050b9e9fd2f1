"""Fuzz config overrides with hypothesis: every key of every group gets wrong types, null,
negative, huge, unicode and path values; the result is a clean one-line error or a valid
config, never a traceback, and nothing is written.

In-process against the code ``cobel run`` validates with before any folder exists (configs
composed once per base, a value set on a copy, then :func:`cobelrun.runner.build_task` with
the agent probed): a few milliseconds per example, so the slow run affords 2,000 of them.
The default suite runs ``COBEL_FUZZ_EXAMPLES`` (default 60); a handful go through the real
CLI. Errors must be :class:`~cobelrun.errors.CobelError` raised by a check, not the CLI's
catch-all, so every finding here is a missing check. A size that would not fit in memory must be
refused by an estimate before it is allocated (``... would allocate about ...``): a MemoryError
is not caught anywhere on the way and fails the test.

``COBEL_FUZZ_LOG=FILE`` writes the counts (tried, clean errors, of which memory refusals,
accepted) there after every example.
"""

from __future__ import annotations

import copy
import json
import math
import os
from functools import cache
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import DictConfig, ListConfig, OmegaConf

from cobelrun.errors import CobelError
from cobelrun.hydra_app import composer
from cobelrun.runner import build_task

#: composed configs the fuzz starts from: every cheap task, each tabular-capable agent and
#: env (3D renders and deep-agent training are left to their own tests: they take seconds)
BASES = (
    ("task=tmaze_extinction",),
    ("task=gridworld",),
    ("task=two_afc",),
    ("task=latent_learning",),
    ("task=tmaze_extinction", "agent=dyna_dqn"),
    ("task=tmaze_extinction", "agent=dyna_dsr"),
    ("task=gridworld", "env=blodgett"),
    ("task=gridworld", "env=open_field"),
    ("task=gridworld", "env=gridworld_layout"),
    ("task=gridworld", "env=tmaze"),
    ("task=render_benchmark",),
    ("task=dyna_maze",),
    ("task=morris_water_maze",),
    ("task=reward_revaluation",),
    ("task=transition_revaluation",),
    ("task=policy_revaluation",),
)
#: small budgets, so that a value that is accepted builds quickly
SMALL = ("task.runs=1", "task.save_agents=false")

FIGURES = {"tried": 0, "clean_errors": 0, "memory_refusals": 0, "accepted": 0, "unreachable": 0}


def leaves(node: Any, prefix: str = "") -> list[str]:
    """Dotted keys of every leaf (and every inner node: replacing a whole node is fuzzed too)."""
    out = []
    items = node.items() if isinstance(node, DictConfig) else enumerate(node)
    for k, v in items:
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, DictConfig | ListConfig):
            out.append(key)
            out.extend(leaves(v, key))
        else:
            out.append(key)
    return out


@cache
def bases() -> list[tuple[DictConfig, list[str]]]:
    found = []
    with composer() as compose:
        for base in BASES:
            overrides = [*base, *SMALL] if base != ("task=render_benchmark",) else list(base)
            cfg = compose(overrides)
            build_task(cfg, probe_agent=True)  # the base itself is valid
            keys = [k for k in leaves(cfg) if not k.startswith("hydra")]
            found.append((cfg, keys))
    return found


def all_keys() -> set[str]:
    return {k for _, keys in bases() for k in keys}


BAD_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.sampled_from([-1, 0, 2**31, 2**63, 10**12, -(2**63)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, -1e308, 1e308, -0.5, 1e-320]),
    st.text(max_size=12),
    st.sampled_from(
        [
            "",
            " ",
            "../../x",
            "/etc/passwd",
            "~",
            "a/b",
            "ünïcødé",
            "\x00",
            "${oops}",
            "${oc.env:HOME}",
            "nan",
            "true",
            "-1",
            "1e999",
            "💥" * 3,
        ]
    ),
    st.lists(st.integers(min_value=-5, max_value=10**9), max_size=4),
    st.lists(st.text(max_size=4), max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
    st.just({"_target_": "os.system"}),
    st.just({"_target_": "builtins.nonexistent"}),
)


def attempt(cfg: DictConfig, key: str, value: Any) -> str:
    """Set ``key`` to ``value`` on a copy of ``cfg`` and build it; ``accepted`` or ``error``.

    Anything but a CobelError propagates (the test fails with it)."""
    cfg = copy.deepcopy(cfg)
    try:
        OmegaConf.update(cfg, key, value, merge=False, force_add=True)
    except Exception:  # OmegaConf itself refuses (e.g. a string key on a list): not reachable
        return "unreachable"
    try:
        build_task(cfg, probe_agent=True)
    except CobelError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg.strip(), f"{key}={value!r}: multi-line error {msg!r}"
        assert "MemoryError" not in msg and "Unable to allocate" not in msg, (
            f"{key}={value!r}: an allocation failed instead of an estimate refusing it: {msg}"
        )
        return "memory" if " would allocate about " in msg else "error"
    return "accepted"


EXAMPLES = int(os.environ.get("COBEL_FUZZ_EXAMPLES", "60"))


def fuzz(data: st.DataObject, tmp_path: Path) -> None:
    cfg, keys = data.draw(st.sampled_from(bases()), label="base")
    key = data.draw(st.sampled_from(keys), label="key")
    value = data.draw(BAD_VALUES, label="value")
    before = sorted(tmp_path.iterdir())
    outcome = attempt(cfg, key, value)
    assert sorted(tmp_path.iterdir()) == before  # nothing written
    FIGURES["tried"] += 1
    if outcome in ("error", "memory"):
        FIGURES["clean_errors"] += 1
        FIGURES["memory_refusals"] += outcome == "memory"
    else:
        FIGURES[outcome] += 1
    if os.environ.get("COBEL_FUZZ_LOG"):
        Path(os.environ["COBEL_FUZZ_LOG"]).write_text(json.dumps(FIGURES))


@pytest.fixture
def quiet_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("COBEL_RESULTS", str(tmp_path / "results"))
    return tmp_path


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                 HealthCheck.data_too_large])  # fmt: skip
@given(data=st.data())
def test_fuzzed_overrides_fail_cleanly(quiet_cwd, data):
    fuzz(data, quiet_cwd)


@pytest.fixture
def memory_cap():
    """A 10 GB address-space cap while the slow fuzz runs, a safety net for the shared machine
    only: should a size still escape the estimates, its allocation raises MemoryError, which
    fails the test (with the key and value), instead of waking the kernel's OOM killer."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = 10 * 10**9 if hard == resource.RLIM_INFINITY else min(hard, 10 * 10**9)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


@pytest.mark.slow
@settings(max_examples=2000, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                 HealthCheck.data_too_large])  # fmt: skip
@given(data=st.data())
def test_fuzzed_overrides_fail_cleanly_2000(quiet_cwd, memory_cap, data):
    fuzz(data, quiet_cwd)


def test_zz_fuzz_figures():
    """Prints the counts for the closing note (run with -s); every key was reachable."""
    print(f"fuzz: {FIGURES}; keys: {len(all_keys())} in {len(BASES)} configs")
    assert len(all_keys()) > 100


@pytest.mark.parametrize(
    "override",
    [pytest.param("agent.epsilon=null"), pytest.param("seed=-1"), *(pytest.param(o, marks=pytest.mark.slow) for o in [ "task.protocol.phases.0.trials=1e999", "agent.replay_batch=-3",
     "task.record.runs='../../x'", "agent.gamma=[1,2]", "task.record.trial_every=0",
     "task.protocol.max_steps=9999999999999"])],
)  # fmt: skip
def test_cli_examples(cobel, tmp_path, override):
    proc = cobel("run", "task=tmaze_extinction", "task.runs=1", override)
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("cobel: error:"), proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "results").exists()
