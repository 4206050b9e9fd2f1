"""Writers for run folders: streamed Parquet tables, an MCAP stream for Foxglove, the manifest.

Both stream writers flush in chunks (memory stays flat) and write to their final path; closing
them (also from ``with`` on an exception or Ctrl-C) leaves complete, readable files.

The names below are imported from their modules on first use, so that importing a submodule
(``cobelrun.io.lock``) does not import foxglove and pyarrow: a run that writes no MCAP never
loads the MCAP writer.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cobelrun.io.manifest import Manifest, config_hash
    from cobelrun.io.mcap import McapRecorder
    from cobelrun.io.mcap_repair import repair_mcap
    from cobelrun.io.parquet import ParquetStreamWriter

#: each public name -> the module that defines it
_WHERE = {
    "Manifest": "cobelrun.io.manifest",
    "config_hash": "cobelrun.io.manifest",
    "McapRecorder": "cobelrun.io.mcap",
    "repair_mcap": "cobelrun.io.mcap_repair",
    "ParquetStreamWriter": "cobelrun.io.parquet",
}

__all__ = [
    "Manifest",
    "McapRecorder",
    "ParquetStreamWriter",
    "config_hash",
    "repair_mcap",
]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(import_module(_WHERE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
