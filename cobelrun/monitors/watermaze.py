"""Water-maze measures per trial (``trials.parquet`` columns), from the trials' poses."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from cobelrun.analysis.watermaze import MEASURE_COLUMNS, split_trials, trial_measures
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.monitors.base import TrialColumnsMonitor
from cobelrun.records import TrialBatch


class WaterMazeMonitor(TrialColumnsMonitor):
    """Escape latency in seconds, path length, distance to the platform, quadrant occupancy,
    platform and annulus crossings of every trial (:mod:`cobelrun.analysis.watermaze`).

    The platform a trial is measured against is the rewarded terminal goal region of the
    environment when the trial's phase ran; in a probe phase (no such region: the platform is
    removed) it is the last one seen, so quadrant occupancy is about the trained location. A
    reversal phase that moves the platform switches the target with it.

    Parameters
    ----------
    platform : str, optional
        Measure against this goal region always (default: follow the rewarded region as above).
    crossing_radius : float, optional
        Radius of the crossing zones (default the platform's radius).
    dt : float, optional
        Seconds per step (default the environment's ``dt``).
    """

    #: the platform the measures refer to, kept by checkpoints
    checkpoint_fields: ClassVar[tuple[str, ...]] = ("_target",)

    requires = ("pose", "geometry")

    def __init__(
        self,
        platform: str | None = None,
        crossing_radius: float | None = None,
        dt: float | None = None,
    ) -> None:
        for name, value in (("crossing_radius", crossing_radius), ("dt", dt)):
            if value is not None and (
                isinstance(value, bool) or not isinstance(value, int | float) or value <= 0
            ):
                raise ConfigError(f"watermaze monitor: {name} must be > 0, got {value!r}")
        self.platform = platform
        self.crossing_radius = crossing_radius
        self.dt = dt
        self._target: str | None = None

    def setup(self, env: Any) -> None:
        super().setup(env)
        base = env.unwrapped
        regions = base.geometry().regions
        circles = [k for k, r in regions.items() if r.get("shape") == "circle" and "reward" in r]
        if self.platform is not None and self.platform not in circles:
            raise ConfigError(
                f"watermaze monitor: platform {self.platform!r} is not a circular goal region"
                f"{suggest(self.platform, circles)}; known: {allowed_list(circles)}"
            )
        if not circles:
            raise ConfigError("the water-maze monitor needs a circular goal region (the platform)")
        if self.dt is None:
            self.dt = float(getattr(base, "dt", 1.0))

    def start_run(self, run: int, agent: Any = None) -> None:
        self._target = self.platform

    def fields(self) -> list[pa.Field]:
        ints = {"platform_crossings"}
        return [pa.field("platform", pa.string())] + [
            pa.field(c, pa.int64() if c in ints else pa.float64()) for c in MEASURE_COLUMNS
        ]

    def _current_target(self, regions: dict[str, dict[str, Any]]) -> str:
        if self.platform is not None:
            return self.platform
        active = [k for k, r in regions.items() if r.get("shape") == "circle"
                  and r.get("terminal") and r.get("reward", 0) > 0]  # fmt: skip
        if active:
            self._target = active[0]
        if self._target is None:  # a probe first: the first circular goal
            self._target = next(
                k for k, r in regions.items() if r.get("shape") == "circle" and "reward" in r
            )
        return self._target

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        base = env.unwrapped
        regions = base.geometry().regions
        target = self._current_target(regions)
        poses = batch.poses()
        if poses is None:
            raise ConfigError("the water-maze monitor needs poses in the trial records")
        reg = regions[target]
        outline = base.geometry().outline
        centre = outline.mean(axis=0) if len(outline) else (0.0, 0.0)
        df = trial_measures(split_trials(poses, batch.steps), (reg["x"], reg["y"]), reg["radius"],
                            float(self.dt or 1.0), centre, self.crossing_radius)  # fmt: skip
        cols = {c: df[c].to_numpy() for c in MEASURE_COLUMNS}
        cols["platform_crossings"] = cols["platform_crossings"].astype(np.int64)
        cols["platform"] = np.full(batch.n_trials, target, dtype=object)
        return cols
