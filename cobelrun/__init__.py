"""cobel: config-driven experiment runner for neuroscience-oriented reinforcement learning.

The Python API (``cobelrun.run``, ``cobelrun.rerun``, ``cobelrun.load``,
``cobelrun.load_sweep``, ``cobelrun.Run``) lives in :mod:`cobelrun.api` and is imported on
first use, so ``import cobelrun`` stays light (no torch, no Hydra).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from cobelrun._version import __version__

__all__ = ["Run", "__version__", "load", "load_sweep", "rerun", "run"]

if TYPE_CHECKING:
    from cobelrun.api import Run, load, load_sweep, rerun, run

_API = {"Run", "load", "load_sweep", "rerun", "run"}


def __getattr__(name: str) -> Any:
    if name in _API:
        from cobelrun import api

        return getattr(api, name)
    raise AttributeError(f"module 'cobelrun' has no attribute {name!r}")
