"""Unit activity of deep agents: layer activations for fixed probe observations.

The monitor takes snapshots at the start of each run (trial 0), after every ``every``-th
trial and after the run's last trial. A snapshot feeds the probe observations (by default the
observation of every state of the environment) through the agent's network and records the
outputs of the named layers. The ``activity`` table (``activity.parquet``) is long format:
one row per (run, trial, layer, unit, probe) with the activation ``value``.

Agents opt in by offering ``activations(observations, layers) -> {layer: (n_probes, units)}``
and ``layer_names()`` (DQNAgent, DynaDQN, DynaDSR). The snapshots are taken through a
:class:`~cobelrun.agents.base.TrialCallback`, at the end of the trial; for tabular agents that
means the per-step Python path.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
import pyarrow as pa

from cobelrun.agents.base import TrialCallback
from cobelrun.envs.base import DiscreteStates, StateObservations
from cobelrun.errors import ConfigError, suggest
from cobelrun.monitors.base import Monitor, Table


@runtime_checkable
class HasActivations(Protocol):
    """Agents whose named layers can be read out (DQNAgent, DynaDQN, DynaDSR)."""

    def layer_names(self) -> list[str]: ...

    def activations(
        self, observations: np.ndarray, layers: Sequence[str]
    ) -> dict[str, np.ndarray]: ...


class ActivityMonitor(Monitor, TrialCallback):
    """Record activations of named layers for probe observations every ``every`` trials.

    Parameters
    ----------
    layers
        Layer names (see the agent's ``layer_names()``); default: all of them.
    every
        Snapshot after every N-th trial (trial numbers count across phases, from 1).
    probes
        (n, ...) probe observations; default: the environment's ``observations`` (one per
        state), or the state indices of an environment that observes indices.
    """

    #: a run's snapshot bookkeeping, kept by checkpoints
    checkpoint_fields: ClassVar[tuple[str, ...]] = ("_run", "_last", "layers")

    def __init__(
        self, layers: Sequence[str] | None = None, every: int = 10, probes: Any = None
    ) -> None:
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ConfigError(f"activity monitor 'every' must be an integer >= 1, got {every!r}")
        self.layers = None if layers is None else [str(x) for x in layers]
        self.every = every
        self.probes = None if probes is None else np.asarray(probes)
        self._run = 0
        self._first = 1
        self._last = -1

    # -- wiring ------------------------------------------------------------------------------
    def setup(self, env: Any) -> None:
        if self.probes is not None:
            return
        base = env.unwrapped
        if isinstance(base, StateObservations):
            self.probes = np.asarray(base.observations)
        elif isinstance(base, DiscreteStates):
            self.probes = np.arange(base.n_states)
        else:
            raise ConfigError(
                f"activity monitor: {type(base).__name__} has no per-state observations; "
                "give probe observations with 'probes'"
            )

    def tables(self) -> list[Table]:
        return [Table("activity", (
            pa.field("run", pa.int32()), pa.field("trial", pa.int32()),
            pa.field("layer", pa.string()), pa.field("unit", pa.int32()),
            pa.field("probe", pa.int32()), pa.field("value", pa.float32()),
        ), per="event")]  # fmt: skip

    def check_agent(self, agent: Any) -> None:
        """Before anything is written: the agent exposes activations and has the named layers
        (a one-line ConfigError with the closest name and the layers it has otherwise)."""
        if not isinstance(agent, HasActivations):
            raise ConfigError(
                f"activity monitor: agent {type(agent).__name__} exposes no layer activations "
                "(deep agents do: DQNAgent, DynaDQN, DynaDSR)"
            )
        names = list(agent.layer_names())
        unknown = [name for name in self.layers or [] if name not in names]
        if unknown:
            raise ConfigError(
                f"activity monitor: unknown layer {unknown[0]!r}{suggest(unknown[0], names)}; "
                f"agent {type(agent).__name__} has: {', '.join(names)}"
            )

    # -- timing ------------------------------------------------------------------------------
    def start_run(self, run: int, agent: Any = None) -> None:
        """A new agent (run): check it (:meth:`check_agent`) and take the trial-0 snapshot."""
        self.check_agent(agent)
        self._run, self._last = run, -1
        if self.layers is None:
            self.layers = list(agent.layer_names())
        self.snapshot(agent, 0)

    def callbacks(self, first_trial: int) -> list[Any]:
        """The next trials passed to the callback are numbered from ``first_trial``."""
        self._first = first_trial
        return [self]

    def _on_trial_end(self, agent: Any, trial: int, record: dict[str, Any]) -> None:
        t = self._first + trial
        if t % self.every == 0:
            self.snapshot(agent, t)

    def end_run(self, run: int, agent: Any, last_trial: int) -> None:
        """The run is over: snapshot its last trial unless that was just done."""
        if self._last != last_trial:
            self.snapshot(agent, last_trial)

    def snapshot(self, agent: Any, trial: int) -> None:
        assert self.layers is not None and self.probes is not None
        acts = agent.activations(self.probes, self.layers)
        cols: dict[str, list[np.ndarray]] = {f.name: [] for f in self.tables()[0].fields}
        for layer, arr in acts.items():
            arr = np.asarray(arr, dtype=np.float32).reshape(len(self.probes), -1)
            n_probes, n_units = arr.shape
            n = arr.size
            cols["run"].append(np.full(n, self._run, np.int32))
            cols["trial"].append(np.full(n, trial, np.int32))
            cols["layer"].append(np.full(n, layer, dtype=object))
            cols["unit"].append(np.tile(np.arange(n_units, dtype=np.int32), n_probes))
            cols["probe"].append(np.repeat(np.arange(n_probes, dtype=np.int32), n_units))
            cols["value"].append(arr.ravel())
        self._last = trial
        if cols["run"]:
            self.emit("activity", {k: np.concatenate(v) for k, v in cols.items()})
