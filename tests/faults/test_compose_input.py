"""Bad input before any folder, the config search path in the open, YAML aliases bounded
(issue 31, items 2, 4 and 7).

In-process through the composer and ``cobel run``'s up-front validation
(:func:`cobelrun.compose.validate`), and through the real CLI where the issue met the message
there (``cobel show -cd``).
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

import cobelrun.compose as compose_mod
from cobelrun.compose import composer, config_args, validate
from cobelrun.errors import CobelError, ConfigError

TINY = ["task=tmaze_extinction", "task.runs=1", "task.protocol.phases.0.trials=3",
        "task.protocol.phases.1.trials=3"]  # fmt: skip

BOMB = """\
a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]
b: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]
c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]
d: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]
e: &e [*d,*d,*d,*d,*d,*d,*d,*d,*d]
f: &f [*e,*e,*e,*e,*e,*e,*e,*e,*e]
g: &g [*f,*f,*f,*f,*f,*f,*f,*f,*f]
h: &h [*g,*g,*g,*g,*g,*g,*g,*g,*g]
i: &i [*h,*h,*h,*h,*h,*h,*h,*h,*h]
"""


def one_line_error(proc) -> str:
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert len(lines) == 1 and lines[0].startswith("cobel: error:"), proc.stderr
    return lines[0]


# -- deletions of keys the run uses ------------------------------------------------------------
@pytest.mark.parametrize(
    "override, message",
    [("~task.runs", "~task.runs deletes task.runs, a setting (its default: 1) that the run uses; "
                    "set it instead (task.runs=VALUE)"),
     ("~agent.epsilon", "~agent.epsilon deletes agent.epsilon, a setting (its default: 0.3)"),
     ("~task.record.steps", "deletes task.record.steps, a setting (its default: True)"),
     ("~task.name", "~task.name deletes task.name, a required key"),
     ("~task.protocol.phases.0.trials", "deletes task.protocol.phases.0.trials, a required key")],
)  # fmt: skip
def test_deleting_a_key_the_run_uses_is_one_line(override, message):
    with pytest.raises(ConfigError) as err:
        validate([*TINY, override], multirun=False)
    assert message in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize(
    "overrides",
    [["~task.monitors.trajectory"], ["~task.description"], ["~task.protocol.phases.0.rewards"],
     ["~task.runs", "+task.runs=2"]],
)  # fmt: skip
def test_deleting_what_is_optional_still_works(overrides):
    cfg, _ = validate([*TINY, *overrides], multirun=False)
    if "+task.runs=2" in overrides:
        assert cfg.task.runs == 2


# -- run lists outside task.runs -------------------------------------------------------------
def test_record_runs_outside_task_runs_is_one_line():
    with pytest.raises(ConfigError, match=r"task.record.runs must be 'all' or a list of run "
                       r"indices in 0..0 \(task.runs is 1\), got \[100\]"):  # fmt: skip
        validate([*TINY, "task.record.runs=[100]"], multirun=False)
    validate([*TINY, "task.runs=3", "task.record.runs=[0,2]"], multirun=False)


def test_save_agents_outside_task_runs_is_one_line():
    with pytest.raises(ConfigError, match=r"task.save_agents .* in 0..0, got \[5\]"):
        validate([*TINY, "task.save_agents=[5]"], multirun=False)


# -- phases ---------------------------------------------------------------------------------
def test_misspelled_phase_key_names_the_phase_and_suggests_trials():
    with pytest.raises(ConfigError) as err:
        validate([*TINY, "task.protocol.phases.0.trails=30"], multirun=False)
    msg = str(err.value)
    assert msg.startswith(
        "unknown key 'task.protocol.phases.0.trails': phase 0 ('acquisition') has no 'trails' "
        "(did you mean 'trials'?); allowed: 'name', 'trials',"
    ), msg
    assert "phases has no '0'" not in msg and "+task.protocol" not in msg


def test_phase_index_out_of_range_lists_the_phases():
    with pytest.raises(ConfigError) as err:
        validate([*TINY, "task.protocol.phases.5.trials=3"], multirun=False)
    assert str(err.value) == (
        "task.protocol.phases.5.trials: there is no phase 5; the protocol has 2 phases "
        "(0 'acquisition', 1 'extinction'); add phases in a protocol config (protocol=NAME)"
    )


def test_a_phase_field_the_yaml_does_not_set_can_be_set():
    cfg, _ = validate([*TINY, "task.protocol.phases.1.max_steps=20"], multirun=False)
    assert cfg.task.protocol.phases[1].max_steps == 20


# -- arguments of a world function -------------------------------------------------------------
def test_an_argument_the_world_function_takes_is_no_unknown_key():
    cfg, _ = validate(["task=latent_learning", "task.runs=1", "env.world.goal_reward=1"],
                      multirun=False)  # fmt: skip
    assert cfg.env.world._target_ == "cobelrun.envs.world.blodgett"
    assert cfg.env.world.goal_reward == 1


@pytest.mark.parametrize("override", ["env.world.goal_reward=1", "+env.world.goal_reward=1"])
def test_a_world_function_without_arguments_says_so(override):
    with pytest.raises(ConfigError) as err:
        validate([*TINY, override], multirun=False)
    assert str(err.value) == (
        "unknown key 'env.world.goal_reward': env.world (cobelrun.envs.world.tmaze_paper) "
        "takes no arguments"
    )


def test_a_misspelled_agent_argument_lists_the_agents_arguments():
    with pytest.raises(ConfigError) as err:
        validate([*TINY, "agent.epsilonn=0.1"], multirun=False)
    assert str(err.value).startswith(
        "unknown key 'agent.epsilonn' (did you mean 'epsilon'?); allowed: 'epsilon', 'beta', "
        "'learning_rate', 'gamma'"
    )  # the arguments of the agent's class, not only the keys its YAML sets


# -- the search path in the open -------------------------------------------------------------
@pytest.fixture
def fresh_notes(monkeypatch):
    monkeypatch.setattr(compose_mod, "_ANNOUNCED", set())


def test_a_user_file_that_shadows_a_builtin_is_announced_once(tmp_path, monkeypatch, capsys,
                                                              fresh_notes):  # fmt: skip
    mine = tmp_path / "conf" / "env" / "tmaze_paper.yaml"
    mine.parent.mkdir(parents=True)
    mine.write_text((compose_mod.builtin_conf_dir() / "env" / "tmaze_paper.yaml").read_text())
    (tmp_path / "conf" / "env" / "other.yaml").write_text("_target_: cobelrun.envs.TwoAFCEnv\n")
    monkeypatch.chdir(tmp_path)
    for _ in range(2):
        with composer() as compose:
            compose(TINY)
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"cobel: note: {mine} replaces the built-in env=tmaze_paper "
        f"({compose_mod.builtin_conf_dir() / 'env' / 'tmaze_paper.yaml'})"
    ]


def test_no_note_without_a_shadow(tmp_path, monkeypatch, capsys, fresh_notes):
    (tmp_path / "conf" / "env").mkdir(parents=True)
    (tmp_path / "conf" / "env" / "mine.yaml").write_text("_target_: cobelrun.envs.TwoAFCEnv\n")
    monkeypatch.chdir(tmp_path)
    with composer() as compose:
        compose(TINY)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "args, expected",
    [(["-cd", "DIR", "env=x"], ("DIR", "config", ["env=x"])),
     (["--config-dir=DIR", "-cn", "mine", "a=1"], ("DIR", "mine", ["a=1"])),
     (["-cp", "DIR", "--config-name=m"], ("DIR", "m", [])),
     (["a=1"], (None, "config", ["a=1"]))],
)  # fmt: skip
def test_config_args(tmp_path, args, expected):
    args = [a.replace("DIR", str(tmp_path)) for a in args]
    folder, name, rest = config_args(args)
    assert (folder, name, rest) == (tmp_path if expected[0] else None, *expected[1:])


def test_config_args_errors(tmp_path):
    with pytest.raises(ConfigError, match="-cd needs a value"):
        config_args(["-cd"])
    with pytest.raises(ConfigError, match="does not exist"):
        config_args(["-cd", str(tmp_path / "nope")])


def _myconf(tmp_path: Path) -> Path:
    conf = tmp_path / "myconf" / "env"
    conf.mkdir(parents=True)
    (conf / "mymaze.yaml").write_text(
        "# a 4x3 open field\n_target_: cobelrun.envs.GridWorldEnv\nworld:\n"
        "  _target_: cobelrun.envs.world.open_field\n  width: 4\n  height: 3\n"
    )
    return tmp_path / "myconf"


def test_show_takes_config_dir_in_process(tmp_path):
    from cobelrun.commands.show import show

    path, text = show(["-cd", str(_myconf(tmp_path)), "env=mymaze"], None)
    assert path is None and text.startswith("mymaze: grid, bounds (-0.5, -0.5, 3.5, 2.5)")


def test_cli_show_and_list_take_config_dir(cobel, tmp_path):
    conf = _myconf(tmp_path)
    proc = cobel("show", "-cd", str(conf), "env=mymaze", "--no-png")
    assert proc.returncode == 0, proc.stderr
    assert "LexerNoViableAltException" not in proc.stderr and "mymaze: grid" in proc.stdout
    listed = cobel("list", "env", "-cd", str(conf))
    assert listed.returncode == 0, listed.stderr
    assert "mymaze" in listed.stdout and "a 4x3 open field" in listed.stdout
    assert "tmaze_paper" in listed.stdout  # the built-in ones after it


# -- YAML aliases bounded -------------------------------------------------------------------
def test_billion_laughs_in_conf_is_refused_quickly(tmp_path, monkeypatch):
    bomb = tmp_path / "conf" / "env" / "bomb.yaml"
    bomb.parent.mkdir(parents=True)
    bomb.write_text(BOMB)
    monkeypatch.chdir(tmp_path)
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as err:
        validate(TINY, multirun=False)  # the file is refused even when not chosen
    assert time.perf_counter() - t0 < 5
    assert str(err.value) == (
        f"{bomb}: its YAML aliases (&anchor / *alias) expand to more than 1,000,000 nodes; "
        "refusing to load it (a config needs far fewer; is it a 'billion laughs' file?)"
    )


def test_billion_laughs_in_a_config_dir_is_refused(tmp_path):
    (tmp_path / "config.yaml").write_text("defaults:\n  - _self_\nseed: 1\n" + BOMB)
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match="expand to more than 1,000,000 nodes"):
        validate([], multirun=False, config_dir=tmp_path)
    assert time.perf_counter() - t0 < 5


def test_billion_laughs_in_a_run_folders_config_is_refused(tmp_path):
    from cobelrun.api import rerun

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text(BOMB)
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"run/config\.yaml: its YAML aliases"):
        rerun(tmp_path / "run", [], tmp_path / "out")
    assert time.perf_counter() - t0 < 5 and not (tmp_path / "out").exists()


def test_cli_billion_laughs_is_one_line(cobel, tmp_path):
    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "conf" / "task" / "bomb.yaml").write_text("# @package _global_\n" + BOMB)
    t0 = time.perf_counter()
    proc = cobel("run", "task=bomb", timeout=60)
    assert "expand to more than 1,000,000 nodes" in one_line_error(proc)
    assert time.perf_counter() - t0 < 30  # the CLI's start-up included
    listed = cobel("list", timeout=60)
    assert "expand to more than 1,000,000 nodes" in one_line_error(listed)


def test_aliases_in_an_ordinary_config_are_fine(tmp_path):
    """YAML anchors are legitimate: a small shared block is used several times."""
    (tmp_path / "config.yaml").write_text(
        "defaults:\n  - _self_\nshared: &s {a: 1, b: [1, 2, 3]}\nx: *s\ny: *s\nseed: 2\n"
    )
    with composer(tmp_path) as compose:
        cfg = compose([])
    assert cfg.x == cfg.y == {"a": 1, "b": [1, 2, 3]} and cfg.seed == 2


def test_a_run_folders_config_that_is_no_file_or_huge_is_refused(tmp_path):
    from cobelrun.api import rerun

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").symlink_to("/dev/zero")
    with pytest.raises(CobelError, match=r"is not a run folder \(no config\.yaml\)"):
        rerun(run, [], tmp_path / "out")  # a device, not a file
    with pytest.raises(ConfigError, match=r"config\.yaml is not a regular file"):
        compose_mod.load_config(run / "config.yaml")
    (run / "config.yaml").unlink()
    with open(run / "config.yaml", "wb") as f:
        f.truncate(compose_mod.YAML_BYTES_LIMIT + 1)
    with pytest.raises(ConfigError, match="a config file may hold at most 16,777,216"):
        rerun(run, [], tmp_path / "out")
    assert not (tmp_path / "out").exists()
