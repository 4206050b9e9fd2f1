"""The limit for cobel's tabular Dyna-Q: the smallest compiled loop that does Fig. 6B's work.

Fig. 6B (``task=tmaze_extinction``): the 7 x 7 T-maze, epsilon-greedy Dyna-Q (epsilon 0.1,
learning rate 0.9, gamma 0.9), model memory with running-average rewards (rate 0.9), 5
replayed experiences after every step sampled uniformly over all state-action pairs, 100
acquisition trials (reward at the right arm) then 100 extinction trials (reward at the left
arm), at most 35 steps per trial.

:func:`limit_run` does exactly that work for one run, as one numba function, with nothing
else: no masks, no softmax branch, no visited-pair bookkeeping, no per-step output arrays,
no Python between trials or phases. It makes the same random draws as cobel's ``DynaQ`` in the
same order (agent draws from the agent's ``Generator``, the start state from the
environment's; the bounded integers through the same Lemire routine), so it gives the same
step counts and Q table as cobel for the same seeds: ``python benchmarks/limit_dyna_q.py``
checks that, then prints env steps/s of this loop, of cobel's kernel alone
(``run_trials``) and of cobel's steady state (fresh agent per run, both phases through
``DynaQ.train``; the runner's per-run work without recording), and their ratios.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from numba import njit

from cobelrun.agents.kernels import randint  # the RNG primitive cobel's kernels use
from cobelrun.envs import GridWorldEnv
from cobelrun.envs.world import tmaze_paper
from cobelrun.runner import run_seed

EPSILON, LR, GAMMA, RATE, BATCH = 0.1, 0.9, 0.9, 0.9, 5
#: the clock of every timing here: this thread's CPU time (on a shared machine, wall time
#: also counts the time other processes hold the core; ``--wall`` switches to it)
CLOCK = time.thread_time
PHASES = ({"right_arm": 1.0, "left_arm": 0.0}, {"right_arm": 0.0, "left_arm": 1.0})
TRIALS, MAX_STEPS = 100, 35


@njit(cache=True, nogil=True)
def limit_run(rng, env_rng, next_state, rewards, terminal, starts, trials, max_steps,
              eps, lr, gamma, rate, batch, Q, m_next, m_reward, m_terminal, steps):  # fmt: skip
    """One run: ``rewards[p]`` holds phase ``p``'s arrival rewards, ``trials`` trials each.
    Fills ``Q``, the memory arrays and ``steps`` (per trial); returns the env steps."""
    n_actions = Q.shape[1]
    n_pairs = Q.shape[0] * n_actions
    total = 0
    for p in range(rewards.shape[0]):
        R = rewards[p]
        for trial in range(trials):
            s = starts[randint(env_rng, starts.shape[0])]
            n = 0
            while n < max_steps:
                if rng.random() < eps:
                    a = randint(rng, n_actions)
                else:  # greedy, ties broken at random
                    best = Q[s, 0]
                    m = 1
                    a = 0
                    for b in range(1, n_actions):
                        q = Q[s, b]
                        if q > best:
                            best, m, a = q, 1, b
                        elif q == best:
                            m += 1
                    if m > 1:
                        j = randint(rng, m)
                        for b in range(n_actions):
                            if Q[s, b] == best:
                                if j == 0:
                                    a = b
                                    break
                                j -= 1
                s2 = next_state[s, a]
                r = R[s2]
                done = terminal[s2]
                target = r
                if not done:
                    best = Q[s2, 0]
                    for b in range(1, n_actions):
                        best = max(best, Q[s2, b])
                    target += gamma * best
                Q[s, a] += lr * (target - Q[s, a])
                m_next[s, a] = s2
                m_reward[s, a] += rate * (r - m_reward[s, a])
                m_terminal[s, a] = done
                for _ in range(batch):  # replay, uniform over all pairs
                    idx = randint(rng, n_pairs)
                    rs = idx // n_actions
                    ra = idx - rs * n_actions
                    target = m_reward[rs, ra]
                    if not m_terminal[rs, ra]:
                        s3 = m_next[rs, ra]
                        best = Q[s3, 0]
                        for b in range(1, n_actions):
                            best = max(best, Q[s3, b])
                        target += gamma * best
                    Q[rs, ra] += lr * (target - Q[rs, ra])
                n += 1
                s = s2
                if done:
                    break
            steps[p * trials + trial] = n
            total += n
    return total


def fig6b_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(next_state, rewards per phase, terminal, starts) of Fig. 6B's T-maze."""
    env = GridWorldEnv(tmaze_paper())
    base = env.unwrapped
    rewards = []
    for changes in PHASES:
        base.apply_changes(rewards=changes)
        rewards.append(np.array(base.world.rewards, np.float64))
    w = base.world
    return (np.ascontiguousarray(w.next_state, np.int64), np.array(rewards),
            np.ascontiguousarray(w.terminal, np.bool_), np.ascontiguousarray(w.starts, np.int64))  # fmt: skip


def run_limit(runs: int, seed: int = 0, loop_only: bool = False) -> tuple[int, float, list]:
    """Env steps, seconds and per-run (steps, Q) of ``runs`` runs of the limit loop.

    Timed per run: what any program with these semantics must do, namely derive the run's
    two seeds from the one ``seed`` (``SeedSequence`` children, as cobel), make its two
    generators, zero its Q table and memory, and run the compiled loop. ``loop_only`` times
    only the compiled calls (the loop's own speed, seeding excluded).
    """
    nxt, rewards, terminal, starts = fig6b_tables()
    n_states = nxt.shape[0]
    total, elapsed, out = 0, 0.0, []
    for run in range(runs):
        t0 = CLOCK()
        agent_seed, env_seed = run_seed(seed, run)
        rng, env_rng = np.random.default_rng(agent_seed), np.random.default_rng(env_seed)
        Q = np.zeros((n_states, 4))
        m_next = np.repeat(np.arange(n_states, dtype=np.int64)[:, None], 4, 1)
        m_reward, m_terminal = np.zeros((n_states, 4)), np.ones((n_states, 4), np.bool_)
        steps = np.zeros(2 * TRIALS, np.int64)
        t1 = CLOCK()
        total += limit_run(rng, env_rng, nxt, rewards, terminal, starts, TRIALS, MAX_STEPS,
                           EPSILON, LR, GAMMA, RATE, BATCH, Q, m_next, m_reward, m_terminal,
                           steps)  # fmt: skip
        elapsed += CLOCK() - (t1 if loop_only else t0)
        out.append((steps, Q))
    return total, elapsed, out


def run_cobel(runs: int, seed: int = 0, kernel_only: bool = False) -> tuple[int, float, list]:
    """Env steps, seconds and per-run (steps, Q) of cobel's ``DynaQ`` on Fig. 6B, the way
    the runner does a run (world reset, environment generator, fresh agent, one ``train``
    per phase), without recording. ``kernel_only`` times only the compiled ``run_trials``
    calls inside."""
    import cobelrun.agents.kernels as kernels
    from cobelrun.agents import DynaQ

    env = GridWorldEnv(tmaze_paper())
    base = env.unwrapped
    inner = [0.0]
    kernel = kernels.run_trials

    def timed(*args):
        t = CLOCK()
        try:
            return kernel(*args)
        finally:
            inner[0] += CLOCK() - t

    if kernel_only:
        kernels.run_trials = timed
    total, out = 0, []
    try:
        t0 = CLOCK()
        for run in range(runs):
            agent_seed, env_seed = run_seed(seed, run)
            base.reset_world()
            base.np_random = np.random.default_rng(env_seed)
            agent = DynaQ(env, epsilon=EPSILON, beta=5.0, learning_rate=LR, gamma=GAMMA,
                          replay_batch=BATCH, memory_reward_rate=RATE, seed=agent_seed)  # fmt: skip
            steps = []
            for changes in PHASES:
                base.apply_changes(rewards=changes)
                batch = agent.train(TRIALS, MAX_STEPS)
                total += batch.n_steps
                steps.append(batch.steps)
            out.append((np.concatenate(steps), agent.Q.copy()))
        elapsed = CLOCK() - t0
    finally:
        kernels.run_trials = kernel
    return total, inner[0] if kernel_only else elapsed, out


def check_same(runs: int = 5) -> None:
    """The limit and cobel make the same draws: identical steps per trial and Q tables."""
    _, _, lim = run_limit(runs)
    _, _, cob = run_cobel(runs)
    for r, ((s1, q1), (s2, q2)) in enumerate(zip(lim, cob, strict=True)):
        if not (np.array_equal(s1, s2) and np.array_equal(q1, q2)):
            raise SystemExit(f"run {r}: the limit loop and cobel's DynaQ differ")


def measure(runs: int = 100, repeat: int = 7) -> dict[str, float]:
    """Steps/s of the limit (with and without its per-run seeding), cobel's steady state and
    cobel's kernel alone: interleaved rounds, so that machine load hits all of them alike.
    Rates are the best round; ratios are the median of the rounds' ratios."""
    check_same()
    run_limit(1), run_cobel(1)  # compile or load from numba's cache
    fns = {
        "limit": lambda: run_limit(runs),
        "limit_loop": lambda: run_limit(runs, loop_only=True),
        "steady": lambda: run_cobel(runs),
        "kernel": lambda: run_cobel(runs, kernel_only=True),
    }
    rounds: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            steps, seconds, _ = fn()
            rounds[name].append(steps / seconds)
    ratio = {
        "steady_over_limit": ("steady", "limit"),
        "steady_over_limit_loop": ("steady", "limit_loop"),
        "kernel_over_limit_loop": ("kernel", "limit_loop"),
    }
    return {
        **{f"{k}_steps_per_s": max(v) for k, v in rounds.items()},
        **{
            k: float(np.median(np.array(rounds[a]) / np.array(rounds[b])))
            for k, (a, b) in ratio.items()
        },
        "steps_per_run": run_limit(1)[0],
        "clock": "wall" if CLOCK is time.perf_counter else "thread CPU",
    }


def report(res: dict[str, float]) -> None:
    """Print :func:`measure`'s result."""
    rows = [
        ("limit (per run: seeds, generators, arrays, compiled loop)", "limit", None),
        ("limit, compiled loop only", "limit_loop", None),
        ("cobel steady state (fresh DynaQ per run, train per phase)", "steady",
         "steady_over_limit"),
        ("cobel kernel alone (run_trials calls)", "kernel", "kernel_over_limit_loop"),
    ]  # fmt: skip
    print(f"Fig. 6B Dyna-Q, env steps/s ({res['clock']} time, {res['steps_per_run']} steps per "
          "run); same steps and Q tables as cobel's DynaQ: yes")  # fmt: skip
    for label, key, ratio in rows:
        extra = (
            f"  {res[ratio]:.2f} of {'the limit' if ratio == 'steady_over_limit' else 'the compiled loop'}"
            if ratio
            else ""
        )
        print(f"  {label:58s} {res[key + '_steps_per_s']:>12,.0f}{extra}")
    print(f"  cobel steady state / the limit's compiled loop alone: "
          f"{res['steady_over_limit_loop']:.2f}")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    global CLOCK
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--wall", action="store_true", help="time with the wall clock")
    opts = ap.parse_args(argv)
    if opts.wall:
        CLOCK = time.perf_counter
    report(measure(opts.runs, opts.repeat))


if __name__ == "__main__":
    sys.exit(main())
