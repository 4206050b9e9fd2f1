"""Greedy probe monitor: scores the greedy choice on fixed probes without changing training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cobelrun.config import builtin_conf_dir, register_resolvers
from cobelrun.envs.choice import TwoAFCEnv
from cobelrun.errors import ConfigError
from cobelrun.monitors.probe import GreedyProbeMonitor
from cobelrun.runner import run


def compose(overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    register_resolvers()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(builtin_conf_dir()), version_base="1.3"):
            cfg = hydra_compose("config", overrides=overrides)
    finally:
        GlobalHydra.instance().clear()
    OmegaConf.resolve(cfg)
    return cfg


class FixedAgent:
    def __init__(self, q: np.ndarray) -> None:
        self.q = q

    def predict(self, observations: np.ndarray) -> np.ndarray:
        return self.q[: len(observations)]


def test_probe_scores_greedy_choices_against_the_correct_actions() -> None:
    env = TwoAFCEnv()
    np.testing.assert_array_equal(env.correct_actions, [0, 1, 0, 1])
    probe = GreedyProbeMonitor()
    probe.setup(env)
    q = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])  # right on displays 0 and 3
    assert probe.score(FixedAgent(q)) == 0.5
    with pytest.raises(ConfigError, match="4 probes but 3 correct actions"):
        GreedyProbeMonitor(correct=[0, 1, 0]).setup(env)


def test_probe_does_not_change_training_for_the_same_seed(tmp_path: Path) -> None:
    base = ["task=two_afc", "task.runs=3", "seed=11", "task.save_agents=false"]
    with_probe = run(compose(base), tmp_path / "probe")
    without = run(compose([*base, "task.monitors.probe=null"]), tmp_path / "none")
    a = pd.read_parquet(with_probe / "trials.parquet")
    b = pd.read_parquet(without / "trials.parquet")
    assert "greedy_correct" in a and "greedy_correct" not in b
    pd.testing.assert_frame_equal(a.drop(columns="greedy_correct"), b)
    assert len(a) == 150 and a["greedy_correct"].between(0, 1).all()
    # the four displays: fractions are multiples of 1/4
    assert np.allclose(a["greedy_correct"] * 4, np.round(a["greedy_correct"] * 4))
