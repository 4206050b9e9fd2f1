"""Grid envs offer ``render_mode="rgb_array"``: a top-down image with the agent on its cell."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from cobelrun.envs import GridWorldEnv
from cobelrun.envs.world import from_layout


def _agent_cell(img: np.ndarray, px: int) -> tuple[int, int]:
    blue = np.all(img == (30, 90, 200), axis=-1)
    rows, cols = np.nonzero(blue)
    return int(rows.mean() // px), int(cols.mean() // px)


def test_rgb_array_shows_the_agent_where_it_is() -> None:
    env = GridWorldEnv(from_layout("S.G\n#.."), render_mode="rgb_array")
    px = env.RENDER_CELL_PX
    env.reset(seed=0)
    img = env.render()
    assert (
        isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.shape == (2 * px, 3 * px, 3)
    )
    assert _agent_cell(img, px) == (0, 0)
    assert tuple(img[px + px // 2, px // 2]) == (40, 40, 40)  # the wall '#'
    assert tuple(img[px // 2, 2 * px + 2]) == (250, 200, 60)  # the rewarded goal
    env.step(2)  # right
    assert _agent_cell(env.render(), px) == (0, 1)


def test_rgb_array_is_offered_to_gymnasium() -> None:
    assert "rgb_array" in GridWorldEnv.metadata["render_modes"]
    env = gym.make("cobelrun.envs:cobel/GridWorld-v0", render_mode="rgb_array")
    env.reset(seed=1)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3
