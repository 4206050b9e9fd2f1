"""A full disk in a sweep, ``cobel status``, ``cobel collect`` and ``cobel export nwb`` (issue
31, item 5, the "Full disk" cases): one line each, no traceback, and neither temporary files
(``.jobs.csv.PID.tmp``) nor 0-byte outputs left behind. A 2 MB tmpfs (root only) is filled to
the last few kilobytes before each command."""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.faults.conftest import mounted_tmpfs
from tests.faults.folders import TINY, _cobel, copy_folder, invoke


def fill(disk: Path, leave: int = 0) -> Path:
    """Fill ``disk`` until fewer than ``leave`` bytes are free."""
    filler = disk / "filler"
    with open(filler, "ab") as f:
        with contextlib.suppress(OSError):
            while True:
                st = os.statvfs(disk)
                free = st.f_bavail * st.f_frsize
                if free <= leave:
                    break
                f.write(bytes(min(1 << 16, max(4096, free - leave))))
                f.flush()
    return filler


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    with mounted_tmpfs(tmp_path / "disk", "2m") as d:
        yield d


def leftovers(root: Path) -> list[Path]:
    """Temporary files and 0-byte outputs under ``root``."""
    bad = [p for p in root.rglob("*") if p.is_file() and ".tmp" in p.name]
    bad += [p for p in root.rglob("*.nwb") if p.stat().st_size == 0]
    return bad


def one_line(code: int, out: str, exc: BaseException | None) -> str:
    assert exc is None, f"traceback: {exc!r}\n{out}"
    assert "Traceback" not in out, out
    errors = [ln for ln in out.splitlines() if ln.startswith("cobel: error:")]
    assert code != 0 and len(errors) == 1, out
    return errors[0]


def test_sweep_on_a_full_disk_fails_cleanly(disk, tmp_path):
    """Both jobs fail for want of space; the launcher reports them and exits 1, no traceback."""
    fill(disk, leave=48 << 10)
    proc = _cobel(tmp_path, "run", "-m", "--quiet", *TINY, "seed=0,1",
                  f"hydra.sweep.dir={disk / 'sweep'}", "hydra/launcher=basic")  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert "jobs failed" in proc.stderr or "disk is full" in proc.stderr, proc.stderr
    assert not leftovers(disk)


def test_status_and_collect_on_a_full_disk(disk, real_sweep):
    sweep = copy_folder(real_sweep, disk / "sweep")
    (sweep / "jobs.csv").unlink()
    fill(disk)
    code, out, exc = invoke("status", str(sweep))
    assert exc is None and code == 0, out  # the status is read from the job folders
    assert "cannot write to" in out and "disk is full" in out and "2 done" in out
    line = one_line(*invoke("collect", str(sweep)))
    assert "the disk is full" in line
    assert not leftovers(disk)
    assert not any((sweep / "collected").glob("*")) if (sweep / "collected").exists() else True


def test_export_nwb_on_a_full_disk(disk, real_run):
    pytest.importorskip("pynwb")
    run = copy_folder(real_run, disk / "run")
    fill(disk, leave=8 << 10)
    line = one_line(*invoke("export", "nwb", str(run)))
    assert "cannot write to" in line and ("disk is full" in line or "No space" in line)
    assert not leftovers(disk)
    assert not list((run / "nwb").glob("*.nwb")) if (run / "nwb").exists() else True


def test_a_permission_error_mid_run_is_called_a_permission_error(tmp_path, monkeypatch):
    """A run whose tables cannot be finished (EACCES: root ignores permissions, so the error is
    raised where the parts are merged) fails with one line that says "permission denied",
    names the parts it kept and the (quoted) command that merges them, and tells nobody to
    free space."""
    import shlex

    import cobelrun
    from cobelrun.errors import CobelError
    from cobelrun.io.parquet import PartedTableWriter

    def refuse(self, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(self.path))

    # the parts are written; finishing the tables from them is refused
    monkeypatch.setattr(PartedTableWriter, "_write_row_groups", refuse)
    out = tmp_path / "my results" / "run"
    with pytest.raises(CobelError) as err:
        cobelrun.run(None, list(TINY), out)
    msg = str(err.value)
    assert "permission denied" in msg and "free space" not in msg and "disk is full" not in msg
    assert "kept: parts of steps, trials" in msg
    assert f"cobel status {shlex.quote(str(out))}" in msg  # pastes into a shell


def test_next_commands_are_shell_quoted(tmp_path, real_run, capsys):
    """The commands printed after a run paste into a shell when the path has spaces."""
    import shlex

    from cobelrun.commands.summary import print_run_summary

    run = copy_folder(real_run, tmp_path / "my results" / "run 1")
    print_run_summary(run)
    err = capsys.readouterr().err
    lines = [ln.strip() for ln in err.splitlines() if ln.strip().startswith("cobel ")]
    assert len(lines) == 4, err
    for ln in lines:
        words = shlex.split(ln.split("    #")[0])
        assert str(run) in words, ln
