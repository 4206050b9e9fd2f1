"""Thread count of the OpenBLAS libraries loaded in this process (numpy's and scipy's wheels).

numpy has no API for it and OpenBLAS reads ``OPENBLAS_NUM_THREADS`` only when it is loaded, so
this calls OpenBLAS's own setter through ctypes (what ``threadpoolctl`` does; Linux only, a no-op
elsewhere). One vector times a matrix per step (MFEC's projection) is memory-bound: a second
thread does not make it faster, and on shared cores a busy-waiting OpenBLAS thread can make it
10-30x slower. Thread counts never change OpenBLAS's results (each output element is summed by
one thread in the same order).
"""

from __future__ import annotations

import ctypes
import os
import sys
from pathlib import Path
from typing import Any

_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
            "openblas_set_num_threads64_", "openblas_set_num_threads")  # fmt: skip
_GETTERS = tuple(s.replace("_set_", "_get_") for s in _SETTERS)


def _libraries() -> list[ctypes.CDLL]:
    if not sys.platform.startswith("linux"):
        return []
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return []
    paths = sorted({line.split()[-1] for line in maps.splitlines()
                    if "openblas" in line.rsplit("/", 1)[-1].lower() and ".so" in line})  # fmt: skip
    libs = []
    for path in paths:
        try:
            libs.append(ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_GLOBAL))
        except OSError:
            continue
    return libs


def _function(lib: ctypes.CDLL, names: tuple[str, ...]) -> Any:
    for name in names:
        try:
            return getattr(lib, name)
        except AttributeError:
            continue
    return None


def set_blas_threads(n: int) -> int:
    """Set the thread count of every loaded OpenBLAS; returns how many libraries took it."""
    done = 0
    for lib in _libraries():
        fn = _function(lib, _SETTERS)
        if fn is not None:
            fn.restype = None
            fn(ctypes.c_int(int(n)))
            done += 1
    return done


def blas_threads() -> list[int]:
    """Thread counts of the loaded OpenBLAS libraries."""
    counts = []
    for lib in _libraries():
        fn = _function(lib, _GETTERS)
        if fn is not None:
            fn.restype = ctypes.c_int
            counts.append(int(fn()))
    return counts
