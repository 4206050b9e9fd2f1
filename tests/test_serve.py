"""``cobel serve``: the dashboard's data layer, its one-line errors, and the page in a real
headless Chromium (selenium): the folder list, a run's page with its figures, and a running
run's curve growing as the recorder's writer adds parts.

The browser tests need Debian's ``chromium`` and ``chromium-driver`` (``.ci/run`` installs
them) and are skipped, saying so, where they are absent. Set ``COBEL_DOCS_SCREENSHOTS=1`` to
write the screenshots into ``docs/img/`` (the "Seeing a run" page shows them).
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pytest

import cobelrun
from cobelrun.errors import CobelError
from cobelrun.io.parquet import PartedTableWriter
from cobelrun.io.run_folder import RunFolder
from cobelrun.web import data
from tests.webpages import free_port, headless_chromium, web_command

REPO = Path(__file__).resolve().parents[1]
DOCS_IMG = REPO / "docs" / "img"


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A results folder: a finished tiny T-maze run and a running copy with half its trials
    in parts (the recorder's writer, :class:`PartedTableWriter`)."""
    root = tmp_path_factory.mktemp("results")
    done = cobelrun.run("tmaze_extinction", ["task.runs=2", "seed=3"], out=root / "tmaze" / "done")
    live = root / "tmaze" / "live"
    live.mkdir()
    folder = RunFolder(done.path)
    shutil.copy(folder.world, live / "world.json")
    manifest = (folder.manifest).read_text().replace('"status": "completed"', '"status": "running"')
    (live / "manifest.json").write_text(manifest)
    # a real two-job sweep (agent.epsilon swept), through the CLI as a user starts one
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    sweep = subprocess.run(
        [sys.executable, "-c", "from cobelrun.cli import main; main()", "run", "-m",
         "hydra/launcher=basic", "task=tmaze_extinction", "agent.epsilon=0.1,0.5",
         "task.runs=2", "task.protocol.phases.0.trials=10", "task.protocol.phases.1.trials=10",
         f"hydra.sweep.dir={root / 'sweep'}"],
        env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert sweep.returncode == 0, sweep.stderr[-2000:]
    return root


def _live_writer(root: Path) -> tuple[PartedTableWriter, pd.DataFrame]:
    live = RunFolder(root / "tmaze" / "live")
    trials = cobelrun.load(root / "tmaze" / "done").trials
    schema = pa.Schema.from_pandas(trials, preserve_index=False)
    w = PartedTableWriter(live.table("trials"), live.parts("trials"), schema)
    return w, trials


# -- data layer (no browser) ------------------------------------------------------------------
def test_scan_lists_runs_with_status_task_seed_overrides(results: Path) -> None:
    rows = {f.rel: f for f in data.scan(results)}
    assert set(rows) == {"tmaze/done", "tmaze/live", "sweep"}
    assert rows["sweep"].kind == "sweep" and rows["sweep"].swept == ["agent.epsilon"]
    assert rows["sweep"].jobs == 2
    done = rows["tmaze/done"]
    assert (done.kind, done.status, done.task, done.seed) == (
        "run",
        "completed",
        "tmaze_extinction",
        3,
    )
    assert done.duration_s is not None and done.duration_s > 0
    assert rows["tmaze/live"].status == "running"


def test_overrides_leave_out_hydra_keys() -> None:
    cmd = ["cobel", "run", "task=x", "seed=2", "hydra.run.dir=/tmp/a", "-m"]
    assert data.overrides_of(cmd) == ["task=x", "seed=2"]


def test_live_curve_reads_parts_then_the_table(results: Path, tmp_path: Path) -> None:
    run = tmp_path / "r"
    run.mkdir()
    trials = cobelrun.load(results / "tmaze" / "done").trials
    folder = RunFolder(run)
    schema = pa.Schema.from_pandas(trials, preserve_index=False)
    w = PartedTableWriter(folder.table("trials"), folder.parts("trials"), schema)
    live = data.LiveCurve(run)
    assert live.trials().empty
    first = trials[trials["trial"] <= 50]
    w.write_part(pa.Table.from_pandas(first, schema=schema, preserve_index=False))
    assert len(data.curve_points(live.trials(), "steps")) == 50
    rest = trials[trials["trial"] > 50]
    w.write_part(pa.Table.from_pandas(rest, schema=schema, preserve_index=False))
    w.close()  # parts merged into trials.parquet and removed
    assert not folder.parts("trials").exists()
    pts = data.curve_points(live.trials(), "steps")
    assert len(pts) == trials["trial"].nunique()
    expected = trials.groupby("trial")["steps"].mean()
    assert pts[10][1] == pytest.approx(expected.loc[pts[10][0]])


def test_resolve_refuses_paths_outside_the_results_folder(results: Path) -> None:
    assert data.resolve(results, "tmaze/done") == (results / "tmaze" / "done").resolve()
    with pytest.raises(CobelError, match="not inside the results folder"):
        data.resolve(results, "../..")


def test_not_a_results_folder_and_busy_port_are_one_line(results: Path, tmp_path: Path) -> None:
    from cobelrun.web.app import serve

    (tmp_path / "a" / "b").mkdir(parents=True)
    with pytest.raises(CobelError, match="is not a results folder"):
        serve(tmp_path / "a")
    with pytest.raises(CobelError, match="does not exist"):
        serve(tmp_path / "nope")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(CobelError, match=f"port {port} on 127.0.0.1 is in use"):
            serve(results, port=port)


# -- the page in Chromium ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def server(results: Path):
    port = free_port()
    yield from web_command(["serve", str(results), "--port", str(port)], port, stop_timeout=10)


@pytest.fixture(scope="module")
def browser():
    yield from headless_chromium(1400)


def _wait(driver, css: str, timeout: float = 20.0):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout).until(
        ec.presence_of_element_located((By.CSS_SELECTOR, css))
    )


def _wait_text(driver, css: str, pattern: str, timeout: float = 20.0) -> str:
    from selenium.webdriver.common.by import By

    deadline = time.monotonic() + timeout
    text = ""
    while time.monotonic() < deadline:
        els = driver.find_elements(By.CSS_SELECTOR, css)
        text = els[0].text if els else ""
        if re.search(pattern, text):
            return text
        time.sleep(0.2)
    raise AssertionError(f"{css} never matched {pattern!r}; last text {text!r}")


def _shot(driver, name: str) -> None:
    if os.environ.get("COBEL_DOCS_SCREENSHOTS") == "1":
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(DOCS_IMG / name))


def test_page_loads_nothing_from_outside(server: str) -> None:
    import urllib.request

    for page in ("/", "/run?p=tmaze/done"):
        html = urllib.request.urlopen(server + page, timeout=10).read().decode()
        outside = re.findall(r"""(?:src|href)\s*=\s*["'](https?:)?//[^"']*""", html)
        outside += re.findall(r"""@import\s+url\(["']?(?:https?:)?//""", html)
        assert not outside, f"{page} loads from outside: {outside}"
        assert "/_nicegui/" in html  # the wheel's own scripts


def test_folder_list_and_opening_a_run(server: str, browser) -> None:
    from selenium.webdriver.common.by import By

    browser.get(server + "/")
    _wait(browser, ".cobel-folders")
    text = _wait_text(browser, ".cobel-folders", r"tmaze/done")
    assert "tmaze_extinction" in text and "completed" in text and "running" in text
    _shot(browser, "serve-index.png")
    link = next(a for a in browser.find_elements(By.CSS_SELECTOR, "a.cobel-folder-link")
                if a.text == "tmaze/done")  # fmt: skip
    link.click()
    _wait(browser, ".cobel-figure-task-figure img", timeout=60)
    _wait(browser, ".cobel-figure-occupancy img", timeout=60)
    _wait(browser, ".cobel-figure-policy img", timeout=60)  # what the agent learned
    imgs = browser.find_elements(By.CSS_SELECTOR, ".cobel-figure img")
    assert len(imgs) == 5  # task figure, trajectories, occupancy, value, policy
    for img in imgs:  # decoded PNGs with real pixels
        assert browser.execute_script("return arguments[0].naturalWidth", img) > 200
    assert _wait_text(browser, ".cobel-live-count", r"200 trials \(2 runs\)")
    _shot(browser, "serve-run.png")


def test_live_run_curve_grows(server: str, browser, results: Path) -> None:
    writer, trials = _live_writer(results)
    schema = writer.schema
    writer.write_part(pa.Table.from_pandas(trials[trials["trial"] <= 40], schema=schema,
                                           preserve_index=False))  # fmt: skip
    browser.get(server + "/run?p=" + "tmaze/live")
    first = _wait_text(browser, ".cobel-live-count", r"^40 trials")
    assert "2 runs" in first
    n_first = _chart_points(browser)
    assert n_first == 40
    writer.write_part(pa.Table.from_pandas(trials[(trials["trial"] > 40) & (trials["trial"] <= 120)],
                                           schema=schema, preserve_index=False))  # fmt: skip
    _wait_text(browser, ".cobel-live-count", r"^120 trials")
    assert _chart_points(browser) == 120
    _shot(browser, "serve-live.png")
    writer.close()


def _chart_points(driver) -> int:
    """Points of the live chart's line, read from ECharts in the page."""
    from selenium.webdriver.common.by import By

    deadline = time.monotonic() + 10
    n = -1
    while time.monotonic() < deadline:
        el = driver.find_element(By.CSS_SELECTOR, ".cobel-live-chart")
        n = driver.execute_script(
            "const v = getElement(arguments[0]);"  # NiceGUI's handle on the Vue component
            "return v && v.chart ? v.chart.getOption().series[0].data.length : -1;",
            el,
        )
        if n >= 0:
            return int(n)
        time.sleep(0.2)
    return int(n)


def test_sweep_curves_by_a_hue_chosen_in_the_page(server: str, browser) -> None:
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.common.by import By

    browser.get(server + "/sweep?p=sweep")
    img = _wait(browser, ".cobel-sweep-figure img[src^='data:image/png']", timeout=60)
    first = img.get_attribute("src")
    assert browser.execute_script("return arguments[0].naturalWidth", img) > 200
    assert "agent.epsilon" in browser.find_element(By.CSS_SELECTOR, ".cobel-hue").text
    _shot(browser, "serve-sweep.png")
    browser.find_element(By.CSS_SELECTOR, ".cobel-hue").click()  # the --hue menu
    option = next(o for o in _wait_all(browser, ".q-menu .q-item", timeout=30)
                  if o.text == "(none)")  # fmt: skip
    option.click()
    deadline = time.monotonic() + 90  # the figure is drawn on the server (a loaded CI core)
    while time.monotonic() < deadline:  # redrawn: one curve over both values
        try:
            img = browser.find_element(By.CSS_SELECTOR, ".cobel-sweep-figure img")
            if (
                img.get_attribute("src") not in ("", first)
                and "(none)" in browser.find_element(By.CSS_SELECTOR, ".cobel-hue").text
            ):
                break
        except StaleElementReferenceException:  # the page replaced it while we read it
            pass
        time.sleep(0.2)
    else:
        raise AssertionError("the sweep figure was not redrawn after choosing --hue (none)")


def _wait_all(driver, css: str, timeout: float = 10.0):
    from selenium.webdriver.common.by import By

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        els = driver.find_elements(By.CSS_SELECTOR, css)
        if els:
            return els
        time.sleep(0.1)
    raise AssertionError(f"nothing matches {css}")
