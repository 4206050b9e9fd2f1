"""cobel's tabular agents against neuro-nav's (awjuliani/neuro-nav) on the same task.

Run on demand (not a test)::

    python benchmarks/bench_neuronav.py --neuronav-python /tmp/nnvenv/bin/python [--repeats 3]

neuro-nav is never installed into cobel's environment: set it up in a throwaway venv from its
public repository, e.g.::

    git clone https://github.com/awjuliani/neuro-nav /tmp/neuronav
    python -m venv /tmp/nnvenv && /tmp/nnvenv/bin/pip install /tmp/neuronav

(its grid env imports torch, cv2, matplotlib and gym). This script writes neuro-nav's run
script itself (:data:`NEURONAV_SCRIPT`) into a temporary folder.

The setting (issue 38): an open 9 x 9 field (neuro-nav's ``GridTemplate.empty`` at
``GridSize.small``: 11 x 11 with the border walls; cobel's ``open_field(9, 9)``), start in one
corner, goal (reward 1, terminal) in the opposite one, 16 steps apart; 5 seeds x 200 episodes
of at most 100 steps (neuro-nav's default episode length); softmax policy, beta 50, learning
rate 0.3 (cobel's SR agents: also their reward rate), gamma 0.95; Dyna agents replay 3
experiences per step, uniformly from the experienced pairs (neuro-nav's ``DynaModule`` with
``recency="uniform"``; cobel's SR-Dyna with ``replay_reward=true``, as neuro-nav's ``DynaSR``
also updates the reward weights in replay).

Per agent and repetition (the agents interleaved, then the repetitions, so machine load hits
both alike) it measures

* the run loop: neuro-nav's episode loop (``time.perf_counter`` around it); cobel's phase
  loop, ``cobel run``'s manifest ``phase_wall_time_s`` (everything a run does per phase:
  the simulation, monitors and recording; numba's once-per-process start too, unless the
  runner calls the agent's ``prepare()`` before the phase: docs/speed.md);
* the whole process: wall time of the subprocess, from start to exit, and its CPU time (user +
  system, from ``os.wait4``; steadier than wall time on a shared machine).

and reports medians, steps per second and the cobel / neuro-nav ratios, as a Markdown table
(and ``--json`` for the raw numbers), after one untimed tiny run of each (numba's cache of
the kernels, the files in the page cache). The mean episode length of the last 20 episodes shows
both learned the shortest path. ``--baseline CHECKOUT`` also runs ``cobel run`` from another
checkout of cobel (``PYTHONPATH``), interleaved, as the row's "baseline" process columns.

``--breakdown`` instead splits one ``cobel run`` of each agent into where its CPU time goes
(:data:`BREAKDOWN_SCRIPT`: in one process, the packages a run imports, in the order given, then
the run itself with Hydra's composition, the instantiation gate, building the task, Hydra's
job, cobel's run (manifest, the kernel's load, the loop, the writes) and the end-of-run summary
timed by ``time.process_time``), medians of ``--repeats`` processes, next to the whole
process's CPU time of a plain ``cobel run``.

cobel's bytecode is compiled first (``compileall`` of the checkout's ``cobelrun``), as an
installed package has it: with ``PYTHONDONTWRITEBYTECODE=1`` (set in some development
shells) a checkout is otherwise compiled from source in every process (~80 modules, ~0.3-0.5 s
of CPU), which no installed cobel pays and neuro-nav's venv does not pay either.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

NEURONAV_SCRIPT = r"""
import json, sys, time
import numpy as np
from neuronav.envs.grid_env import GridEnv, GridObservation, GridSize
from neuronav.envs.grid_templates import GridTemplate
from neuronav.agents import td_agents, dyna_agents, mc_agents

name, seeds, episodes, max_steps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
lr, gamma, beta, replays = 0.3, 0.95, 50.0, 3
CLASSES = {
    "q_learning": td_agents.TDQ, "dyna_q": dyna_agents.DynaQ, "sr_td": td_agents.TDSR,
    "sr_dyna": dyna_agents.DynaSR, "sarsa": td_agents.SARSA, "q_lambda": td_agents.QET,
    "mc_control": mc_agents.QMC, "tabular_actor_critic": td_agents.TDAC,
    "dyna_actor_critic": dyna_agents.DynaAC,
}
cls = CLASSES[name]
steps = 0
last = []
t0 = time.perf_counter()
for seed in range(seeds):
    np.random.seed(seed)
    env = GridEnv(template=GridTemplate.empty, size=GridSize.small,
                  obs_type=GridObservation.index, seed=seed)
    agent = cls(env.state_size, env.action_space.n, lr=lr, gamma=gamma, poltype="softmax",
                beta=beta)
    if hasattr(agent, "dyna"):
        agent.dyna = dyna_agents.DynaModule(env.state_size, num_recall=replays,
                                            recency="uniform")
    lengths = []
    for ep in range(episodes):
        obs = env.reset(agent_pos=[1, 1], objects={"rewards": {(9, 9): 1.0}},
                        episode_length=max_steps)
        agent.reset()
        if name == "mc_control":
            agent.exp_list = []
        if name == "sarsa":
            agent.last_exp = None
        n = 0
        done = False
        while not done and n < max_steps:
            act = agent.sample_action(obs)
            obs2, reward, done, _ = env.step(act)
            agent.update([obs, act, obs2, reward, done])
            obs = obs2
            n += 1
        steps += n
        lengths.append(n)
    last.append(float(np.mean(lengths[-20:])))
loop = time.perf_counter() - t0
print(json.dumps({"steps": steps, "loop_s": loop, "last20": float(np.mean(last))}))
"""

#: cobel in-process, kernels loaded: the same runs (agents from the same configs and overrides)
#: timed after one warm-up trial per agent; what the simulation itself costs
COBEL_WARM_SCRIPT = r"""
import json, sys, time
import numpy as np
import yaml
from omegaconf import OmegaConf
from cobelrun.config import instantiate
from cobelrun.envs import GridWorldEnv, open_field

conf, overrides = sys.argv[1], json.loads(sys.argv[2])
seeds, episodes, max_steps = int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
node = OmegaConf.load(conf)
for item in overrides:  # agent.KEY=VALUE, the value parsed as YAML (as Hydra does)
    key, value = item.split("=", 1)
    OmegaConf.update(node, key.removeprefix("agent."), yaml.safe_load(value))
node = OmegaConf.to_container(node)
agents = []
for seed in range(seeds):
    env = GridWorldEnv(open_field(9, 9, starts=[0], goal=80))
    env.unwrapped.np_random = np.random.default_rng(seed)
    agents.append(instantiate("agent", node, env=env, seed=seed))
warm = instantiate("agent", node, env=GridWorldEnv(open_field(9, 9, starts=[0], goal=80)), seed=99)
warm.train(1, max_steps)
steps = 0
t0 = time.perf_counter()
for agent in agents:
    steps += int(agent.train(episodes, max_steps).steps.sum())
print(json.dumps({"steps": steps, "loop_s": time.perf_counter() - t0}))
"""

#: one ``cobel run`` in this process, its CPU time split into stages (``--breakdown``): the
#: packages a run imports (in this order, each charged with what it imports first), then the
#: run itself, with a few functions of Hydra and cobel timed (``time.process_time``, this
#: process only: the ``git`` and ``uname`` children of the manifest are not in it)
BREAKDOWN_SCRIPT = r"""
import functools, importlib, json, os, sys, time
sys.path[0] = os.path.dirname(sys.executable)  # as the console script's process has it
T0 = time.process_time()
os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")
import cobelrun.signals
from cobelrun import startup
cobelrun.signals.HOLD_AFTER_STOP = True
startup.pause_gc()  # as cobel run does
kernel_module, args = sys.argv[1], json.loads(sys.argv[2])
last = time.process_time()
out = {"the interpreter's start": T0, "cobel's entry point (standard library)": last - T0}
for label, mods in [
    ("numpy", ["numpy"]), ("OmegaConf", ["omegaconf"]),
    ("Hydra", ["hydra", "hydra.core.utils"]), ("cobel's CLI and composer", ["cobelrun.hydra_app"]),
    ("pydantic", ["pydantic"]), ("cobel's config schema (pydantic models)", ["cobelrun.schema"]),
    ("gymnasium", ["gymnasium"]), ("pyarrow", ["pyarrow", "pyarrow.parquet"]),
    ("cobel's runner, envs, agents, recorder", ["cobelrun.runner", "cobelrun.agents"]),
    ("numba", ["numba"]), ("the agent's kernel module", [kernel_module]),
    ("the summary table (rich)", ["cobelrun.commands.summary"]),
]:
    for m in mods:
        importlib.import_module(m)
    now = time.process_time()
    out["import " + label] = now - last
    last = now
spent = {}
def wrap(owner, name, label):
    fn = getattr(owner, name)
    @functools.wraps(fn)
    def timed(*a, **k):
        t = time.process_time()
        try:
            return fn(*a, **k)
        finally:
            spent[label] = spent.get(label, 0.0) + time.process_time() - t
    setattr(owner, name, timed)
import hydra, hydra.core.utils
import cobelrun.compose, cobelrun.hydra_app, cobelrun.runner, cobelrun.commands.summary
import cobelrun.agents.compiled_trials as ct
wrap(cobelrun.hydra_app, "validate", "validate")  # launch calls it by this name
wrap(hydra, "compose", "Hydra's composition")
wrap(cobelrun.compose, "check_config", "the instantiation gate")
wrap(cobelrun.runner, "build_task", "building and checking the task")
wrap(hydra.core.utils, "run_job", "Hydra's job")
wrap(cobelrun.runner, "run", "cobel's run")
for mod in list(sys.modules.values()):  # the agents import load_kernel by name
    if getattr(mod, "__name__", "").startswith("cobelrun.agents") and hasattr(mod, "load_kernel"):
        wrap(mod, "load_kernel", "numba's start and the kernel's load")
wrap(cobelrun.commands.summary, "print_run_summary", "the end-of-run summary")
import cobelrun.commands.run as cr
t = time.process_time()
code = cr.run_plain(cr.plain_run(args))
total_run = time.process_time() - t
v, job = spent.pop("validate", 0.0), spent.pop("Hydra's job", 0.0)
c, g, b = (spent.get(k, 0.0) for k in ("Hydra's composition", "the instantiation gate",
                                        "building and checking the task"))
r, k, sm = (spent.get(k, 0.0) for k in ("cobel's run", "numba's start and the kernel's load",
                                        "the end-of-run summary"))
out["Hydra's composition"] = c
out["the instantiation gate"] = g
out["building and checking the task"] = b
out["the rest of the up-front validation (parse, checks)"] = v - c - g - b
out["numba's start and the kernel's load (first dispatch)"] = k
out["cobel's run: manifest, loop, writes"] = r - k
out["the end-of-run summary"] = sm
out["Hydra's job: .hydra files, logging, copies"] = job - r - sm
out["the rest (argument parsing, run folder, lock)"] = total_run - v - job
out["total (this process)"] = time.process_time() - T0
print(json.dumps(out))
os._exit(code or 0)
"""

#: the kernel module of each agent (``--breakdown`` imports it as its own stage)
KERNELS = {"sr_td": "cobelrun.agents.sr_kernels", "sr_dyna": "cobelrun.agents.sr_kernels",
           "dyna_q": "cobelrun.agents.kernels", "q_learning": "cobelrun.agents.kernels"}  # fmt: skip

#: cobel agent configs and their overrides for the setting
COBEL = {
    "q_learning": ["agent=q_learning", "agent.learning_rate=0.3"],
    "dyna_q": ["agent=dyna_q", "agent.learning_rate=0.3", "agent.replay_batch=3",
               "agent.memory_sampling=visited"],
    "sr_td": ["agent=sr_td", "agent.learning_rate=0.3", "agent.reward_rate=0.3"],
    "sr_dyna": ["agent=sr_dyna", "agent.learning_rate=0.3", "agent.reward_rate=0.3",
                "agent.replay_batch=3", "agent.replay_reward=true"],
    "sarsa": ["agent=sarsa", "agent.learning_rate=0.3"],
    "q_lambda": ["agent=q_lambda", "agent.learning_rate=0.3", "agent.lam=0.95",
                 "agent.trace=accumulating"],
    "mc_control": ["agent=mc_control", "agent.learning_rate=0.3"],
    "tabular_actor_critic": ["agent=tabular_actor_critic", "agent.actor_lr=0.3",
                             "agent.critic_lr=0.3"],
    "dyna_actor_critic": ["agent=dyna_actor_critic", "agent.actor_lr=0.3",
                          "agent.critic_lr=0.3", "agent.replay_batch=3"],
}  # fmt: skip

NAMES = {
    "q_learning": "Q-learning", "dyna_q": "Dyna-Q, 3 replays", "sr_td": "SR-TD",
    "sr_dyna": "SR-Dyna, 3 replays", "sarsa": "SARSA", "q_lambda": "Q(lambda) (QET)",
    "mc_control": "MC control", "tabular_actor_critic": "actor-critic",
    "dyna_actor_critic": "Dyna actor-critic, 3 replays",
}  # fmt: skip


def cobel_cmd() -> list[str]:
    exe = Path(sys.executable).with_name("cobel")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cobelrun.cli"]


def compile_bytecode(checkout: Path) -> None:
    """Compile ``checkout``'s ``cobelrun`` to bytecode (as ``pip install`` does)."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(checkout / "cobelrun")],
                   check=True, stdout=subprocess.DEVNULL)  # fmt: skip


def timed(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float, str, str, int]:
    """Wall and CPU (user + system) seconds of one child process, its output and exit code."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        return (wall, usage.ru_utime + usage.ru_stime, out.read().decode(), err.read().decode(),
                os.waitstatus_to_exitcode(status))  # fmt: skip


def run_args(name: str, seeds: int, episodes: int, max_steps: int, out: Path) -> list[str]:
    """The words after ``cobel`` of the setting's ``cobel run`` of ``name`` into ``out``."""
    return ["run", "task=gridworld", "env.world.width=9", "env.world.height=9",
            "env.world.starts=[0]", "env.world.goal=80", *COBEL[name],
            "agent.policy=softmax", "agent.beta=50", "agent.gamma=0.95",
            f"task.runs={seeds}", f"task.protocol.phases.0.trials={episodes}",
            f"task.protocol.max_steps={max_steps}", "task.record.steps=false",
            "task.record.mcap=false", "task.save_agents=none", f"hydra.run.dir={out}"]  # fmt: skip


def run_cobel(name: str, seeds: int, episodes: int, max_steps: int, tmp: Path,
              checkout: Path | None = None) -> dict:  # fmt: skip
    """One ``cobel run`` of ``name``; ``checkout``: run that checkout of cobel instead."""
    out = tmp / f"cobel_{name}_{time.monotonic_ns()}"
    args = [*cobel_cmd(), *run_args(name, seeds, episodes, max_steps, out)]
    env = None if checkout is None else {**os.environ, "PYTHONPATH": str(checkout)}
    wall, cpu, _, stderr, code = timed(args, env)
    if code != 0:
        raise SystemExit(f"cobel run failed for {name}: {stderr.strip()[-400:]}")
    manifest = json.loads((out / "manifest.json").read_text())
    import pyarrow.parquet as pq

    trials = pq.read_table(out / "trials.parquet", columns=["run", "steps"]).to_pydict()
    steps = sum(trials["steps"])
    per_run: dict[int, list[int]] = {}
    for r, s in zip(trials["run"], trials["steps"], strict=True):
        per_run.setdefault(r, []).append(s)
    last20 = statistics.mean(statistics.mean(v[-20:]) for v in per_run.values())
    shutil.rmtree(out, ignore_errors=True)
    return {"steps": steps, "loop_s": sum(manifest["phase_wall_time_s"].values()),
            "process_s": wall, "process_cpu_s": cpu, "last20": last20}  # fmt: skip


def run_cobel_warm(name: str, seeds: int, episodes: int, max_steps: int, tmp: Path) -> dict:
    script = tmp / "cobel_warm.py"
    script.write_text(COBEL_WARM_SCRIPT)
    agent = COBEL[name][0].split("=", 1)[1]
    overrides = [*COBEL[name][1:], "agent.policy=softmax", "agent.beta=50", "agent.gamma=0.95"]
    proc = subprocess.run(
        [sys.executable, str(script), str(HERE.parent / "conf" / "agent" / f"{agent}.yaml"),
         json.dumps(overrides), str(seeds), str(episodes), str(max_steps)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        raise SystemExit(f"cobel warm run failed for {name}: {proc.stderr.strip()[-400:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_breakdown(name: str, seeds: int, episodes: int, max_steps: int, tmp: Path) -> dict:
    """One ``cobel run`` of ``name`` under :data:`BREAKDOWN_SCRIPT`: CPU seconds by stage."""
    script = tmp / "cobel_breakdown.py"
    script.write_text(BREAKDOWN_SCRIPT)
    out = tmp / f"breakdown_{name}_{time.monotonic_ns()}"
    args = run_args(name, seeds, episodes, max_steps, out)
    _, cpu, stdout, stderr, code = timed(
        [sys.executable, str(script), KERNELS.get(name, "cobelrun.agents.kernels"),
         json.dumps(args)]
    )  # fmt: skip
    shutil.rmtree(out, ignore_errors=True)
    if code != 0:
        raise SystemExit(f"cobel breakdown failed for {name}: {stderr.strip()[-400:]}")
    lines = [line for line in stdout.splitlines() if line.startswith("{")]
    return {**json.loads(lines[-1]), "whole process (wait4: with its git and uname children)": cpu}


def breakdown(agents: list[str], repeats: int, seeds: int, episodes: int,
              max_steps: int) -> str:  # fmt: skip
    """The ``--breakdown`` table: medians of ``repeats`` processes per agent, interleaved with
    a plain ``cobel run`` of the same setting (its whole-process CPU seconds)."""
    rows: dict[str, list[dict]] = {a: [] for a in agents}
    plain: dict[str, list[float]] = {a: [] for a in agents}
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        for a in agents:  # untimed: numba's cache, the page cache
            run_breakdown(a, 1, 2, max_steps, tmp)
        for _ in range(repeats):
            for a in agents:
                rows[a].append(run_breakdown(a, seeds, episodes, max_steps, tmp))
                plain[a].append(run_cobel(a, seeds, episodes, max_steps, tmp)["process_cpu_s"])
    keys = list(rows[agents[0]][0])
    names = " | ".join(NAMES[a] for a in agents)
    lines = [f"| CPU s (median of {repeats}) | {names} |", "|---|" + "---:|" * len(agents)]
    for k in keys:
        lines.append(f"| {k} | " + " | ".join(
            f"{statistics.median(r[k] for r in rows[a]):.3f}" for a in agents) + " |")  # fmt: skip
    lines.append("| a plain `cobel run` of the setting, whole process | " + " | ".join(
        f"{statistics.median(plain[a]):.3f}" for a in agents) + " |")  # fmt: skip
    return "\n".join(lines)


def run_neuronav(python: str, script: Path, name: str, seeds: int, episodes: int,
                 max_steps: int) -> dict:  # fmt: skip
    wall, cpu, stdout, stderr, code = timed(
        [python, str(script), name, str(seeds), str(episodes), str(max_steps)]
    )
    if code != 0:
        raise SystemExit(f"neuro-nav run failed for {name}: {stderr.strip()[-400:]}")
    out = json.loads(stdout.strip().splitlines()[-1])
    return {**out, "process_s": wall, "process_cpu_s": cpu}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--neuronav-python", default="/tmp/nnvenv/bin/python")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--max-steps", type=int, default=100)
    ap.add_argument("--agents", default=",".join(COBEL))
    ap.add_argument("--json", type=Path, help="also write the raw numbers here")
    ap.add_argument(
        "--baseline",
        type=Path,
        metavar="CHECKOUT",
        help="also run cobel run from this checkout (interleaved)",
    )
    ap.add_argument("--no-warm", action="store_true", help="skip the in-process warm runs")
    ap.add_argument("--breakdown", action="store_true",
                    help="only split cobel's whole process into stages (CPU seconds)")  # fmt: skip
    ap.add_argument("--add-warm", type=Path, metavar="JSON",
                    help="only measure cobel warm and add it to an earlier --json file")  # fmt: skip
    args = ap.parse_args()
    if args.add_warm:
        raw = json.loads(args.add_warm.read_text())
        with tempfile.TemporaryDirectory() as tmpdir:
            for _ in range(args.repeats):
                for a in raw:
                    raw[a].setdefault("cobel_warm", []).append(run_cobel_warm(
                        a, args.seeds, args.episodes, args.max_steps, Path(tmpdir)))  # fmt: skip
        args.add_warm.write_text(json.dumps(raw, indent=1))
        print(table(raw))
        return
    agents = args.agents.split(",")
    unknown = [a for a in agents if a not in COBEL]
    if unknown:
        raise SystemExit(f"unknown agent {unknown[0]!r}; allowed: {', '.join(COBEL)}")
    if args.breakdown:
        compile_bytecode(HERE.parent)
        print(breakdown(agents, args.repeats, args.seeds, args.episodes, args.max_steps))
        return
    raw: dict[str, dict[str, list[dict]]] = {
        a: {"neuronav": [], "cobel": [], "cobel_warm": [], "baseline": []} for a in agents
    }
    compile_bytecode(HERE.parent)
    if args.baseline:
        compile_bytecode(args.baseline)
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        script = tmp / "neuronav_run.py"
        script.write_text(NEURONAV_SCRIPT)
        for a in agents:  # untimed: numba's cache of the kernels, the files in the page cache
            run_neuronav(args.neuronav_python, script, a, 1, 2, args.max_steps)
            run_cobel(a, 1, 2, args.max_steps, tmp)
            if args.baseline:
                run_cobel(a, 1, 2, args.max_steps, tmp, args.baseline)
        for rep in range(args.repeats):
            for a in agents:
                raw[a]["neuronav"].append(run_neuronav(args.neuronav_python, script, a,
                                                       args.seeds, args.episodes,
                                                       args.max_steps))  # fmt: skip
                raw[a]["cobel"].append(run_cobel(a, args.seeds, args.episodes, args.max_steps,
                                                 tmp))  # fmt: skip
                if args.baseline:
                    raw[a]["baseline"].append(run_cobel(a, args.seeds, args.episodes,
                                                        args.max_steps, tmp, args.baseline))  # fmt: skip
                if not args.no_warm:
                    raw[a]["cobel_warm"].append(run_cobel_warm(a, args.seeds, args.episodes,
                                                               args.max_steps, tmp))  # fmt: skip
                print(f"rep {rep + 1}/{args.repeats} {a}: neuro-nav "
                      f"{raw[a]['neuronav'][-1]['loop_s']:.2f} s, cobel "
                      f"{raw[a]['cobel'][-1]['loop_s']:.2f} s", file=sys.stderr, flush=True)  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(raw, indent=1))
    print(table(raw))


def _med(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def table(raw: dict[str, dict[str, list[dict]]]) -> str:
    """The Markdown table of medians: steps per second of the run loop and of the whole
    process (steps over the process's wall time), and cobel / neuro-nav ratios; then the
    processes' CPU seconds (and the baseline checkout's process, where measured)."""
    lines = [
        "| agent | neuro-nav loop | cobel loop | ratio | cobel warm | ratio "
        "| neuro-nav process | cobel process | ratio | last 20 episodes (nn / cobel) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for a, r in raw.items():
        nn, cb = r["neuronav"], r["cobel"]
        nn_loop = statistics.median(x["steps"] / x["loop_s"] for x in nn)
        cb_loop = statistics.median(x["steps"] / x["loop_s"] for x in cb)
        warm = r.get("cobel_warm") or [{"steps": float("nan"), "loop_s": 1.0}]
        cb_warm = statistics.median(x["steps"] / x["loop_s"] for x in warm)
        nn_proc = statistics.median(x["steps"] / x["process_s"] for x in nn)
        cb_proc = statistics.median(x["steps"] / x["process_s"] for x in cb)
        lines.append(
            f"| {NAMES[a]} | {nn_loop:,.0f} | {cb_loop:,.0f} | {cb_loop / nn_loop:.1f}x "
            f"| {cb_warm:,.0f} | {cb_warm / nn_loop:.0f}x "
            f"| {nn_proc:,.0f} | {cb_proc:,.0f} | {cb_proc / nn_proc:.1f}x "
            f"| {_med(nn, 'last20'):.1f} / {_med(cb, 'last20'):.1f} |"
        )
    if not all("process_cpu_s" in x for r in raw.values() for x in (*r["neuronav"], *r["cobel"])):
        return "\n".join(lines)  # an older --json file: wall times only
    base = any(r.get("baseline") for r in raw.values())
    lines += [
        "",
        "| agent | neuro-nav process s (CPU s) | cobel process s (CPU s) | steps/s ratio "
        "| CPU ratio |"
        + (" baseline process s (CPU s) | steps/s ratio | CPU ratio |" if base else ""),
        "|---|---:|---:|---:|---:|" + ("---:|---:|---:|" if base else ""),
    ]
    for a, r in raw.items():
        nn = r["neuronav"]
        nn_proc = statistics.median(x["steps"] / x["process_s"] for x in nn)
        nn_cpu = statistics.median(x["steps"] / x["process_cpu_s"] for x in nn)
        row = f"| {NAMES[a]} | {_med(nn, 'process_s'):.2f} ({_med(nn, 'process_cpu_s'):.2f}) "
        for key in ("cobel", "baseline") if base else ("cobel",):
            cb = r.get(key) or []
            if not cb:
                row += "| | | |"
                continue
            cb_proc = statistics.median(x["steps"] / x["process_s"] for x in cb)
            cb_cpu = statistics.median(x["steps"] / x["process_cpu_s"] for x in cb)
            row += (f"| {_med(cb, 'process_s'):.2f} ({_med(cb, 'process_cpu_s'):.2f}) "
                    f"| {cb_proc / nn_proc:.1f}x | {cb_cpu / nn_cpu:.1f}x ")  # fmt: skip
        lines.append(row + "|")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
