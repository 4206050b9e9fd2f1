"""Writers for run folders: streamed Parquet tables, an MCAP stream for Foxglove, the manifest.

Both stream writers flush in chunks (memory stays flat) and write to their final path; closing
them (also from ``with`` on an exception or Ctrl-C) leaves complete, readable files.
"""

from __future__ import annotations

from cobelrun.io.manifest import Manifest, config_hash
from cobelrun.io.mcap import McapRecorder
from cobelrun.io.mcap_repair import repair_mcap
from cobelrun.io.parquet import ParquetStreamWriter

__all__ = [
    "Manifest",
    "McapRecorder",
    "ParquetStreamWriter",
    "config_hash",
    "repair_mcap",
]
