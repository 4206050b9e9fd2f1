"""`hydra/launcher=ray` (the `ray` extra) runs a sweep through cobel's sweeper on a local Ray."""

from __future__ import annotations

import importlib.util

import pytest

from cobelrun.io.sweep_folder import job_rows


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_ray_launcher") is None,
                    reason="needs the ray extra: pip install 'cobelrun[ray]'")  # fmt: skip
def test_ray_launcher_sweep(cobel, tmp_path):
    proc = cobel("run", "-m", "hydra/launcher=ray", "+hydra.launcher.ray.init.num_cpus=2",
                 "task=tmaze_extinction", "seed=1,2", "task.runs=2",
                 "task.protocol.phases.0.trials=5", "task.protocol.phases.1.trials=5",
                 "task.record.mcap=false", f"hydra.sweep.dir={tmp_path / 'sw'}", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert [r["status"] for r in job_rows(tmp_path / "sw", write=False)] == ["done", "done"]
