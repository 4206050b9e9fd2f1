"""PMA replay speed: cobel's compiled replay bout vs CoBeL-RL v2.0.0's PMA agent (issue 14).

Run on demand (not a test)::

    python benchmarks/bench_pma.py [--v2-src DIR] [--v2-python PY] [--bouts N]

Setting (the same for both): Sutton's Dyna maze (``task=dyna_maze``), the model pre-explored
(every action of every free cell), a Q table and transition matrix from a PMA agent trained for
3 episodes (seed 0), and replay bouts of 20 backups from the start state with the successor
representation as need (computed once per bout), gain under softmax(beta = 5), alpha 1,
gamma 0.9, n-step extension on. Each bout starts from the same Q. Reported: backups per second
(best of 3 repeats of ``--bouts`` bouts; compile time excluded).

CoBeL-RL v2.0.0 runs in its own interpreter (``--v2-python``, a throwaway venv with numpy and
scipy, which is all its PMA agent imports) from its source (``--v2-src``: a folder holding
``cobel/agents/{rl_agent,dyna_q}.py`` and ``cobel/memory_modules/dyna_q_memory.py`` of the
v2.0.0 tag; nothing of it is vendored here). Two runtime shims, applied in the child only:

* ``PMAMemory.compute_gain`` returns a 1-element array that ``replay`` assigns to one element
  of the gain vector, which NumPy >= 2 rejects ("setting an array element with a sequence");
  the shim returns the element;
* its ``PMAAgent`` passes ``gamma_SR`` into the memory's learning-rate slot (see
  ``docs/replay.md``), so the SR discount is set on the memory directly (0.9, as ours).

Writes ``benchmarks/results/pma.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
N_BACKUPS = 20

V2_DRIVER = textwrap.dedent(
    """
    import json, sys, time, types
    import numpy as np
    src, data_path, bouts, repeats = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    sys.path.insert(0, src)
    # import the three modules PMA needs without the packages' __init__ (which pull in the
    # rest of the framework: gym, Qt, tensorflow, ...)
    import importlib.util
    for pkg in ("cobel", "cobel.agents", "cobel.memory_modules"):
        mod = types.ModuleType(pkg); mod.__path__ = [src + "/" + pkg.replace(".", "/")]
        sys.modules[pkg] = mod
    from cobel.agents.dyna_q import PMAAgent
    from cobel.memory_modules.dyna_q_memory import PMAMemory

    _orig_gain = PMAMemory.compute_gain
    def _gain_numpy2(self, updates):  # NumPy 2 shim: one update -> its scalar gain
        g = _orig_gain(self, updates)
        return g[0] if len(updates) == 1 else g
    PMAMemory.compute_gain = _gain_numpy2

    d = np.load(data_path)
    S, A = d["Q"].shape
    class Space: n = A
    class Interface:
        world = {"states": S, "sas": d["sas"]}
        action_space = Space()
    np.random.seed(0)
    agent = PMAAgent(Interface(), epsilon=0.0, beta=5.0, learning_rate=1.0, gamma=0.9,
                     gamma_SR=0.9)
    agent.policy = "softmax"
    M = agent.M
    M.gamma = 0.9  # the SR discount (v2 passes gamma_SR into the learning-rate slot)
    M.states[...] = d["next_state"]
    M.rewards[...] = d["reward"]
    M.terminals[...] = d["nonterminal"]  # v2 stores 1 - terminal
    M.T = d["T"].copy()
    M.update_SR()
    M.compute_update_mask()
    Q0 = d["Q"].copy()
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(bouts):
            agent.Q = Q0.copy()
            M.update_SR()
            M.replay(int(d["n_backups"]), int(d["start"]))
        best = min(best, time.perf_counter() - t0)
    print(json.dumps({"seconds": best, "backups": bouts * int(d["n_backups"]),
                      "numpy": np.__version__}))
    """
)


def setting() -> tuple[object, object]:
    """A PMA agent in the Dyna maze after 3 episodes, and its environment."""
    from cobelrun.agents import PMA
    from cobelrun.config import instantiate
    from cobelrun.runner import run_seed
    from tests.test_configs import _compose

    env = instantiate("env", _compose("task=dyna_maze").env)
    agent_seed, env_seed = run_seed(0, 0)
    env.unwrapped.np_random = np.random.default_rng(env_seed)
    agent = PMA(env, seed=agent_seed, policy="epsilon_greedy", epsilon=0.0)
    agent.train(3, 10_000)
    return agent, env


def bench_cobel(agent: object, bouts: int, repeats: int) -> dict:
    world = agent.env.unwrapped.world
    start = int(world.starts[0])
    Q0 = agent.Q.copy()
    from cobelrun.agents.replay_log import ReplayLog

    agent._log = ReplayLog()
    agent._bout(start, start, 0, 0)  # compile / load the cache
    best = np.inf
    for _ in range(repeats):
        agent._log = ReplayLog()
        t0 = time.perf_counter()
        for _ in range(bouts):
            agent.Q[...] = Q0
            agent._bout(start, start, 0, 0)
        best = min(best, time.perf_counter() - t0)
    done = int(agent._log.collect()["state"].size)
    agent.Q[...] = Q0
    return {"seconds": best, "backups": done}


def bench_v2(agent: object, src: Path, python: str, bouts: int, repeats: int) -> dict:
    world = agent.env.unwrapped.world
    nonterminal = (~world.terminal[np.maximum(agent.model_next, 0)]).astype(int)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "setting.npz"
        np.savez(
            data, Q=agent.Q, sas=world.T, next_state=np.maximum(agent.model_next, 0),
            reward=agent.model_reward, nonterminal=nonterminal, T=agent.T,
            start=int(world.starts[0]), n_backups=N_BACKUPS,
        )  # fmt: skip
        driver = Path(tmp) / "v2_driver.py"
        driver.write_text(V2_DRIVER)
        proc = subprocess.run(
            [python, str(driver), str(src), str(data), str(bouts), str(repeats)],
            capture_output=True, text=True, timeout=3600,
        )  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"CoBeL-RL v2 benchmark failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--v2-src", type=Path, default=Path("/tmp/cobel_v2_src"))
    p.add_argument("--v2-python", default="/tmp/cobel_v2_venv/bin/python")
    p.add_argument("--bouts", type=int, default=20, help="bouts per repeat (v2)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--out", type=Path, default=HERE / "results" / "pma.json")
    args = p.parse_args()
    sys.path.insert(0, str(HERE.parent))
    agent, _env = setting()
    ours = bench_cobel(agent, args.bouts * 50, args.repeat)
    result = {
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "numpy": np.__version__,
        },
        "setting": "dyna_maze, 20 backups per bout from the start, SR need, softmax(5) gain",
        "cobel": ours,
    }
    rate = ours["backups"] / ours["seconds"]
    print(f"cobel   : {rate:12,.0f} backups/s ({ours['backups']} backups)")
    if args.v2_src.exists():
        v2 = bench_v2(agent, args.v2_src, args.v2_python, args.bouts, args.repeat)
        v2_rate = v2["backups"] / v2["seconds"]
        result["cobel_v2"] = v2
        result["ratio"] = rate / v2_rate
        print(
            f"CoBeL v2: {v2_rate:12,.0f} backups/s ({v2['backups']} backups, numpy {v2['numpy']})"
        )
        print(f"ratio   : {rate / v2_rate:12,.0f}x")
    else:
        print(f"CoBeL-RL v2 source not found at {args.v2_src}; see the module docstring")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
