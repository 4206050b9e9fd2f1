"""Run and sweep folders are data: every file cobel reads from one is checked first, and a bad
one is one line naming the file and the problem, never a traceback (issue 31, item 5, the
"Untrusted run-folder files" cases). Each case runs the command in-process on a copy of a
real run or sweep folder made once per session."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.faults.folders import copy_folder, invoke

Mutation = Callable[[Path], None]


def truncate(name: str) -> Mutation:
    def cut(folder: Path) -> None:
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: len(data) // 2])

    return cut


def edit_json(name: str, change: Callable[[dict], object]) -> Mutation:
    def edit(folder: Path) -> None:
        data = json.loads((folder / name).read_text())
        (folder / name).write_text(json.dumps(change(data)))

    return edit


def world(**fields: object) -> Mutation:
    return edit_json("world.json", lambda d: {**d, **fields})


def one_error_line(code: int, out: str, exc: BaseException | None, *names: str) -> str:
    """The command ended with one ``cobel: error:`` line naming ``names``, no traceback."""
    assert exc is None, f"traceback: {exc!r}\n{out}"
    assert code != 0, out
    lines = [ln for ln in out.splitlines() if ln.startswith("cobel: error:")]
    assert len(lines) == 1, out
    assert "Traceback" not in out
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


MANIFEST_CASES = {
    "truncated": (truncate("manifest.json"), "not valid JSON"),
    "list": (edit_json("manifest.json", lambda d: [d]), "must hold a JSON object, not a list"),
    "status-number": (edit_json("manifest.json", lambda d: {**d, "status": 3}), "status"),
}


@pytest.mark.parametrize("command", ["status", "plot"])
@pytest.mark.parametrize("case", sorted(MANIFEST_CASES))
def test_bad_manifest_is_one_line(real_run, tmp_path, case, command):
    mutate, words = MANIFEST_CASES[case]
    run = copy_folder(real_run, tmp_path / "run")
    mutate(run)
    line = one_error_line(*invoke(command, str(run)), "manifest.json")
    assert words in line
    assert not (run / "plot.png").exists()


WORLD_CASES = {
    "truncated": (truncate("world.json"), "not valid JSON"),
    "walls-of-three": (world(walls=[[1, 2, 3]]), "walls[0] must be a list of 4 numbers"),
    "cell-size-zero": (world(cell_size=0), "cell_size must be a finite number > 0"),
    "region-without-xy": (world(regions={"goal": {"shape": "point"}}), "regions.goal (point) has no 'x'"),
    # 1e5 / 0.01 = 10 million cells a side: 728 TiB of histogram bins before this check
    "huge-grid": (world(cells=[[0, 0], [1e5, 1e5]], cell_size=0.01), "more than the 10,000,000"),
    "edge-to-nowhere": (world(edges=[[0, 10**6]]), "edges name nodes outside"),
}  # fmt: skip


@pytest.mark.parametrize("kind", ["occupancy", "trajectories"])
@pytest.mark.parametrize("case", sorted(WORLD_CASES))
def test_bad_world_is_one_line(real_run, tmp_path, case, kind):
    mutate, words = WORLD_CASES[case]
    run = copy_folder(real_run, tmp_path / "run")
    mutate(run)
    line = one_error_line(*invoke("plot", str(run), "--kind", kind), "world.json")
    assert words in line
    assert not (run / f"plot_{kind}.png").exists()


def test_intact_world_still_plots(real_run, tmp_path):
    run = copy_folder(real_run, tmp_path / "run")
    code, out, exc = invoke("plot", str(run), "--kind", "occupancy")
    assert exc is None and code == 0, out
    assert (run / "plot_occupancy.png").is_file()


SWEEP_CASES = {
    "jobs-not-a-list": (edit_json("sweep.json", lambda d: {**d, "jobs": "x"}), "jobs"),
    "job-path": (edit_json("sweep.json", lambda d: {**d, "jobs": [{**d["jobs"][0], "job": "../x"}]}),
                 "jobs.0.job"),
    "swept-not-a-list": (edit_json("sweep.json", lambda d: {**d, "swept": 5}), "swept"),
    "truncated": (truncate("sweep.json"), "not valid JSON"),
}  # fmt: skip


@pytest.mark.parametrize("command", ["status", "collect"])
@pytest.mark.parametrize("case", sorted(SWEEP_CASES))
def test_bad_sweep_file_is_one_line(real_sweep, tmp_path, case, command):
    mutate, words = SWEEP_CASES[case]
    sweep = copy_folder(real_sweep, tmp_path / "sweep")
    mutate(sweep)
    line = one_error_line(*invoke(command, str(sweep)), "sweep.json")
    assert words in line
    assert not (sweep / "collected").exists()


def test_status_does_not_call_a_truncated_table_completed(real_run, tmp_path):
    run = copy_folder(real_run, tmp_path / "run")
    truncate("trials.parquet")(run)
    code, out, exc = invoke("status", str(run))
    assert exc is None and code == 1, out
    assert "completed, but damaged" in out
    assert "unreadable:" in out and "trials.parquet is not a readable Parquet table" in out
    assert "tables: steps\n" in out  # the readable one only


def test_status_of_an_intact_run_is_completed(real_run, tmp_path):
    run = copy_folder(real_run, tmp_path / "run")
    code, out, exc = invoke("status", str(run))
    assert exc is None and code == 0, out
    assert f"{run}: completed\n" in out and "tables: steps, trials" in out


def test_sweep_job_with_a_damaged_manifest_is_failed_not_done(real_sweep, tmp_path):
    sweep = copy_folder(real_sweep, tmp_path / "sweep")
    truncate("manifest.json")(sweep / "1")
    code, out, exc = invoke("status", str(sweep))
    assert exc is None and code == 1, out
    assert "1 done, 1 failed" in out
    from cobelrun.io.sweep_folder import job_rows

    row = job_rows(sweep, write=False)[1]  # the table folds long errors: read the row
    assert row["status"] == "failed" and "manifest.json" in row["error"]


def test_sweep_job_folder_linking_outside_is_not_followed(real_sweep, tmp_path):
    """A job folder that is a symlink to a folder elsewhere is reported, never written to."""
    sweep = copy_folder(real_sweep, tmp_path / "sweep")
    outside = copy_folder(sweep / "1", tmp_path / "elsewhere")
    (outside / "job.json").write_text(json.dumps({"status": "running", "pid": 999999,
                                                   "host": "x"}))  # fmt: skip
    import shutil

    shutil.rmtree(sweep / "1")
    (sweep / "1").symlink_to(outside)
    before = {p: p.stat().st_mtime_ns for p in outside.rglob("*")}
    code, out, exc = invoke("status", str(sweep))
    assert exc is None and code == 1, out
    assert "1 done, 1 failed" in out
    from cobelrun.io.sweep_folder import job_rows

    row = job_rows(sweep, write=False)[1]  # the table folds long errors: read the row
    assert row["status"] == "failed" and "not a folder of the sweep" in row["error"]
    assert {p: p.stat().st_mtime_ns for p in outside.rglob("*")} == before


def test_collect_leaves_out_a_job_whose_table_is_cut_short(real_sweep, tmp_path):
    """A job whose table has no footer is not done (`cobel status` says failed), so collect
    takes the other job and says one was left out."""
    import pandas as pd

    sweep = copy_folder(real_sweep, tmp_path / "sweep")
    (sweep / "1" / "steps.parquet").write_bytes(b"PAR1" + b"\0" * 100 + b"PAR1")
    code, out, exc = invoke("collect", str(sweep))
    assert exc is None and code == 0, out
    assert "collected 1 of 2 jobs" in out
    assert set(pd.read_parquet(sweep / "collected" / "steps.parquet")["job"]) == {0}


def test_collect_refuses_a_table_with_a_damaged_page(real_sweep, tmp_path):
    """The footer intact, a byte of the data changed: the page checksum catches it, one line
    naming the file, and no collected file or temporary file is left."""
    import pyarrow.parquet as pq

    sweep = copy_folder(real_sweep, tmp_path / "sweep")
    path = sweep / "1" / "steps.parquet"
    col = pq.read_metadata(path).row_group(0).column(0)
    raw = bytearray(path.read_bytes())
    raw[col.data_page_offset + col.total_compressed_size - 3] ^= 0xFF
    path.write_bytes(bytes(raw))
    line = one_error_line(*invoke("collect", str(sweep)), "steps.parquet")
    assert "is damaged" in line
    assert not list((sweep / "collected").glob("*steps*"))


def test_load_manifest_and_plot_refuse_a_manifest_of_wrong_types(real_run, tmp_path):
    from cobelrun.errors import CobelError
    from cobelrun.results import load_manifest

    run = copy_folder(real_run, tmp_path / "run")
    edit_json("manifest.json", lambda d: {**d, "started_at": "yesterday"})(run)
    with pytest.raises(CobelError, match=r"manifest.json: started_at: .*ISO 8601"):
        load_manifest(run)


def test_resuming_a_sweep_never_clears_a_job_folder_that_links_elsewhere(real_sweep, tmp_path):
    """`cobel run -m` again on a sweep whose job folder was replaced by a link: refused in one
    line, and the folder the link points to keeps every file (a rerun clears a job's outputs)."""
    import shutil

    from tests.faults.folders import TINY, _cobel

    sweep = copy_folder(real_sweep, tmp_path / "sweep")
    outside = copy_folder(sweep / "1", tmp_path / "elsewhere")
    (outside / ".done").unlink()  # not done: a resume would clear it and run it again
    shutil.rmtree(sweep / "1")
    (sweep / "1").symlink_to(outside)
    before = sorted(p.name for p in outside.iterdir())
    proc = _cobel(tmp_path, "run", "-m", "--quiet", *TINY, "seed=0,1",
                  f"hydra.sweep.dir={sweep}", "hydra/launcher=basic")  # fmt: skip
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr
    assert "is a link or a file, not a folder of the sweep" in proc.stderr
    assert sorted(p.name for p in outside.iterdir()) == before


def test_status_finds_a_flipped_byte_in_a_table(real_run, tmp_path):
    """cobel writes a CRC-32 per Parquet page: a byte changed inside the data (the footer
    intact) is found by `cobel status`, and the readers refuse the table in one line."""
    import pyarrow.parquet as pq

    run = copy_folder(real_run, tmp_path / "run")
    path = run / "trials.parquet"
    col = pq.read_metadata(path).row_group(0).column(0)
    raw = bytearray(path.read_bytes())
    raw[col.data_page_offset + col.total_compressed_size - 3] ^= 0xFF  # inside the first page
    path.write_bytes(bytes(raw))
    code, out, exc = invoke("status", str(run))
    assert exc is None and code == 1, out
    assert "completed, but damaged" in out and "trials.parquet: its data is damaged" in out
    line = one_error_line(*invoke("plot", str(run), "--kind", "latency"), "trials.parquet")
    assert "cannot read" in line


def test_sweep_job_with_a_truncated_table_is_not_done(real_sweep, tmp_path):
    sweep = copy_folder(real_sweep, tmp_path / "sweep")
    truncate("trials.parquet")(sweep / "0")
    code, out, exc = invoke("status", str(sweep))
    assert exc is None and code == 1, out
    assert "1 done, 1 failed" in out
    from cobelrun.io.sweep_folder import job_rows

    row = job_rows(sweep, write=False)[0]
    assert row["status"] == "failed" and "trials.parquet is not a readable" in row["error"]


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("[" * 100_000 + "]" * 100_000, "nests deeper than 200 levels"),  # RecursionError before
        ('{"status": NaN}', "NaN is not valid JSON"),
        ("", "not valid JSON"),
        ("\xff\xfe", "not UTF-8"),
    ],
)
def test_json_files_are_bounded_before_parsing(tmp_path, text, words):
    from cobelrun.errors import CobelError
    from cobelrun.io.validate import read_manifest

    path = tmp_path / "manifest.json"
    path.write_bytes(text.encode("latin-1") if text.startswith("\xff") else text.encode())
    with pytest.raises(CobelError, match=words):
        read_manifest(path)
