"""Batched CNN DQN runs (``task.batch_runs`` with ``CnnPolicy``: Fig. 6A's and Fig. 8's agents).

A batched CNN run draws what its sequential twin draws (exploration and replay sampling from
its numpy stream, initial weights and dropout masks from its torch stream) and applies SB3's
update rule; only floating-point sums are ordered differently. Checked here at the level of
the network (initial weights bit for bit, dropout masks bit for bit, gradient steps within
float32 rounding) and of whole runs of Fig. 8's task (same tables, most runs identical).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
from gymnasium import spaces

pytest.importorskip("stable_baselines3")

from cobelrun.api import compose
from cobelrun.runner import build_task, execute, run_seed


class PanoramaEnv(gym.Env):
    """Fig. 8's observation and action spaces (12 x 48 x 3 uint8 panoramas, 12 actions); the
    network tests fill replay memories directly, so it is never stepped."""

    observation_space = spaces.Box(0, 255, (12, 48, 3), np.uint8)
    action_space = spaces.Discrete(12)


#: agent=dqn_fig8's network and training settings (dropout 0.35, Keras init, Q from -5)
FIG8_AGENT = dict(policy="CnnPolicy", net_arch=[], activation="relu",
                  convs=[[32, 5, 1], [64, 4, 2], [64, 3, 2]], features_dim=50, dropout=0.35,
                  init="keras", q_init=-5.0, loss="mse", max_grad_norm=None, learning_rate=1e-3,
                  gamma=0.8, batch_size=8, buffer_size=100, learning_starts=0)  # fmt: skip


def _agents_and_learner(runs: int, **extra):
    from cobelrun.agents.dqn import DQNAgent

    seeds = [run_seed(0, r)[0] for r in range(runs)]
    agents = [DQNAgent(PanoramaEnv(), seed=s, **{**FIG8_AGENT, **extra}) for s in seeds]
    return agents, agents[0].batch_learner(seeds, 100)


def _fill(agents, learner, n: int, seed: int) -> np.ndarray:
    """The same random transitions into each sequential agent's buffer and its batched run;
    returns probe images (N, 12, 48, 3)."""
    rng = np.random.default_rng(seed)
    for r, agent in enumerate(agents):
        buf = agent.model.replay_buffer
        for _ in range(n):
            o, o2 = rng.integers(0, 256, (2, 3, 12, 48), dtype=np.uint8)
            a, rew, done = rng.integers(12), float(rng.random() < 0.2), bool(rng.random() < 0.1)
            buf.add(o[None], o2[None], np.array([[a]]), np.array([rew]), np.array([done]), [{}])
            learner._store(np.array([r]), o[None], o2[None], np.array([a]), np.array([rew]),
                           np.array([done]))  # fmt: skip
    return rng.integers(0, 256, (5, 12, 48, 3), dtype=np.uint8)


def test_cnn_initial_networks_and_dropout_streams_equal_the_sequential_agents():
    """Run r's initial online and target networks are the sequential agent's bit for bit, and
    its dropout generator holds the state the sequential agent's torch stream holds."""
    import torch

    agents, learner = _agents_and_learner(3)
    assert type(learner).__name__ == "BatchedCNNDQN" and learner.dropout == 0.35
    for r, agent in enumerate(agents):
        got, want = learner.view(r).get_state(), agent.get_state()
        assert set(got) == set(want)
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)
        assert torch.equal(learner.torch_gens[r].get_state(), agent._torch_state)
    images = np.random.default_rng(1).integers(0, 256, (4, 12, 48, 3), dtype=np.uint8)
    for r, agent in enumerate(agents):
        np.testing.assert_array_equal(learner.view(r).predict(images), agent.predict(images))
        want = agent.activations(images, ["analysis", "q"])
        got = learner.view(r).activations(images, ["analysis", "q"])
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_cnn_dropout_masks_are_bit_for_bit_f_dropout():
    """The masks a run draws from its generator are those ``F.dropout`` draws from torch's
    global stream in the same state (the sequential agent's), step after step."""
    import torch
    import torch.nn.functional as F

    agents, learner = _agents_and_learner(2)
    h = torch.rand(8, 50) + 0.5
    for step in range(3):
        noise = learner._dropout_noise(np.array([1]), (8, 50))  # run 0 does not learn: no draw
        with agents[1]._rng_scope():
            want = F.dropout(h, 0.35, training=True)
        assert torch.equal(h * noise[0], want), step
        assert torch.equal(learner.torch_gens[1].get_state(), agents[1]._torch_state)
    assert torch.equal(learner.torch_gens[0].get_state(), agents[0]._torch_state)


@pytest.mark.parametrize("conv", ["loop", "grouped"])
def test_cnn_gradient_steps_equal_the_sequential_agents(conv):
    """Three gradient steps on the same replay contents (same sampled indices, same dropout
    masks) give the same parameters and Adam state within float32 rounding, with a run that
    waits in the second step, clipping on; both ways of batching the convolutions, and with a
    convolution per run (the CPU's way) bit for bit."""
    from stable_baselines3.common.logger import configure

    agents, learner = _agents_and_learner(3, max_grad_norm=1.0)
    learner.conv = conv
    images = _fill(agents, learner, 30, seed=2)
    steps = {0: 3, 1: 2, 2: 3}
    for r, agent in enumerate(agents):
        agent.model.set_logger(configure(None, []))
        with agent._rng_scope():
            agent.model.train(gradient_steps=steps[r], batch_size=agent.model.batch_size)
    learner._gradient_step(np.ones(3, bool))
    learner._gradient_step(np.array([True, False, True]))
    learner._gradient_step(np.ones(3, bool))
    for r, agent in enumerate(agents):
        np.testing.assert_allclose(learner.view(r).predict(images), agent.predict(images),
                                   rtol=1e-5, atol=1e-5)  # fmt: skip
        got, want = learner.view(r).get_state(), agent.get_state()
        for key in want:
            np.testing.assert_allclose(got[key], want[key], rtol=1e-4, atol=1e-5, err_msg=key)
            if conv == "loop":  # the sequential network's own operations and Adam
                np.testing.assert_array_equal(got[key], want[key], err_msg=key)
        assert learner.adam_steps[r] == steps[r]


#: Fig. 8's task (place_cells_original: Adam 1e-3, Q from 0) at tiny settings
FIG8_TINY = [
    "task=place_cells_original", "task.protocol.phases=[{name: training, trials: 3}]",
    "task.protocol.max_steps=12", "agent.learning_starts=8", "agent.batch_size=8",
    "task.monitors.maps.grid=[3,3]", "task.monitors.maps.headings=2",
    "task.monitors.maps.every=2", "task.save_agents=all", "task.record.steps=true",
]  # fmt: skip


def _run(tmp_path, name: str, overrides: list[str]):
    task = build_task(compose(None, overrides))
    folder = tmp_path / name
    folder.mkdir()
    execute(task, folder, background_writes=False)
    return task, folder


@pytest.mark.slow
def test_fig8_batched_runs_match_sequential_runs(tmp_path):
    """Fig. 8's task, 3 runs: ``auto`` keeps it sequential on the CPU; batched (``true``), the
    trials, steps and activity-map tables equal the sequential runs' bit for bit (per-run
    convolutions, the sequential network's operations, dropout masks and Adam)."""
    auto = build_task(compose(None, [*FIG8_TINY, "task.runs=3"]))  # auto: Fig. 8 is sequential
    assert auto.batch == 0 and "3.3 M multiply-adds per image on the CPU" in auto.batch_note
    seq_task, seq = _run(tmp_path, "seq", [*FIG8_TINY, "task.runs=3", "task.batch_runs=false"])
    bat_task, bat = _run(tmp_path, "bat", [*FIG8_TINY, "task.runs=3", "task.batch_runs=true"])
    assert seq_task.batch == 0 and bat_task.batch == 3 and bat_task.batch_note is None
    same = 0
    for name in ("trials", "steps", "activity_maps"):
        a = pd.read_parquet(seq / f"{name}.parquet")
        b = pd.read_parquet(bat / f"{name}.parquet")
        assert list(a.columns) == list(b.columns) and a.dtypes.equals(b.dtypes), name
        assert len(a) == len(b) > 0, name
        if name == "trials":
            same = sum(a[a.run == r].reset_index(drop=True).equals(b[b.run == r].reset_index(drop=True))
                       for r in range(3))  # fmt: skip
    assert same == 3  # on the CPU a batched run does the sequential run's arithmetic
    for name in ("trials", "steps", "activity_maps"):  # so the tables are bit for bit equal
        pd.testing.assert_frame_equal(pd.read_parquet(seq / f"{name}.parquet"),
                                      pd.read_parquet(bat / f"{name}.parquet"), obj=name)  # fmt: skip


def test_auto_batches_small_cnns_only_on_the_cpu():
    """``task.batch_runs=auto`` batches a small CNN on the CPU and keeps Fig. 8's (3.3 M
    multiply-adds per image) sequential, saying why (the task-level check is in
    :func:`test_fig8_batched_runs_match_sequential_runs`)."""
    from cobelrun.agents.batched_cnn import CPU_MACS_LIMIT, auto_declines, macs_per_image
    from cobelrun.agents.dqn import DQNAgent

    fig8 = DQNAgent(PanoramaEnv(), seed=0, **FIG8_AGENT)
    macs = macs_per_image(fig8.model.q_net, fig8.model.observation_space.shape)
    # conv 32@5x5 on 12x48 -> 8x44, 64@4x4/2 -> 3x21, 64@3x3/2 -> 1x10, dense 640->50, 50->12
    assert macs == 8 * 44 * 32 * 75 + 3 * 21 * 64 * 512 + 10 * 64 * 576 + 640 * 50 + 50 * 12
    assert macs > CPU_MACS_LIMIT
    why = auto_declines(fig8)
    assert why is not None and "3.3 M multiply-adds per image" in why
    small = DQNAgent(PanoramaEnv(), seed=0, **{**FIG8_AGENT, "convs": [[4, 5, 5]]})
    assert auto_declines(small) is None


@pytest.mark.slow
def test_batched_cnn_runs_resume_at_their_chunk(tmp_path, monkeypatch):
    """Batched Fig. 8 runs (task.batch_runs=2 of 4 runs): a chunk is checkpointed at its
    start and between pieces; a stop inside the second chunk resumes from the checkpoint
    written inside it, with the tables (activity maps included) of the uninterrupted run."""
    from cobelrun import api, runner
    from cobelrun.batched import BatchedRuns
    from tests.test_resume import FAST, assert_same_tables, stopped_and_resumed

    overrides = [o for o in FIG8_TINY if not o.startswith(("task=", "task.protocol.phases"))]
    overrides += ["task.runs=4", "task.batch_runs=2", "task.save_agents=none",
                  "task.protocol.phases=[{name: training, trials: 10}]"]  # fmt: skip
    ref = runner.run(api.compose("place_cells_original", [*overrides, *FAST]), tmp_path / "ref")
    folder = stopped_and_resumed(tmp_path, monkeypatch, "place_cells_original", overrides,
                                 piece=4, cls=BatchedRuns)  # fmt: skip
    assert_same_tables(ref, folder)


#: Fig. 6A's task (36 x 36 camera images, conv 16@8x8/4 -> 32@4x4/2 -> dense 256) shortened
FIG6A_TINY = [
    "task=tmaze_extinction_3d", "task.runs=3", "task.protocol.phases.0.trials=3",
    "task.protocol.phases.1.trials=2", "task.protocol.max_steps=15", "agent.learning_starts=10",
    "agent.batch_size=8", "task.save_agents=all",
]  # fmt: skip


@pytest.mark.slow
def test_fig6a_is_batched_by_auto_and_matches_sequential_runs(tmp_path):
    """Fig. 6A's default task (its CNN is small enough to batch on the CPU): ``auto`` batches
    it; the same tables (trials, steps, MCAP log) as sequential runs, every run identical."""
    bat_task, bat = _run(tmp_path, "bat", FIG6A_TINY)
    seq_task, seq = _run(tmp_path, "seq", [*FIG6A_TINY, "task.batch_runs=false"])
    assert bat_task.batch == 3 and seq_task.batch == 0
    for name in ("trials", "steps"):
        a, b = pd.read_parquet(seq / f"{name}.parquet"), pd.read_parquet(bat / f"{name}.parquet")
        assert list(a.columns) == list(b.columns) and a.dtypes.equals(b.dtypes), name
        assert len(a) == len(b) > 0, name
    a, b = pd.read_parquet(seq / "trials.parquet"), pd.read_parquet(bat / "trials.parquet")
    pd.testing.assert_frame_equal(a, b)  # every run identical trial for trial
    assert sorted(p.name for p in seq.iterdir()) == sorted(p.name for p in bat.iterdir())
