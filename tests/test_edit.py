"""``cobel edit``: the design and its checks (the code ``cobel run`` uses), saving configs that
compose to the drawn world (unknown keys and comments kept, nothing outside the folder), the
one-line refusals, and the page in a real headless Chromium (selenium): a plus-maze drawn from
the open field by clicking cells, saved, run with "run it" (latency falls); the built-in T-maze
loaded, its extinction goal shown, saved unchanged and composed to the same world.

The browser tests need Debian's ``chromium`` and ``chromium-driver`` and are skipped, saying so,
where they are absent. ``COBEL_DOCS_SCREENSHOTS=1`` writes their screenshots into ``docs/img/``
(the "Editing mazes" page shows them).
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cobelrun.envs.gridworld import GridWorldEnv
from cobelrun.errors import CobelError
from cobelrun.web import edit_config as ec
from cobelrun.web.grid_design import GridDesign, same_world
from tests import inprocess
from tests.webpages import free_port, headless_chromium, web_command

REPO = Path(__file__).resolve().parents[1]
DOCS_IMG = REPO / "docs" / "img"
cli = inprocess.cli  # fixture: cobel in this process


def _compose_world(folder: Path | None, env: str):
    from cobelrun.compose import composer
    from cobelrun.config import instantiate

    with composer(folder) as compose:
        cfg = compose([f"env={env}", "task=gridworld"])
    return instantiate("env", cfg.env).unwrapped.world


# -- the design (no browser) -----------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(ec.TEMPLATES))
def test_every_template_becomes_a_layout_of_the_same_world(name: str) -> None:
    from cobelrun.config import instantiate

    loaded = ec.load_template(name)
    built = instantiate("env.world", ec.plain(loaded.doc["world"]))
    assert same_world(loaded.design.world(), built)  # walls, doors, starts in order, places
    assert loaded.design.problems() == []


def test_problems_are_cobel_runs_messages_next_to_their_cells() -> None:
    design = ec.load_template("dyna_maze").design
    for r in range(6):  # a wall across column 6 cuts the goal (row 0, col 8) off
        design.paint("wall", (r, 6))
    (p,) = design.problems()
    assert p.message.startswith("goal state 8 (row 0, col 8) is unreachable from every start")
    assert p.cell == (0, 8)
    tmaze = ec.load_template("tmaze_paper").design
    assert tmaze.phase_names() == ["acquisition", "extinction"]
    tmaze.phases[1]["starts"] = [[2, 0]]  # a wall cell, from the extinction phase on
    (p,) = tmaze.problems()
    assert p.message == ("task.protocol phase 'extinction': starts: state 14 (row 2, col 0) is a "
                         "wall cell; starts must be free cells")  # fmt: skip
    assert (p.cell, p.phase) == ((2, 0), "extinction")


def test_the_env_is_checked_too_not_only_its_world() -> None:
    d = ec.load_template("blodgett_onehot").design  # DiscreteGridWorldEnv, observations kept
    d.env_extra["observations"] = [[0.0, 1.0]] * 40  # an (S, d) array for the 40 states
    assert d.problems() == []
    d.resize(4, 5)  # 20 states now: the array no longer fits, as cobel run would say
    (p,) = d.problems()
    assert p.message == "observations must have shape (S=20, d), got (40, 2); one row per state"


def test_phases_show_and_edit_the_extinction_goal() -> None:
    d = ec.load_template("tmaze_paper").design
    left, right = d.state(d.places["left_arm"]), d.state(d.places["right_arm"])
    acq, ext = d.phase_world(0), d.phase_world(1)
    assert (acq.rewards[right], acq.rewards[left]) == (1.0, 0.0)
    assert (ext.rewards[right], ext.rewards[left]) == (0.0, 1.0)
    d.paint("goal", d.places["left_arm"], value=2.5, phase=1)
    assert d.phases[1]["rewards"]["left_arm"] == 2.5  # by place name, as the protocol file
    assert d.phase_world(1).rewards[left] == 2.5 and d.world().rewards[left] == 0.0


def test_start_weights_are_start_probabilities() -> None:
    d = GridDesign.blank(3, 1)
    d.paint("start", (0, 2), weight=2)  # (0, 0) weight 1, (0, 2) weight 2
    assert d.start_probabilities() == {(0, 0): pytest.approx(1 / 3), (0, 2): pytest.approx(2 / 3)}
    env = GridWorldEnv(d.world())
    env.reset(seed=0)
    draws = [env.reset()[0] for _ in range(3000)]
    assert np.mean(np.array(draws) == 2) == pytest.approx(2 / 3, abs=0.03)
    d.paint("start", (0, 2), weight=1)  # lowered to 1
    assert d.starts.count((0, 2)) == 1
    d.paint("start", (0, 2), weight=1)  # the same weight again: no longer a start
    assert (0, 2) not in d.starts


def test_places_name_cells_that_phases_refer_to() -> None:
    d = ec.load_template("tmaze_paper").design
    d.paint("place", (0, 1), name="near_left")
    d.phases[1]["rewards"]["near_left"] = 0.5  # a phase refers to the new name
    assert d.phase_world(1).rewards[1] == 0.5 and d.world().places["near_left"] == 1
    d.paint("place", (0, 2), name="near_left")  # the name moves
    assert d.phase_world(1).rewards[2] == 0.5
    with pytest.raises(CobelError, match="place name '2x' is not valid"):
        d.paint("place", (0, 2), name="2x")
    d.paint("place", (0, 2), name="")  # dropped: the phase's reference is now cobel run's error
    assert "unknown place 'near_left'" in d.problems()[0].message


def test_one_way_doors_and_walls_block_the_moves_they_should() -> None:
    d = GridDesign.blank(3, 1)
    d.paint("door", (0, 0), side="right")  # 0 -> 1 blocked, 1 -> 0 open
    d.paint("edge", (0, 1), side="right")  # 1 <-> 2 blocked
    ns = d.world().next_state
    right, left = 2, 0
    assert (ns[0, right], ns[1, left], ns[1, right], ns[2, left]) == (0, 0, 1, 2)
    assert d.doors == {((0, 0), (0, 1))} and d.edges == {((0, 1), (0, 2))}
    again = GridDesign.from_world(d.world())
    assert (again.doors, again.edges) == (d.doors, d.edges)


def test_save_keeps_keys_and_comments_and_composes_to_the_drawn_world(tmp_path: Path) -> None:
    conf = tmp_path / "conf"
    (conf / "env").mkdir(parents=True)
    (conf / "env" / "mine.yaml").write_text(
        "# my maze: keep this comment\n"
        "_target_: cobelrun.envs.GridWorldEnv\n"
        "max_steps: 50   # a key the editor does not own\n"
        "world:\n"
        "  _target_: cobelrun.envs.world.from_layout\n"
        "  layout: |\n"
        "    S...\n"
        "    ...G\n"
        "  slip: 0.1     # kept too\n"
    )
    loaded = ec.load(conf, "mine")
    assert loaded.design.extra == {"slip": 0.1}
    assert ec.save(conf, "mine", loaded, loaded.design) == [conf / "env" / "mine.yaml"]
    assert (conf / "env" / "mine.yaml").read_text() == loaded.text  # unchanged: byte for byte
    d = loaded.design.copy()
    d.paint("wall", (0, 2))
    ec.save(conf, "mine", loaded, d)
    text = (conf / "env" / "mine.yaml").read_text()
    for kept in ("# my maze: keep this comment", "max_steps: 50   # a key the editor does not own",
                 "slip: 0.1     # kept too", "S.#."):  # fmt: skip
        assert kept in text
    composed = _compose_world(conf, "mine")
    assert same_world(composed, d.world()) and composed.next_state is None  # slip 0.1 kept


def test_refusals_are_one_line_and_write_nothing(tmp_path: Path) -> None:
    conf = tmp_path / "conf"
    loaded = ec.load_template("open_field")
    for bad in ("../evil", "a/b", "", "1abc", "x" * 70):
        with pytest.raises(CobelError, match="is not a valid config name"):
            ec.save(conf, bad, loaded, loaded.design)
    (conf / "env").mkdir(parents=True)
    (conf / "env" / "other.yaml").write_text("_target_: cobelrun.envs.TwoAFCEnv\n")
    with pytest.raises(CobelError, match="is not a gridworld env config"):
        ec.load(conf, "other")
    with pytest.raises(CobelError, match=r"other\.yaml exists; pick another name"):
        ec.save(conf, "other", loaded, loaded.design)
    big = "\n".join("." * 40 for _ in range(40))
    (conf / "env" / "big.yaml").write_text(
        "_target_: cobelrun.envs.GridWorldEnv\nworld:\n  _target_: cobelrun.envs.world.from_layout\n"
        "  layout: |\n" + "".join(f"    {row}\n" for row in big.splitlines())
    )
    with pytest.raises(CobelError, match=r"too large to edit comfortably.*edit its YAML"):
        ec.load(conf, "big")
    outside = tmp_path / "outside"
    outside.mkdir()
    (conf / "task").symlink_to(outside)  # a folder that leads out of the config folder
    with pytest.raises(CobelError, match="outside the config folder"):
        ec.save(conf, "mine", loaded, loaded.design, with_task=True)
    assert list(outside.iterdir()) == [] and not (conf / "env" / "mine.yaml").exists()
    d = loaded.design.copy()
    d.paint("wall", (0, 0))
    d.starts = [(0, 0)]  # a start inside a wall: cobel run's message, nothing written
    with pytest.raises(CobelError, match=r"not saved: .*row 0, col 0\) is a wall cell"):
        ec.save(conf, "mine", loaded, d)


def test_run_it_command_quotes_the_run_folder() -> None:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from cobelrun.web.editor import Editor

    editor = Editor(folder=Path("/tmp/conf"), results=Path("/tmp/results"))
    out = Path("/tmp/my results,a=b/it's")
    cmd = editor.run_command("plus_maze", "gridworld", out, 3)
    assert cmd[-6:-1] == ["-cd", "/tmp/conf", "task=gridworld", "env=plus_maze", "task.runs=3"]
    (override,) = OverridesParser.create().parse_overrides([cmd[-1]])
    assert override.key_or_group == "hydra.run.dir" and override.value() == str(out)


def test_run_it_overrides_go_before_the_run_folder() -> None:
    from cobelrun.web.editor import Editor

    editor = Editor(folder=Path("/tmp/conf"), results=Path("/tmp/results"))
    cmd = editor.run_command("g", "g", Path("/tmp/out"), 1, ["task.protocol.phases.0.trials=2"])
    assert cmd[-4:-1] == ["env=g", "task.runs=1", "task.protocol.phases.0.trials=2"]
    assert cmd[-1] == "hydra.run.dir='/tmp/out'"


def test_the_three_pages_share_one_scaffold() -> None:
    from cobelrun.web.arena_editor import ArenaPage
    from cobelrun.web.edit_page import EditPage
    from cobelrun.web.editor import Page
    from cobelrun.web.graph_editor import GraphPage

    shared = ("header", "load_rows", "tool_grid", "phase_rows", "save_panel", "change", "undo",
              "use", "save", "run_it", "export", "on_open", "on_load_template")  # fmt: skip
    for page in (Page, GraphPage, ArenaPage):
        assert issubclass(page, EditPage)
        assert not set(shared) & set(vars(page)), f"{page.__name__} writes out shared parts"
        for hook in ("load_template", "load_existing", "existing_names", "write", "figure",
                     "run_target", "refresh"):  # fmt: skip
            assert hook in vars(page), f"{page.__name__} lacks {hook}"


def test_cli_errors_are_one_line(cli, tmp_path: Path) -> None:
    r = cli("edit", "env=../../etc")
    assert r.returncode != 0 and "is not a valid config name" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = cli("edit", "env=bandit")  # neither a gridworld, a topology graph nor an arena
    assert r.returncode != 0 and "is not a gridworld env config" in r.stderr
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = cli("edit", "--port", str(port))
    assert r.returncode != 0 and f"port {port} on 127.0.0.1 is in use" in r.stderr


def test_export_png_and_svg() -> None:
    d = ec.load_template("blodgett_onehot").design
    png, svg = d.figure("png"), d.figure("svg")
    assert png.startswith(b"\x89PNG") and len(png) > 5000
    assert b"<svg" in svg[:500]
    assert d.svg().count('class="cobel-door"') == 6  # the six one-way doors


@pytest.mark.slow  # matplotlib draws 77 nodes and 196 edges: ~4 s
def test_graph_and_arena_export_draw_the_env() -> None:
    from cobelrun.web.arena_editor import load_arena
    from cobelrun.web.graph_design import GraphDesign
    from cobelrun.web.grid_design import geometry_figure

    graph = GraphDesign.from_env_config(
        ec.plain(ec.read_yaml(REPO / "conf/env/hex_3d.yaml")), "hex"
    )
    arena = load_arena(None, "arena").design
    for design in (graph, arena):
        assert geometry_figure(design.export_env(), "png").startswith(b"\x89PNG")
        assert b"<svg" in geometry_figure(design.export_env(), "svg")[:500]
    with pytest.raises(CobelError, match="export format 'gif' is unknown; allowed: png, svg"):
        geometry_figure(arena.export_env(), "gif")


# -- the page in Chromium ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("edit")


@pytest.fixture(scope="module")
def server(workdir: Path):
    port = free_port()
    yield from web_command(
        [
            "edit",
            "env=open_field",
            "-cd",
            str(workdir / "conf"),
            "--port",
            str(port),
            "--results",
            str(workdir / "results"),
        ],
        port,
        cwd=workdir,
    )


@pytest.fixture(scope="module")
def browser():
    yield from headless_chromium(1500)


def _wait_text(driver, css: str, pattern: str, timeout: float = 20.0) -> str:
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.common.by import By

    deadline = time.monotonic() + timeout
    text = ""
    while time.monotonic() < deadline:
        try:
            text = " | ".join(e.text for e in driver.find_elements(By.CSS_SELECTOR, css))
        except StaleElementReferenceException:  # redrawn while read: read again
            continue
        if re.search(pattern, text):
            return text
        time.sleep(0.1)
    raise AssertionError(f"{css} never matched {pattern!r}; last text {text!r}")


def _cell(driver, r: int, c: int):
    from selenium.webdriver.common.by import By

    return driver.find_element(By.CSS_SELECTOR, f"rect.cobel-cell[data-r='{r}'][data-c='{c}']")


def _click_cell(driver, r: int, c: int, kind: str | None = None) -> None:
    """Click a cell, then wait until the page has redrawn it (as ``kind``, if given)."""
    from selenium.common.exceptions import StaleElementReferenceException

    for _ in range(50):  # the grid is redrawn after every change: find the cell afresh
        try:
            _cell(driver, r, c).click()
            break
        except StaleElementReferenceException:
            time.sleep(0.05)
    deadline = time.monotonic() + 10
    while kind is not None and time.monotonic() < deadline:
        try:
            if f"cobel-{kind}" in (_cell(driver, r, c).get_attribute("class") or ""):
                return
        except StaleElementReferenceException:
            pass
        time.sleep(0.05)
    if kind is not None:
        raise AssertionError(f"cell ({r}, {c}) did not become a {kind} cell")


def _fill(driver, css: str, text: str) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    box = driver.find_element(By.CSS_SELECTOR, f"{css} input")
    box.send_keys(Keys.CONTROL, "a")
    box.send_keys(text)
    box.send_keys(Keys.TAB)


def _press(driver, css: str) -> None:
    """Click the element ``css`` matches, found afresh until the click lands."""
    from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException
    from selenium.webdriver.common.by import By

    for _ in range(100):
        try:
            driver.find_element(By.CSS_SELECTOR, css).click()
            return
        except (StaleElementReferenceException, NoSuchElementException):
            time.sleep(0.05)
    raise AssertionError(f"could not click {css}")


def _shot(driver, name: str) -> None:
    if os.environ.get("COBEL_DOCS_SCREENSHOTS") == "1":
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(DOCS_IMG / name))


def _attr(driver, css: str, name: str) -> str:
    """An attribute of the element ``css`` matches, found afresh (the SVG is redrawn after
    every change, so an element found a moment ago may be gone)."""
    from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException
    from selenium.webdriver.common.by import By

    for _ in range(100):
        try:
            return driver.find_element(By.CSS_SELECTOR, css).get_attribute(name) or ""
        except (StaleElementReferenceException, NoSuchElementException):
            time.sleep(0.05)
    raise AssertionError(f"{css} kept changing or never appeared")


def _fill_text(driver, cell: str) -> str:
    r, c = cell.split(",")
    return _attr(driver, f"rect.cobel-cell[data-r='{r}'][data-c='{c}']", "fill")


def test_page_loads_nothing_from_outside(server: str) -> None:
    import urllib.request

    html = urllib.request.urlopen(server + "/", timeout=10).read().decode()
    outside = re.findall(r"""(?:src|href)\s*=\s*["'](https?:)?//[^"']*""", html)
    assert not outside, f"the editor loads from outside: {outside}"
    assert "/_nicegui/" in html


def test_draw_a_plus_maze_and_save(server: str, browser, workdir: Path) -> None:

    browser.get(server + "/")
    _wait_text(browser, ".cobel-origin", "template open_field")
    _fill(browser, ".cobel-width", "5")
    _fill(browser, ".cobel-height", "5")
    _press(browser, ".cobel-resize")
    _wait_text(browser, ".cobel-info", r"^5 x 5 cells")
    _press(browser, ".cobel-tool-wall")
    corners = [(r, c) for r in (0, 1, 3, 4) for c in (0, 1, 3, 4)]
    for r, c in corners:  # a plus: the middle row and column stay open
        _click_cell(browser, r, c, "wall")
    _fill(browser, ".cobel-value", "1")
    _press(browser, ".cobel-tool-goal")
    _click_cell(browser, 0, 2)  # the north arm's end pays 1 and ends the trial
    _wait_text(browser, ".cobel-yaml", r"G")
    _press(browser, ".cobel-tool-start")  # one start: the south arm's end (the template's
    _click_cell(browser, 4, 2)  # top-left start is walled in; its goal went with the resize)
    _wait_text(browser, ".cobel-info", r"start probabilities: \(4,2\) 1\.00;")
    _wait_text(browser, ".cobel-ok", "no problems")
    yaml_text = _wait_text(browser, ".cobel-yaml", "##G##")
    assert "##.##\n....." in yaml_text.replace(" | ", "\n") or "....." in yaml_text
    _shot(browser, "edit-plus-maze.png")
    # a wall across the north arm: cobel run's message next to the goal cell
    _press(browser, ".cobel-tool-wall")
    _click_cell(browser, 1, 2, "wall")
    msg = _wait_text(browser, ".cobel-problem-at", r"goal state 2 \(row 0, col 2\) is unreachable")
    assert "open a path or move it" in msg
    _shot(browser, "edit-problem.png")
    _press(browser, ".cobel-undo")
    _wait_text(browser, ".cobel-ok", "no problems")
    _fill(browser, ".cobel-name", "plus_maze")
    _press(browser, ".cobel-save")
    _wait_text(browser, ".cobel-status", r"saved .*env/plus_maze\.yaml")
    world = _compose_world(workdir / "conf", "plus_maze")  # as cobel run -cd DIR composes it
    assert world.reachable().sum() == 9 and world.starts.tolist() == [22]
    assert world.rewards[2] == 1.0 and world.terminal[2]
    assert same_world(world, _plus_maze().world())


def _plus_maze() -> GridDesign:
    """The plus-maze the browser test draws, painted with the same calls its clicks make."""
    d = ec.load_template("open_field").design
    d.resize(5, 5)
    for r, c in [(r, c) for r in (0, 1, 3, 4) for c in (0, 1, 3, 4)]:
        d.paint("wall", (r, c))
    d.paint("goal", (0, 2), value=1.0)
    d.paint("start", (4, 2))
    return d


@pytest.mark.slow
def test_run_it_runs_the_maze_and_it_learns(server: str, browser, workdir: Path) -> None:
    from selenium.webdriver.common.by import By

    import cobelrun

    conf = workdir / "conf"
    loaded = ec.load_template("open_field")
    ec.save(conf, "plus_run", loaded, _plus_maze())
    browser.get(server + "/?env=plus_run")
    _wait_text(browser, ".cobel-origin", "env/plus_run.yaml")
    _press(browser, ".cobel-run")  # saves, then cobel run -cd DIR task=gridworld env=plus_run
    status = _wait_text(browser, ".cobel-run-status", r"^(finished|failed)", timeout=240)
    assert status.startswith("finished"), status
    link = _wait_text(browser, ".cobel-dashboard", r"dashboard", timeout=30)
    assert "/run?p=edit/plus_run/" in link
    href = browser.find_element(By.CSS_SELECTOR, ".cobel-dashboard").get_attribute("href")
    assert href.startswith("http://127.0.0.1:") and "/run?p=edit/plus_run/" in href
    _shot(browser, "edit-run-it.png")
    run_dir = Path(re.search(r"-> (\S+)$", status).group(1))
    trials = cobelrun.load(run_dir).trials
    assert trials["run"].nunique() == 3
    steps = trials.groupby("trial")["steps"].mean()  # escape latency over the 3 runs
    first, last = steps.iloc[:2].mean(), steps.iloc[-20:].mean()
    assert last < 0.5 * first and last < 8  # falls towards the 4-step shortest path


def test_load_the_tmaze_see_extinction_save_unchanged(server: str, browser, workdir: Path) -> None:
    from selenium.webdriver.common.by import By

    browser.get(server + "/")
    _wait_text(browser, ".cobel-origin", "template")
    _press(browser, ".cobel-template")
    option = next(o for o in _wait_all(browser, ".q-menu .q-item")
                  if o.text.startswith("T-maze (paper"))  # fmt: skip
    option.click()
    _press(browser, ".cobel-load-template")
    _wait_text(browser, ".cobel-origin", "template tmaze_paper")
    left, right = "0,0", "0,6"
    assert _fill_text(browser, right) == "#fac83c" and _fill_text(browser, left) == "#f0bebe"
    _press(browser, ".cobel-phase")
    option = next(o for o in _wait_all(browser, ".q-menu .q-item") if "extinction" in o.text)
    option.click()  # the extinction phase: the reward moved to the left arm
    deadline = time.monotonic() + 10
    while _fill_text(browser, left) != "#fac83c" and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _fill_text(browser, left) == "#fac83c" and _fill_text(browser, right) == "#f0bebe"
    _shot(browser, "edit-tmaze-extinction.png")
    _fill(browser, ".cobel-name", "tmaze_copy")
    browser.find_element(By.CSS_SELECTOR, ".cobel-with-task").click()
    _press(browser, ".cobel-save")
    _wait_text(browser, ".cobel-status", r"saved .*env/tmaze_copy\.yaml, .*task/tmaze_copy\.yaml")
    conf = workdir / "conf"
    assert same_world(_compose_world(conf, "tmaze_copy"), _compose_world(None, "tmaze_paper"))
    from cobelrun.compose import composer

    with composer(conf) as compose:
        mine = compose(["task=tmaze_copy"])
    with composer(None) as compose:
        theirs = compose(["task=tmaze_extinction"])
    assert mine.task.protocol == theirs.task.protocol and mine.agent == theirs.agent
    # a per-phase change: 50 extinction trials and the left arm paying 2, saved with the task
    _fill(browser, ".cobel-trials", "50")
    _fill(browser, ".cobel-value", "2")
    _press(browser, ".cobel-tool-goal")
    _click_cell(browser, 0, 0)
    _wait_text(browser, ".cobel-phase-hint", r"sets rewards right_arm: 0.0, left_arm: 2.0")
    _press(browser, ".cobel-save")  # the status line reads as after the first save: watch the file
    task_file, deadline = conf / "task" / "tmaze_copy.yaml", time.monotonic() + 20
    while "trials: 50" not in task_file.read_text():
        assert time.monotonic() < deadline, "the edited phase was not saved"
        time.sleep(0.1)
    with composer(conf) as compose:
        mine = compose(["task=tmaze_copy"])
    ext = mine.task.protocol.phases[1]
    assert (ext.name, ext.trials, ext.rewards.left_arm) == ("extinction", 50, 2.0)
    assert mine.task.protocol.phases[0] == theirs.task.protocol.phases[0]


def _wait_all(driver, css: str, timeout: float = 10.0):
    from selenium.webdriver.common.by import By

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        els = driver.find_elements(By.CSS_SELECTOR, css)
        if els:
            return els
        time.sleep(0.1)
    raise AssertionError(f"nothing matches {css}")


# -- topology graphs ----------------------------------------------------------------------------
def test_hex_graph_as_a_manual_topology_is_the_same_graph() -> None:
    from cobelrun.config import instantiate
    from cobelrun.web.graph_editor import load_graph_template

    g = load_graph_template("hex_3d").design
    assert (len(g.nodes), len(g.edges), g.n_directions) == (77, 196, 6)
    assert g.rewards == {38: 1.0} and g.terminals == {38} and g.starts == "all"
    manual = instantiate("env.topology", g.topology_node())
    hexagonal = instantiate("env.topology", {"_target_": "cobelrun.envs.topology.hexagonal",
                                             "width": 9, "height": 9})  # fmt: skip
    assert np.array_equal(manual.neighbours, hexagonal.neighbours)
    assert manual.places == hexagonal.places and g.problems() == []


def test_graph_edits_renumber_and_unreachable_goals_are_named() -> None:
    from cobelrun.web.graph_editor import load_graph_template

    g = load_graph_template("grid").design  # 5 x 5, start 0, goal 24
    assert g.problems() == []
    for e in [(19, 24), (23, 24)]:
        g.toggle_edge(*e)
    assert g.problems() == ["goal node 24 is unreachable from every start; add an edge to it"]
    g.toggle_edge(23, 24)
    g.remove_node(0)  # the start goes, everything after it moves down one
    assert g.rewards == {23: 1.0} and g.terminals == {23} and g.starts == []
    assert g.problems() == ["starts: at least one start node is needed"]  # TopologyEnv's message
    i = g.add_node(-1.2, 3.9)  # snapped to the grid
    assert g.nodes[i] == (-1.0, 4.0) and g.add_node(-0.9, 4.1) == i


def test_graph_save_keeps_keys_and_comments(tmp_path: Path) -> None:
    from cobelrun.web.graph_editor import load_graph, load_graph_template, save_graph

    conf = tmp_path / "conf"
    loaded = load_graph_template("hex_3d")
    (path,) = save_graph(conf, "hex_copy", loaded, loaded.design)
    assert path.read_text() == loaded.text  # unchanged: the built-in file as it is
    d = loaded.design.copy()
    d.paint("goal", 0, 2.0)
    save_graph(conf, "hex_copy", load_graph(conf, "hex_copy"), d)
    text = path.read_text()
    assert "cobelrun.envs.topology.manual" in text and "fov: 240" in text
    assert "# Fig. 8: 12 x 48 x 3 panorama" in text  # comments of kept keys stay
    again = load_graph(conf, "hex_copy").design
    assert again.rewards == {0: 2.0, 38: 1.0} and again.extra == d.extra


@pytest.mark.slow
def test_agents_view_is_the_runs_camera(tmp_path: Path, monkeypatch) -> None:
    from cobelrun.web.graph_editor import load_graph_template

    monkeypatch.setenv("COBEL_CACHE", str(tmp_path / "no_cache"))
    d = load_graph_template("hex_3d").design
    img, source = d.preview(38, 90.0)  # no render cache: the run's camera, rendered by pybullet
    assert img.shape == (12, 48, 3) and img.dtype == np.uint8 and img.std() > 5
    assert source.startswith("rendered with pybullet (no render cache for this scene and camera")


def _plant_cache(design, cache_dir: Path) -> np.ndarray:
    """A render cache for ``design``'s camera in ``cache_dir`` whose every view is a flat
    colour (node * 10 + heading), written in the cache's format (``pybullet-<version>.npy``
    and its per-node CRC-32 checksums), so a preview that reads it can be told apart from a
    rendered one."""
    import json

    from cobelrun.render import cache
    from cobelrun.render.scene import pybullet_version

    request = design.cache_request()
    n, k, cam = request.n_nodes, request.n_directions, request.camera
    images = np.zeros((n, k, cam.height, cam.width, 3), np.uint8)
    images[:] = (np.arange(n)[:, None] * 10 + np.arange(k)[None, :])[..., None, None, None]
    folder = request.folder()
    folder.mkdir(parents=True)
    path = folder / f"pybullet-{pybullet_version() or '0'}.npy"
    np.save(path, images)
    Path(f"{path}.crc32.json").write_text(
        json.dumps({"block": "node", "crc32": cache.block_checksums(images)})
    )
    assert cache.locate(request) == path
    return images


def test_view_preview_reads_the_render_cache(tmp_path: Path) -> None:
    from cobelrun.web.graph_editor import load_graph_template

    d = load_graph_template("grid").design  # 5 x 5 nodes, 4 headings
    d.extra["observation"].update(height=6, width=8, cache_dir=str(tmp_path / "cache"))
    images = _plant_cache(d, tmp_path / "cache")
    img, source = d.preview(12, 180.0)  # heading index 2 (0, 90, 180, 270 degrees)
    assert img.shape == (6, 8, 3) and (img == 122).all()  # the cache's image, its size
    assert np.array_equal(img, images[12, 2])
    assert source.startswith("read from the render cache ") and str(tmp_path / "cache") in source
    # the key is the run's: a cache cobel render-cache built for the built-in hex_3d is found
    from cobelrun.config import instantiate

    hexd = load_graph_template("hex_3d").design
    env = instantiate("env", ec.plain(ec.read_yaml(REPO / "conf/env/hex_3d.yaml")))
    assert hexd.cache_request().key() == env.unwrapped.observation_module.cache_request().key()
    hexd.toggle_edge(0, 1)  # an edited graph is saved as a manual topology: another scene
    assert hexd.cache_request().key() != env.unwrapped.observation_module.cache_request().key()


# -- per-phase variants of graphs and arenas --------------------------------------------------
def test_graph_phases_change_goals_and_starts_and_go_into_the_task(tmp_path: Path) -> None:
    from cobelrun.compose import composer
    from cobelrun.web.graph_editor import (
        load_graph,
        load_graph_template,
        quick_overrides,
        save_graph,
    )

    loaded = load_graph_template("grid")  # its DQN task: one training phase of 200 trials
    d = loaded.design
    assert d.phase_names() == ["training"] and d.phase_state(0)[:2] == ({24: 1.0}, {24})
    d.phases.append({"name": "moved", "trials": 50})
    d.paint("clear", 24, phase=1)  # the goal moves to node 20 from the second phase on
    d.paint("goal", 20, 2.0, phase=1)
    d.paint("start", 4, phase=1)
    assert d.phases[1] == {"name": "moved", "trials": 50, "rewards": {24: 0.0, 20: 2.0},
                           "terminals": {24: False, 20: True}, "starts": [0, 4]}  # fmt: skip
    assert d.phase_state(1) == ({20: 2.0}, {20}, {0, 4})
    assert d.phase_state(0)[:2] == ({24: 1.0}, {24}) and d.rewards == {24: 1.0}  # env as built
    fill = r'data-node="{}"[^>]*fill="(#\w+)"'
    assert re.search(fill.format(20), d.svg(phase=1)).group(1) == "#fac83c"  # pays, ends
    assert re.search(fill.format(24), d.svg(phase=1)).group(1) == "#ffffff"  # no longer
    assert re.search(fill.format(24), d.svg(phase=0)).group(1) == "#fac83c"
    d.toggle_edge(15, 20)
    d.toggle_edge(20, 21)  # node 20 (the bottom-left corner) cut off: the phase paying there
    assert d.problems() == ["task.protocol phase 'moved': goal node 20 is unreachable from "
                            "every start; add an edge to it"]  # fmt: skip
    d.toggle_edge(20, 21)
    conf = tmp_path / "conf"
    written = save_graph(conf, "moving", loaded, d, with_task=True)
    assert written == [conf / "env" / "moving.yaml", conf / "task" / "moving.yaml"]
    with composer(conf) as compose:
        cfg = compose(["task=moving", *quick_overrides(d.phases, 5)])
    phases = cfg.task.protocol.phases
    assert [(p.name, p.trials) for p in phases] == [("training", 5), ("moved", 5)]
    assert dict(phases[1].rewards) == {20: 2.0} | {24: 0.0} and list(phases[1].starts) == [0, 4]
    assert cfg.agent._target_.endswith("DQNAgent") or "dqn" in str(cfg.agent).lower()
    again = load_graph(conf, "moving").design
    assert again.phases == d.phases and again.rewards == {24: 1.0}


def test_arena_phase_moves_the_platform_and_saves_it_in_the_task(tmp_path: Path) -> None:
    from cobelrun.compose import composer
    from cobelrun.config import instantiate
    from cobelrun.protocol import Protocol
    from cobelrun.web.arena_editor import load_arena, save_arena

    loaded = load_arena(None, "water_maze")
    d = loaded.design
    rev = d.phase_names().index("reversal")
    # the reversal platform switched off, a new one in the SE quadrant switched on instead
    assert d.paint_phase("goal", -0.42, -0.42, rev) == "phase reversal: goal platform_reversal off"
    assert d.paint_phase("goal", 0.42, -0.42, rev, radius=0.05) == "phase reversal: goal goal_0 on"
    assert d.node["goals"]["goal_0"] == {"shape": "circle", "x": 0.42, "y": -0.42, "radius": 0.05,
                                         "reward": 0.0, "terminal": False}  # fmt: skip
    d.paint_phase("start", 0.0, 0.95, rev, tol=0.05)  # north no longer a start of the reversal
    d.paint_phase("start", 0.5, 0.0, rev)  # a point start
    assert d.phases[rev]["starts"] == ["east", "south", "west", [0.5, 0.0]]
    assert d.problems() == []
    goals = d.phase_env(rev).unwrapped.arena.goals
    assert (goals["goal_0"].reward, goals["goal_0"].terminal) == (1.0, True)
    assert (goals["platform_reversal"].reward, goals["platform_reversal"].terminal) == (0, False)
    assert d.phase_env(0).unwrapped.arena.goals["goal_0"].reward == 0.0  # off before the reversal
    with pytest.raises(CobelError, match="the obstacle tool edits the env, not a phase"):
        d.paint_phase("obstacle", 0.0, 0.0, rev)
    conf = tmp_path / "conf"
    save_arena(conf, "pool", loaded, d, with_task=True)
    with composer(conf) as compose:
        cfg = compose(["task=pool"])
    proto = cfg.task.protocol
    assert [p.name for p in proto.phases] == ["acquisition", "probe", "reversal"]
    assert dict(proto.phases[2].rewards) == {"platform": 0.0, "platform_reversal": 0.0,
                                             "goal_0": 1.0}  # fmt: skip
    env = instantiate("env", cfg.env)
    from omegaconf import OmegaConf

    protocol = Protocol.from_config(OmegaConf.to_container(proto))
    for p in protocol.phases:
        protocol.apply(p, env)  # as the run applies them: the new platform pays in the reversal
    assert env.unwrapped.arena.goals["goal_0"].reward == 1.0
    assert load_arena(conf, "pool").design.phases == d.phases


def test_arena_start_heading_is_the_envs_and_drawn(tmp_path: Path) -> None:
    from cobelrun.compose import composer
    from cobelrun.config import instantiate
    from cobelrun.web.arena_editor import load_arena, save_arena

    loaded = load_arena(None, "arena")  # start_heading not given: the env's "centre"
    d = loaded.design
    assert d.start_heading() == "centre"
    (arrow,) = re.findall(r'class="cobel-heading" data-deg="([-\d.]+)"', d.svg())
    assert float(arrow) == pytest.approx(45.0)  # from (0.15, 0.15) towards the centre (0.5, 0.5)
    d.set_start_heading(-90)
    assert d.node["start_heading"] == 270
    (arrow,) = re.findall(r'class="cobel-heading" data-deg="([-\d.]+)"', d.svg())
    assert float(arrow) == pytest.approx(270.0)
    with pytest.raises(CobelError, match="start heading must be an angle in degrees, 'random' "
                       "or 'centre', got 'north'"):  # fmt: skip
        d.set_start_heading("north")
    conf = tmp_path / "conf"
    save_arena(conf, "facing", loaded, d)
    assert "start_heading: 270\n" in (conf / "env" / "facing.yaml").read_text()
    with composer(conf) as compose:
        cfg = compose(["env=facing", "task=morris_water_maze"])
    assert cfg.env.start_heading == 270
    instantiate("env", cfg.env)  # the env takes it (a start then faces -y)
    d.set_start_heading("random")
    assert "cobel-heading-random" in d.svg() and 'class="cobel-heading"' not in d.svg()


@pytest.mark.slow  # renders with pybullet: ~25 s on 2 loaded cores
def test_graph_page_add_node_edge_and_preview_the_view(server: str, browser, workdir: Path) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    browser.get(server + "/graph")
    _wait_text(browser, ".cobel-origin", "template grid")
    _wait_text(browser, ".cobel-ok", "no problems")
    _press(browser, ".cobel-tool-node")
    bg = browser.find_element(By.CSS_SELECTOR, "rect.cobel-bg")
    top_right = browser.find_element(By.CSS_SELECTOR, "circle.cobel-node[data-node='4']")
    # one spacing (48 px) right of node 4: a new node 25 at (5, 4)
    ActionChains(browser).move_to_element_with_offset(top_right, 48, 0).click().perform()
    _wait_all(browser, "circle.cobel-node[data-node='25']")
    assert bg is not None
    _wait_text(browser, ".cobel-yaml", r"- \[5\.0, 4\.0\]")
    _press(browser, ".cobel-tool-edge")
    for node in (4, 25):
        _press(browser, f"circle.cobel-node[data-node='{node}']")
        time.sleep(0.3)
    _wait_text(browser, ".cobel-yaml", r"\[4, 25\]")
    _press(browser, ".cobel-tool-view")
    _press(browser, "circle.cobel-node[data-node='12']")
    _wait_text(browser, ".cobel-view-label", r"agent's view at node 12, heading 90 degrees "
               r"\(84 x 84 px", timeout=60)  # fmt: skip
    img = _wait_all(browser, ".cobel-view img[src^='data:image/png']", timeout=20)[0]
    assert browser.execute_script("return arguments[0].naturalWidth", img) == 84
    _shot(browser, "edit-graph.png")
    _fill(browser, ".cobel-name", "grid_plus")
    _press(browser, ".cobel-save")
    _wait_text(browser, ".cobel-status", r"saved .*env/grid_plus\.yaml")
    from cobelrun.compose import composer
    from cobelrun.config import instantiate

    with composer(workdir / "conf") as compose:
        cfg = compose(["env=grid_plus", "task=gridworld", "~env.observation"])
    env = instantiate("env", cfg.env).unwrapped
    assert env.topology.n_nodes == 26 and 25 in env.topology.neighbours[4]


# -- 2D arenas ----------------------------------------------------------------------------------
def test_arena_checks_are_the_envs_and_name_the_shape() -> None:
    from cobelrun.web.arena_editor import load_arena

    d = load_arena(None, "water_maze").design
    assert d.problems() == []
    assert d.svg().count("cobel-place-cell") == 493  # the env's own place-cell centres
    d.node["goals"]["platform"]["x"] = 0.99  # the platform half out of the pool
    assert d.problems() == [("goal 'platform' lies (partly) outside the arena", "platform")]
    assert 'stroke="#d00000"' in d.svg(bad="platform")
    d.node["goals"]["platform"]["x"] = 0.42
    for x, y in [(-0.2, -0.2), (0.2, -0.2), (0.2, 0.2)]:
        d.add_vertex(x, y)
    d.finish("obstacle")
    name = d.add_start(0.1, -0.1)  # inside the new obstacle
    assert d.problems() == [(f"start '{name}' at [0.1, -0.1] lies inside an obstacle "
                             "(obstacles[0])", name)]  # fmt: skip
    assert d.erase(0.1, -0.1, 0.05) == name and d.problems() == []
    assert d.erase(0.15, -0.1, 0.01) == "obstacles[0]" and "obstacles" in d.node


def test_arena_phases_are_the_water_mazes_protocol() -> None:
    from cobelrun.web.arena_editor import load_arena

    d = load_arena(None, "water_maze").design
    assert d.phase_names() == ["acquisition", "probe", "reversal"]
    gold = 'class="cobel-goal cobel-goal-{}" points="[^"]*" fill="#fac83c"'
    assert re.search(gold.format("platform"), d.svg(phase=0))  # the platform pays
    assert not re.search(gold.format("platform"), d.svg(phase=2))  # moved in the reversal
    assert re.search(gold.format("platform_reversal"), d.svg(phase=2))
    del d.node["goals"]["platform_reversal"]  # the protocol still switches it on: run's message
    ((msg, name),) = d.problems()
    assert msg.startswith("task.protocol phase 'acquisition': rewards: unknown goal "
                          "'platform_reversal'")  # fmt: skip
    assert name == "platform_reversal"


def test_arena_save_keeps_the_rest_and_composes(tmp_path: Path) -> None:
    from cobelrun.web.arena_editor import load_arena, save_arena

    conf = tmp_path / "conf"
    loaded = load_arena(None, "water_maze")
    path = save_arena(conf, "pool", loaded, loaded.design)
    assert path.read_text() == loaded.text
    d = loaded.design.copy()
    d.add_goal(-0.3, 0.4, 0.08, 2.0)
    save_arena(conf, "pool", load_arena(conf, "pool"), d)
    text = path.read_text()
    assert "speed: 0.3                  # m/s" in text and "start_order: shuffled" in text
    from cobelrun.compose import composer
    from cobelrun.config import instantiate

    with composer(conf) as compose:
        cfg = compose(["env=pool", "task=morris_water_maze"])
    env = instantiate("env", cfg.env).unwrapped
    assert set(env.arena.goals) == {"platform", "platform_reversal", "goal_0"}
    assert env.arena.goals["goal_0"].reward == 2.0
    # with its task: the water maze's protocol, agent and monitors, on this arena
    loaded = load_arena(conf, "pool")
    assert loaded.task_doc is None  # the folder has no task/pool.yaml yet
    with pytest.raises(CobelError, match="no task came with this arena"):
        save_arena(conf, "pool", loaded, loaded.design, with_task=True)
    template = load_arena(None, "water_maze")
    save_arena(conf, "pool2", template, template.design, with_task=True)
    with composer(conf) as compose:
        mine, theirs = compose(["task=pool2"]), compose(["task=morris_water_maze"])
    assert mine.task.name == "pool2" and mine.task.protocol == theirs.task.protocol
    assert mine.env == theirs.env and mine.agent == theirs.agent


@pytest.mark.slow
def test_arena_page_start_goal_and_rays(server: str, browser) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    browser.get(server + "/arena?env=water_maze")
    _wait_text(browser, ".cobel-origin", "template water_maze")
    _wait_text(browser, ".cobel-ok", "no problems", timeout=30)
    svg = browser.find_element(By.CSS_SELECTOR, "svg.cobel-arena")
    _press(browser, ".cobel-tool-rays")
    ActionChains(browser).move_to_element_with_offset(svg, -60, 40).click().perform()
    rays = _wait_all(browser, "polyline.cobel-ray", timeout=30)
    assert len(rays) == 36  # boundary-vector rays at the pose, every 10 degrees
    _press(browser, ".cobel-tool-start")
    svg = browser.find_element(By.CSS_SELECTOR, "svg.cobel-arena")
    ActionChains(browser).move_to_element_with_offset(svg, 60, -60).click().perform()
    _wait_text(browser, ".cobel-yaml", r"start_0: \[")
    _press(browser, ".cobel-phase")  # the reversal: the platform moved to the SW quadrant
    next(o for o in _wait_all(browser, ".q-menu .q-item") if "reversal" in o.text).click()
    deadline = time.monotonic() + 20
    css = "polygon.cobel-goal-platform_reversal"
    while _attr(browser, css, "fill") != "#fac83c":
        assert time.monotonic() < deadline, "the reversal phase did not show the moved platform"
        time.sleep(0.2)
    _shot(browser, "edit-arena.png")


@pytest.mark.slow
def test_arena_run_it_runs_the_water_maze_task(server: str, browser, workdir: Path) -> None:
    from selenium.webdriver.common.by import By

    browser.get(server + "/arena?env=water_maze")
    _wait_text(browser, ".cobel-origin", "template water_maze")
    _fill(browser, ".cobel-name", "pool_run")
    _press(browser, ".cobel-run")  # no task yet: says what it needs
    _wait_text(browser, ".cobel-status", "run it needs a task")
    browser.find_element(By.CSS_SELECTOR, ".cobel-with-task").click()
    _press(browser, ".cobel-run")
    status = _wait_text(browser, ".cobel-run-status", r"^(finished|failed)", timeout=400)
    assert status.startswith("finished"), status
    assert "task=pool_run env=pool_run task.runs=1" in status
    assert "/run?p=edit/pool_run/" in _wait_text(browser, ".cobel-dashboard", "dashboard")
    assert (workdir / "conf" / "task" / "pool_run.yaml").is_file()


# -- the pages' new parts in Chromium ----------------------------------------------------------
def _pick(driver, select_css: str, text: str) -> None:
    """Open the menu ``select_css`` and pick the option whose text holds ``text``."""
    _press(driver, select_css)
    option = next(o for o in _wait_all(driver, ".q-menu .q-item") if text in o.text)
    option.click()


def _click_world(driver, x: float, y: float) -> None:
    """Click the arena drawing at world point ``(x, y)`` (its data-* give the transform)."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    svg = driver.find_element(By.CSS_SELECTOR, "svg.cobel-arena")
    x0, y1, s = (float(svg.get_attribute(f"data-{k}")) for k in ("x0", "y1", "scale"))
    w, h = float(svg.get_attribute("width")), float(svg.get_attribute("height"))
    dx, dy = (x - x0) * s - w / 2, (y1 - y) * s - h / 2  # offsets from the element's centre
    ActionChains(driver).move_to_element_with_offset(svg, round(dx), round(dy)).click().perform()


def test_arena_page_outline_menu_and_start_heading(server: str, browser) -> None:
    browser.get(server + "/arena?env=arena")  # the open square
    _wait_text(browser, ".cobel-origin", "template arena")
    shape = _wait_text(browser, ".cobel-outline-shape", r"\bsquare\b")
    assert "circle" not in shape  # the loaded arena's outline, not the menu's default
    assert _attr(browser, ".cobel-outline-size input", "value") == "1"
    assert float(_attr(browser, "polyline.cobel-heading", "data-deg")) == pytest.approx(45.0)
    _pick(browser, ".cobel-heading-kind", "angle (degrees)")
    _fill(browser, ".cobel-heading-deg", "270")
    _press(browser, ".cobel-heading-set")
    _wait_text(browser, ".cobel-yaml", r"start_heading: 270")
    _wait_text(browser, ".cobel-info", r"start heading: 270 degrees")
    assert _attr(browser, "polyline.cobel-heading", "data-deg") == "270.0"


@pytest.mark.slow  # the water maze's 493 place cells: ~10 s
def test_arena_page_outline_menu_follows_the_loaded_arena(server: str, browser) -> None:
    browser.get(server + "/arena?env=arena")
    _wait_text(browser, ".cobel-outline-shape", r"\bsquare\b")
    _pick(browser, ".cobel-template", "Morris water maze")
    _press(browser, ".cobel-load-template")
    _wait_text(browser, ".cobel-origin", "template water_maze")
    _wait_text(browser, ".cobel-outline-shape", r"\bcircle\b")
    _wait_text(browser, ".cobel-heading-kind", r"face the centre")


@pytest.mark.slow  # ~10 s on the loaded machine (test_view_preview_reads_the_render_cache: 1 s)
def test_graph_page_view_from_the_render_cache(server: str, browser, workdir: Path) -> None:
    from cobelrun.web.graph_editor import _GRID_TEMPLATE, load_graph

    conf = workdir / "conf"
    (conf / "env").mkdir(parents=True, exist_ok=True)
    cache_dir = workdir / "render_cache"
    text = _GRID_TEMPLATE.replace("height: 84", "height: 6").replace("width: 84", "width: 8")
    (conf / "env" / "cached_grid.yaml").write_text(text + f"  cache_dir: {cache_dir}\n")
    images = _plant_cache(load_graph(conf, "cached_grid").design, cache_dir)
    browser.get(server + "/graph?env=cached_grid")
    _wait_text(browser, ".cobel-origin", "cached_grid.yaml")
    _pick(browser, ".cobel-heading", "180")
    _press(browser, ".cobel-tool-view")
    _press(browser, "circle.cobel-node[data-node='12']")
    _wait_text(browser, ".cobel-view-label", r"agent's view at node 12, heading 180 degrees "
               r"\(6 x 8 px")  # fmt: skip
    _wait_text(browser, ".cobel-view-source", r"^read from the render cache .*render_cache")
    src = _attr(browser, ".cobel-view img", "src")
    import base64
    import io

    import matplotlib.pyplot as plt

    png = plt.imread(io.BytesIO(base64.b64decode(src.split(",", 1)[1])), format="png")
    assert png.shape[:2] == (6, 8)
    assert np.allclose(png[..., :3] * 255, images[12, 2], atol=1)  # the cache's pixels


@pytest.mark.slow  # a DQN run on rendered images (2 short phases): ~1 min
def test_graph_page_phases_and_run_it(server: str, browser, workdir: Path) -> None:
    import cobelrun
    from cobelrun.compose import composer

    browser.get(server + "/graph")
    _wait_text(browser, ".cobel-origin", "template grid")
    _wait_text(browser, ".cobel-phase", "env")
    _press(browser, ".cobel-add-phase")  # phase 2 of the grid task's protocol, picked
    _wait_text(browser, ".cobel-phase", r"phase 2: phase_2")
    _press(browser, ".cobel-tool-clear")
    _press(browser, "circle.cobel-node[data-node='24']")
    _wait_text(browser, ".cobel-phase-hint", r"phase_2 \(10 trials\) sets rewards 24: 0.0")
    _press(browser, ".cobel-tool-goal")
    _press(browser, "circle.cobel-node[data-node='20']")
    deadline = time.monotonic() + 10
    while _attr(browser, "circle.cobel-node[data-node='20']", "fill") != "#fac83c":
        assert time.monotonic() < deadline, "the phase's new goal was not drawn"
        time.sleep(0.1)
    assert _attr(browser, "circle.cobel-node[data-node='24']", "fill") == "#ffffff"
    _shot(browser, "edit-graph-phase.png")
    _fill(browser, ".cobel-name", "grid_moves")
    _fill(browser, ".cobel-run-trials", "2")
    _press(browser, ".cobel-with-task")
    _press(browser, ".cobel-run")  # saves env and task, then one run, each phase cut to 2 trials
    _wait_text(browser, ".cobel-status", r"saved .*env/grid_moves\.yaml, .*task/grid_moves\.yaml")
    status = _wait_text(browser, ".cobel-run-status", r"^(finished|failed)", timeout=400)
    assert status.startswith("finished"), status
    assert "task=grid_moves env=grid_moves task.runs=1 task.protocol.phases.0.trials=2" in status
    assert "/run?p=edit/grid_moves/" in _wait_text(browser, ".cobel-dashboard", "dashboard")
    with composer(workdir / "conf") as compose:
        phases = compose(["task=grid_moves"]).task.protocol.phases
    assert [p.name for p in phases] == ["training", "phase_2"] and phases[1].rewards[20] == 1.0
    run_dir = Path(re.search(r"-> (\S+)$", status).group(1))
    trials = cobelrun.load(run_dir).trials
    assert len(trials) == 4  # 2 + 2 trials


@pytest.mark.slow  # the water maze's 493 place cells are rebuilt on every redraw: ~20 s
def test_arena_page_moves_the_platform_in_the_reversal(server: str, browser, workdir: Path) -> None:
    from cobelrun.compose import composer

    browser.get(server + "/arena?env=water_maze")
    _wait_text(browser, ".cobel-ok", "no problems", timeout=30)
    _pick(browser, ".cobel-phase", "reversal")
    _wait_text(browser, ".cobel-phase-hint", r"^reversal \(16 trials\)")
    _press(browser, ".cobel-tool-goal")
    _click_world(browser, -0.42, -0.42)  # the reversal platform: off
    _wait_text(browser, ".cobel-status", "goal platform_reversal off")
    _click_world(browser, 0.42, -0.42)  # a new platform in the SE quadrant: on in this phase
    _wait_text(browser, ".cobel-status", "goal goal_0 on")
    assert _attr(browser, "polygon.cobel-goal-goal_0", "fill") == "#fac83c"
    assert _attr(browser, "polygon.cobel-goal-platform_reversal", "fill") == "#ffffff"
    _shot(browser, "edit-arena-reversal.png")
    _pick(browser, ".cobel-phase", "acquisition")  # before the reversal the new goal is off
    deadline = time.monotonic() + 20
    while _attr(browser, "polygon.cobel-goal-goal_0", "fill") != "#ffffff":
        assert time.monotonic() < deadline, "the new goal pays before the reversal"
        time.sleep(0.2)
    _fill(browser, ".cobel-name", "pool_moved")
    _press(browser, ".cobel-with-task")
    _press(browser, ".cobel-save")
    _wait_text(browser, ".cobel-status", r"saved .*env/pool_moved\.yaml, .*task/pool_moved\.yaml")
    with composer(workdir / "conf") as compose:
        cfg = compose(["task=pool_moved"])
    rev = cfg.task.protocol.phases[2]
    assert (rev.name, rev.rewards.goal_0, rev.terminals.goal_0) == ("reversal", 1.0, True)
    assert rev.rewards.platform_reversal == 0.0 and cfg.env.goals.goal_0.reward == 0.0


def test_the_address_and_env_in_the_address_open_the_page_that_edits_it(tmp_path: Path) -> None:
    from cobelrun.web.editor import page_of, prepare, url_of

    conf = tmp_path / "conf"  # not there yet: built-in envs
    assert [
        page_of(conf, e) for e in ("water_maze", "hex_3d", "tmaze_paper", "../x", "bandit")
    ] == ["arena", "graph", None, None, None]  # None: the gridworld page (or its message)
    assert url_of("127.0.0.1", 8090, prepare(conf, "water_maze", tmp_path)) == \
        "http://127.0.0.1:8090/arena?env=water_maze"  # fmt: skip
    assert url_of("::1", 8090, prepare(conf, None, tmp_path)) == "http://[::1]:8090/"


@pytest.mark.slow  # the arena page draws the open square's place cells: ~5 s
def test_env_in_the_address_of_the_gridworld_page_goes_to_its_page(server: str, browser) -> None:
    browser.get(server + "/?env=arena")  # an arena named on the gridworld page's address
    _wait_text(browser, ".cobel-origin", "template arena")
    assert browser.current_url.endswith("/arena?env=arena")


def test_export_marks_the_goals_of_the_chosen_phase() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    from cobelrun.web.grid_design import _draw_payoffs

    d = ec.load_template("tmaze_paper").design
    left, right = d.state(d.places["left_arm"]), d.state(d.places["right_arm"])
    for phase, goal in ((0, right), (1, left)):  # acquisition pays right, extinction left
        fig, ax = plt.subplots()
        world = d.phase_world(phase)
        _draw_payoffs(GridWorldEnv(world), ax)
        marks = {c.get_label(): c.get_offsets().tolist() for c in ax.collections}
        plt.close(fig)
        assert marks["goal"] == [world.coords[goal].tolist()]
        assert marks["start"] == [world.coords[38].tolist()]
    from cobelrun.web.arena_editor import load_arena

    pool = load_arena(None, "water_maze").design
    pool.node["observation"] = [{"kind": "pose"}]  # the 493 place cells are not drawn here
    reversal = pool.phase_names().index("reversal")
    fig, ax = plt.subplots()
    _draw_payoffs(pool.phase_env(reversal), ax)
    (rim,) = [p for p in ax.patches if isinstance(p, Circle)]
    plt.close(fig)
    assert rim.center == pytest.approx((-0.42, -0.42))  # the moved platform, not the old one


@pytest.mark.slow  # a page in Chromium: ~5 s
def test_resize_beyond_the_limit_says_so(server: str, browser) -> None:
    browser.get(server + "/")
    _wait_text(browser, ".cobel-info", r"^10 x 10 cells")
    _fill(browser, ".cobel-width", "100")
    _fill(browser, ".cobel-height", "100")
    _press(browser, ".cobel-resize")  # not clamped to 32 x 32 without a word
    _wait_text(browser, ".cobel-status", r"a 100 x 100 grid is too large to edit comfortably here "
               r"\(at most 32 x 32\)")  # fmt: skip
    assert _wait_text(browser, ".cobel-info", r"^10 x 10 cells")
    from selenium.webdriver.common.keys import Keys

    _fill(browser, ".cobel-width", Keys.BACKSPACE)  # an empty box
    _press(browser, ".cobel-resize")
    _wait_text(browser, ".cobel-status", r"grid width must be a whole number >= 1, got None")


def test_run_it_links_the_dashboard_only_once_it_listens(tmp_path: Path) -> None:
    from cobelrun.web.edit_runs import Child, Editor

    results = tmp_path / "results"
    out = results / "edit" / "maze" / "stamp-0"
    out.mkdir(parents=True)
    (out / "manifest.json").write_text("{}")
    editor = Editor(folder=tmp_path / "conf", results=results)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    editor.dashboard = Child(sleeper, "cobel serve")  # started, not listening yet
    editor.dashboard_port = free_port()
    run = Child(sleeper, "cobel run", out=out)
    try:
        assert editor.dashboard_url(run) is None  # a link now would be refused
        with socket.socket() as s:
            s.bind(("127.0.0.1", editor.dashboard_port))
            s.listen()
            url = editor.dashboard_url(run)
        assert url == f"http://127.0.0.1:{editor.dashboard_port}/run?p=edit/maze/stamp-0"
    finally:
        editor.dashboard.stop()


def test_graph_problem_is_drawn_next_to_its_node() -> None:
    from cobelrun.web.graph_editor import load_graph

    g = load_graph(REPO / "conf", "hex_3d").design
    goal = 38  # the centre: every edge to it removed
    for a, b in [e for e in g.edges if goal in e]:
        g.toggle_edge(a, b)
    (msg,) = g.problems()
    assert msg.startswith(f"goal node {goal} is unreachable from every start")
    svg = g.svg(problems=[msg])
    ring = re.search(rf'<circle class="cobel-node" data-node="{goal}" [^>]*>', svg).group(0)
    assert 'stroke="#d00000"' in ring and 'stroke-width="4"' in ring
    assert re.findall(r'class="cobel-problem-at"[^>]*>([^<]*)<', svg) == [
        f"goal node {goal} is unreachable from every start"
    ]
    assert "cobel-problem-at" not in g.svg(problems=[])


@pytest.mark.slow  # the arena page in Chromium: ~10 s
def test_arena_outline_menu_reads_polygon_after_drawing_one(server: str, browser) -> None:
    browser.get(server + "/arena?env=arena")  # the open unit square
    _wait_text(browser, ".cobel-outline-shape", r"\bsquare\b")
    _wait_text(browser, ".cobel-ok", "no problems", timeout=30)
    _press(browser, ".cobel-tool-outline")
    for x, y in [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.5, 1.2), (0.0, 1.0)]:  # a house
        _click_world(browser, x, y)
        time.sleep(0.5)  # each vertex is drawn before the next click
    _press(browser, ".cobel-finish")
    _wait_text(browser, ".cobel-yaml", r"arena: \{shape: polygon")
    _wait_text(browser, ".cobel-outline-shape", r"\bpolygon\b")


def test_an_arena_with_too_many_place_cells_is_refused_in_one_line(tmp_path: Path) -> None:
    from cobelrun.web.arena_editor import load_arena

    conf = tmp_path / "conf"
    (conf / "env").mkdir(parents=True)
    (conf / "env" / "dense.yaml").write_text(
        "_target_: cobelrun.envs.Continuous2DEnv\n"
        "arena: {shape: circle, x: 0.0, y: 0.0, radius: 1.0}\n"
        "observation:\n  - {kind: pose}\n  - {kind: place_cells, n: 2000000, sigma: 0.1}\n"
    )  # building its env took minutes on every click
    with pytest.raises(CobelError, match=r"dense\.yaml: 2000000 place cells are too many to draw "
                       r"here \(at most 5000\); edit its YAML instead"):  # fmt: skip
        load_arena(conf, "dense")
    assert len(load_arena(conf, "water_maze").design.node["observation"]) == 1  # 493: opened


def test_a_saved_graph_lists_its_edges_one_a_line(tmp_path: Path) -> None:
    from cobelrun.web.graph_editor import graph_text, load_graph

    loaded = load_graph(tmp_path, "hex_3d")
    d = loaded.design.copy()
    d.toggle_edge(0, 1)  # changed: written as a manual topology
    text = graph_text(loaded, d)
    lines = text[text.index("  edges:") :].splitlines()[1:196]
    assert all(re.fullmatch(r"\s+- \[\d+, \d+\]", line) for line in lines), lines[:3]
