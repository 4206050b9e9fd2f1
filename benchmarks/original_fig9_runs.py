"""Fig. 9's agents with the original CoBeL-RL v2.0.0 + keras-rl2, as per-agent data for cobel's tables.

The driver runs the paper's own Fig. 9 script setting (``simulations/choice/simulation_choice.py``
of sencheng/CoBeL-RL-Paper-Simulations: CoBeL-RL v2.0.0's ``DQNAgentBaseline`` on keras-rl2's
``DQNAgent``, memory 1e6, epsilon 0.3, ``nb_steps_warmup = 1``, 50 trials of at most 35 steps,
the script's ``InterfaceChoice`` and CoBeL-RL's ``RewardMonitor``), imported from source trees you
provide (nothing of them is vendored here), one agent at a time, and writes per agent the same
block means as ``docs/figures/data/fig9_seeds_runs.csv`` (training reward and greedy choice
correct over trials 1-5, 6-10, 11-20, 21-30, 31-40, 41-50), plus the per-trial means over the
agents (``<out stem>_trials.csv``), each with a provenance sidecar. ``python -m
cobelrun.figures.data --derive`` then compares cobel's agents with these, block by block
(``fig9_compare.csv``: Welch interval, Mann-Whitney U, probability of superiority with a
bootstrap interval).

Set-up (once; Python 3.11, a throwaway venv; only PyPI needed)::

    # CoBeL-RL v2.0.0 and the paper's simulation scripts (any checkout of these commits)
    git clone https://github.com/sencheng/CoBeL-RL /tmp/cobel-rl && git -C /tmp/cobel-rl checkout v2.0.0
    git clone https://github.com/sencheng/CoBeL-RL-Paper-Simulations /tmp/cobel-rl-sims
    python3.11 -m venv /tmp/v2venv9
    /tmp/v2venv9/bin/pip install tensorflow-cpu==2.15.1 "keras==2.15.*" keras-rl2==1.0.5 \\
        "numpy<2" gym==0.26.2 scipy "pyqtgraph<=0.12.0" PyQt5
    /tmp/v2venv9/bin/pip install --no-deps /tmp/cobel-rl     # CoBeL-RL v2.0.0 itself
    QT_QPA_PLATFORM=offscreen nice -n 10 /tmp/v2venv9/bin/python benchmarks/original_fig9_runs.py \\
        /tmp/cobel-rl-sims --agents 100 --out docs/figures/data/fig9_original_runs.csv

(``--no-deps``: v2.0.0's setup.py also pulls shapely, scikit-learn and OpenCV, which Fig. 9 never
imports.) Three run-time adaptations, made here in the driver and none touching the learning:

- keras-rl2 1.0.5 reads ``tensorflow.keras.__version__``, gone in TF 2.15: set from ``keras``;
- keras-rl2 needs the pre-2.11 Keras optimizer (it reads ``optimizer._name`` and calls
  ``get_updates``): CoBeL-RL's ``Adam(lr=.001)`` is built from
  ``tensorflow.keras.optimizers.legacy.Adam``, the optimizer TF <= 2.10 called ``Adam``;
- a greedy probe after each trial (the four displays through the Q network: no learning, no
  draws from NumPy's generator), the same measure as cobel's ``greedy_correct``.

The script seeds nothing (``np.random.seed()`` per agent); here agent ``a`` is seeded with
``tf.keras.utils.set_random_seed(a)`` (Python, NumPy and TensorFlow), so the table can be made
again. TensorFlow runs on one thread (``--threads``).
"""

from __future__ import annotations

import argparse
import csv
import importlib
import json
import os
import platform
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

TRIALS, MAX_STEPS, EPSILON, MEMORY = 50, 35, 0.3, 1_000_000
BLOCKS = ((1, 5), (6, 10), (11, 20), (21, 30), (31, 40), (41, 50))
#: the four displays (left stimulus, right stimulus) and the correct action (0 left, 1 right)
DISPLAYS = (((0, 1), 0), ((1, 0), 1), ((2, 3), 0), ((3, 2), 1))


def adapt_keras_rl() -> None:
    """The two library adaptations named in the module docstring (before ``rl`` is imported)."""
    import keras
    import tensorflow as tf

    # keras-rl2 1.0.5 reads tensorflow.keras.__version__, gone in TF 2.15: registered on the
    # module tf.keras loads (keras.api._v2.keras) under the name keras-rl2 imports
    tfk = importlib.import_module(tf.keras.__name__)
    tfk.__version__ = keras.__version__
    sys.modules["tensorflow.keras"] = tfk
    import cobel.agents.keras_rl.dqn as v2_dqn

    v2_dqn.Adam = tf.keras.optimizers.legacy.Adam  # keras-rl2 needs the pre-2.11 optimizer


def one_agent(agent: int, interface_choice: type) -> tuple[list[float], list[float]]:
    """One agent of the paper's ``single_run`` (seeded); its reward and greedy trace."""
    import numpy as np
    import tensorflow as tf
    from cobel.agents.keras_rl.dqn import DQNAgentBaseline
    from cobel.analysis.rl_monitoring.rl_performance_monitors import RewardMonitor
    from tensorflow.keras import backend as K

    tf.keras.utils.set_random_seed(agent)  # the script: np.random.seed() (unseeded)
    observations = np.eye(4)
    choices = [{"correct": 0, "incorrect": 1}, {"correct": 2, "incorrect": 3}]
    modules: dict = {}
    modules["rl_interface"] = interface_choice(modules, observations, choices, False)
    reward_monitor = RewardMonitor(TRIALS, None, False, [0, 1])
    probe_states = np.stack(
        [np.concatenate((observations[a], observations[b])) for (a, b), _ in DISPLAYS]
    )[:, None, :]  # (4 displays, window 1, 8 inputs)
    correct = np.array([c for _, c in DISPLAYS])
    greedy: list[float] = []

    def probe(logs: dict) -> None:
        q = rl_agent.agent.compute_batch_q_values(probe_states)
        greedy.append(float(np.mean(np.argmax(q, axis=1) == correct)))

    rl_agent = DQNAgentBaseline(modules["rl_interface"], MEMORY, EPSILON, None,
                                custom_callbacks={"on_trial_end": [reward_monitor.update, probe]})  # fmt: skip
    rl_agent.agent.nb_steps_warmup = 1
    modules["rl_interface"].rl_agent = rl_agent
    rl_agent.train(TRIALS, MAX_STEPS)
    K.clear_session()
    return [float(r) for r in reward_monitor.reward_trace], greedy


def git_label(path: Path) -> str:
    """``describe (commit)`` of a checkout, or '' when it is none."""
    run = [["git", "-C", str(path), "describe", "--tags", "--always"],
           ["git", "-C", str(path), "rev-parse", "HEAD"]]  # fmt: skip
    out = [
        subprocess.run(c, capture_output=True, text=True, check=False).stdout.strip() for c in run
    ]
    return f"{out[0]} ({out[1]})" if out[1] else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("simulations", type=Path,
                    help="a CoBeL-RL-Paper-Simulations tree (holds simulations/choice/)")  # fmt: skip
    ap.add_argument("--agents", type=int, default=100)
    ap.add_argument("--first", type=int, default=0, help="seed of the first agent")
    ap.add_argument("--threads", type=int, default=1, help="TensorFlow threads")
    ap.add_argument("--out", type=Path, required=True, help="per-agent CSV to write")
    ap.add_argument("--cobel-label", default="",
                    help="CoBeL-RL version when the installed copy is no checkout, e.g. 'v2.0.0 (78bf654)'")  # fmt: skip
    ap.add_argument("--sims-label", default="", help="the simulations tree's version, likewise")
    opts = ap.parse_args()
    choice_dir = opts.simulations / "simulations" / "choice"
    if not (choice_dir / "interface_choice.py").is_file():
        ap.error(f"{choice_dir} holds no interface_choice.py; give the paper-simulations tree")
    if opts.agents < 2:
        ap.error("--agents must be 2 or more (the comparison needs two per sample)")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    import numpy as np
    import tensorflow as tf

    tf.config.threading.set_intra_op_parallelism_threads(opts.threads)
    tf.config.threading.set_inter_op_parallelism_threads(opts.threads)
    from tensorflow.python.framework.ops import disable_eager_execution

    disable_eager_execution()  # as the script does
    adapt_keras_rl()
    sys.path.insert(0, str(choice_dir))
    from interface_choice import InterfaceChoice

    started = datetime.now(UTC).isoformat(timespec="seconds")
    t0, c0 = time.perf_counter(), time.process_time()
    rows, rewards, greedies = [], [], []
    for k in range(opts.agents):
        seed = opts.first + k
        reward, greedy = one_agent(seed, InterfaceChoice)
        rewards.append(reward)
        greedies.append(greedy)
        row: dict[str, float] = {"run": k, "seed": seed}
        for lo, hi in BLOCKS:
            row[f"reward_{lo}_{hi}"] = float(np.mean(reward[lo - 1 : hi]))
        for lo, hi in BLOCKS:
            row[f"greedy_{lo}_{hi}"] = float(np.mean(greedy[lo - 1 : hi]))
        rows.append(row)
        print(f"agent {k + 1}/{opts.agents}: reward 6-10 {row['reward_6_10']:.2f}, "
              f"41-50 {row['reward_41_50']:.2f} ({time.perf_counter() - t0:.0f} s)", flush=True)  # fmt: skip
        write(opts, rows, rewards, greedies, started, t0, c0)  # a stopped run keeps its agents
    print(opts.out)


def write(
    opts: argparse.Namespace,
    rows: list[dict],
    rewards: list,
    greedies: list,
    started: str,
    t0: float,
    c0: float,
) -> None:
    """The per-agent table, the per-trial means and their sidecars, for the agents so far."""
    import numpy as np
    import tensorflow as tf

    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    opts.out.parent.mkdir(parents=True, exist_ok=True)
    with opts.out.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    r, g = np.asarray(rewards), np.asarray(greedies)
    trials_csv = opts.out.with_name(f"{opts.out.stem}_trials.csv")
    with trials_csv.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["trial", "agents", "reward_mean", "reward_se", "greedy_mean"])
        for t in range(TRIALS):
            writer.writerow([t + 1, len(r), f"{r[:, t].mean():.6g}",
                             f"{r[:, t].std(ddof=min(1, len(r) - 1)) / np.sqrt(len(r)):.6g}", f"{g[:, t].mean():.6g}"])  # fmt: skip
    import cobel
    import keras
    import rl

    cobel_src = Path(cobel.__file__).resolve().parents[1]
    versions = {"tensorflow": tf.__version__, "keras": keras.__version__, "numpy": np.__version__,
                "keras-rl2": _dist_version("keras-rl2"), "gym": _dist_version("gym"),
                "rl": str(Path(rl.__file__).parent)}  # fmt: skip
    seeds = [int(r["seed"]) for r in rows]
    base = {
        "source": "run", "figure": "fig9 (the original)",
        "command": "QT_QPA_PLATFORM=offscreen nice -n 10 python benchmarks/original_fig9_runs.py "
                   f"CoBeL-RL-Paper-Simulations --agents {len(rows)} --first {opts.first} "
                   f"--threads {opts.threads} --out {opts.out.name}",
        "original": f"CoBeL-RL {opts.cobel_label or git_label(cobel_src) or cobel_src}, "
                    f"paper simulations {opts.sims_label or git_label(opts.simulations)} "
                    "(simulations/choice/: the setting of simulation_choice.py, its InterfaceChoice)",
        "versions": versions, "python": sys.version.split()[0],
        "cobel_commit": "n/a (the original's code)",
        "seeds": seeds, "seeding": "tf.keras.utils.set_random_seed(seed) per agent",
        "machine": f"{platform.node()} ({platform.platform()})", "cpus": os.cpu_count(),
        "agents_planned": opts.agents, "agents_done": len(rows),
        "tf_threads": opts.threads, "exported": started, "wall_time_s": round(wall, 1),
        "cpu_time_s": round(cpu, 1),
    }  # fmt: skip
    for path, extra in (
        (opts.out, {}),
        (trials_csv, {"derived": f"means over the agents of {opts.out.name}'s traces"}),
    ):
        side = path.with_name(f"{path.stem}.provenance.json")
        side.write_text(json.dumps({"table": path.stem, **base, **extra}, indent=1) + "\n")


def _dist_version(name: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


if __name__ == "__main__":
    main()
