"""Untrusted files: a corrupted render cache or collected dataset is refused with one line that
names the file and the command that rebuilds it (issue 15, item 5). Agent files are checked
against each agent's schema in tests/test_agent_conformance.py."""

from __future__ import annotations

import json
import time

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cobelrun.errors import CobelError
from cobelrun.results import load_collected


# -- render cache -----------------------------------------------------------------------------
@pytest.fixture
def built_cache(tmp_path, monkeypatch):
    pytest.importorskip("pybullet")
    from cobelrun.render import cache
    from tests.test_render import image_env

    monkeypatch.setenv("COBEL_CACHE", str(tmp_path / "cache"))
    req = image_env().observation_module.cache_request()
    path, built = cache.build(req, jobs=1)
    assert built
    return cache, req, path


def test_render_cache_checksums_catch_a_corrupted_frame(built_cache):
    cache, req, path = built_cache
    images = cache.load(req)  # intact: served
    assert images.shape[0] == req.n_nodes
    raw = bytearray(path.read_bytes())
    node = req.n_nodes // 2
    offset = len(raw) - images.nbytes + node * images[0].nbytes + 17  # one pixel of one node
    raw[offset] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(CobelError) as err:
        cache.load(req)
    msg = str(err.value)
    assert f"is corrupted: the frames of node {node} do not match" in msg
    assert "rebuild it with: cobel render-cache" in msg and msg.endswith("--force")


def test_render_cache_without_checksums_is_not_served(built_cache):
    cache, req, path = built_cache
    cache._sums_file(path).unlink()
    with pytest.raises(CobelError, match=r"has no readable checksums .* cannot be trusted"):
        cache.load(req)


def test_render_cache_check_costs_little(tmp_path):
    """Load time with and without the check (printed): a CRC-32 per node block, on a cache the
    size of the 3D T-maze at 84x84 (Fig. 6A paper setting: 200 nodes x 4 headings)."""
    from cobelrun.render import cache

    images = np.random.default_rng(0).integers(0, 255, (200, 4, 84, 84, 3), dtype=np.uint8)
    path = tmp_path / "pybullet-x.npy"
    np.save(path, images)
    cache._sums_file(path).write_text(json.dumps({"crc32": cache.block_checksums(images)}))
    n = 10
    t0 = time.perf_counter()
    for _ in range(n):
        loaded = np.load(path, allow_pickle=False)
    plain = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    for _ in range(n):
        cache.check_blocks(path, loaded)
    check = (time.perf_counter() - t0) / n
    print(f"render cache {images.nbytes / 2**20:.1f} MiB: load {plain * 1e3:.1f} ms, "
          f"checksums {check * 1e3:.1f} ms (+{check / plain:.0%})")  # fmt: skip
    assert check < 0.25  # once per env construction (the cache is loaded once per run)


# -- collected datasets -----------------------------------------------------------------------
def collected_file(tmp_path, **changes):
    out = tmp_path / "sweep" / "collected"
    out.mkdir(parents=True)
    cols = {"job": pa.array([0, 0, 1], pa.int32()), "seed": pa.array([1, 1, 2]),
            "run": pa.array([0, 0, 0], pa.int32()), "trial": pa.array([1, 2, 1], pa.int32())}  # fmt: skip
    cols.update(changes.pop("cols", {}))
    meta = changes.pop("meta", {b"cobel.swept": json.dumps({"seed": "seed"}).encode()})
    table = pa.table(cols).replace_schema_metadata(meta)
    pq.write_table(table, out / "trials.parquet")
    return tmp_path / "sweep"


def test_collected_dataset_is_schema_checked(tmp_path):
    good = collected_file(tmp_path / "a")
    assert len(load_collected(good)) == 3
    cases = {
        "b": ({"meta": {}}, "was not written by `cobel collect`"),
        "c": (
            {"cols": {"job": pa.array(["0", "0", "1"])}},
            "first column must be 'job' \\(int32\\)",
        ),
        "d": ({"meta": {b"cobel.swept": b'{"lr": "lr"}'}}, "lacks the swept columns \\['lr'\\]"),
        "e": ({"cols": {"trial": pa.array([1.5, 2.0, 1.0])}}, "'trial' must hold integers"),
    }
    for name, (changes, message) in cases.items():
        sweep = collected_file(tmp_path / name, **changes)
        with pytest.raises(CobelError, match=message):
            load_collected(sweep)
    broken = collected_file(tmp_path / "f") / "collected" / "trials.parquet"
    broken.write_bytes(broken.read_bytes()[:-20])
    with pytest.raises(
        CobelError, match=r"is not a readable Parquet file.*rewrite it with `cobel collect"
    ):
        load_collected(broken.parent.parent)
    with pytest.raises(CobelError, match="cannot read"):
        load_collected(good, columns=["nope"])
    assert isinstance(load_collected(good, filters=[("seed", "==", 2)]), pd.DataFrame)
