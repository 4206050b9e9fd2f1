"""Fixed start-up costs of a deep process (issue 35, item 5): what ``cobel run task=two_afc``
pays before its first trial, against the floors it stands on.

Whole processes, interleaved round by round (machine load hits all alike), median wall and
CPU time (user + system of the child, ``os.wait4``) of

* ``import torch``;
* ``import torch`` then ``import torch._dynamo`` (what torch.optim loads, below);
* ``import torch`` then one ``torch.optim.Adam`` built: in torch 2.x every optimizer's
  constructor (``Optimizer.add_param_group``, wrapped by ``torch._disable_dynamo``) and every
  ``step`` (``_use_grad_for_differentiable``) imports ``torch._dynamo`` on first use; the
  script checks that it did (``torch._dynamo`` in ``sys.modules``);
* ``import stable_baselines3``;
* ``cobel run task=two_afc`` (100 DQN runs x 50 trials, batched), whole.

Usage::

    python benchmarks/bench_deep_startup.py [--repeats 5]
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
OPTIM = (
    "import sys, torch\n"
    "torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))])\n"
    "assert 'torch._dynamo' in sys.modules, 'torch.optim did not load torch._dynamo'\n"
)


def timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{cmd} failed: {proc.stderr.read().decode()[-2000:]}")
    return wall, usage.ru_utime + usage.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "deep_startup.json")
    args = ap.parse_args()
    py = sys.executable
    cobel = shutil.which("cobel", path=str(Path(py).parent)) or "cobel"
    tmp = Path(tempfile.mkdtemp(prefix="cobel-startup-"))
    env = {**os.environ, "COBEL_RESULTS": str(tmp)}
    cases = {
        "import torch": [py, "-c", "import torch"],
        "import torch + torch._dynamo": [py, "-c", "import torch, torch._dynamo"],
        "import torch + one torch.optim.Adam": [py, "-c", OPTIM],
        "import stable_baselines3": [py, "-c", "import stable_baselines3"],
        "cobel run task=two_afc": [cobel, "run", "task=two_afc", "--quiet"],
    }
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in cases}
    for _ in range(args.repeats):
        for name, cmd in cases.items():
            times[name].append(timed(cmd, env))
    shutil.rmtree(tmp, ignore_errors=True)
    rows = {name: {"wall_s": round(statistics.median(w for w, _ in t), 2),
                   "cpu_s": round(statistics.median(c for _, c in t), 2)}
            for name, t in times.items()}  # fmt: skip
    dyn = rows["import torch + torch._dynamo"]["cpu_s"] - rows["import torch"]["cpu_s"]
    rows["torch._dynamo alone (difference)"] = {"cpu_s": round(dyn, 2)}
    for name, r in rows.items():
        print(f"{name:40s} {r}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"repeats": args.repeats, "results": rows}, indent=1))


if __name__ == "__main__":
    main()
