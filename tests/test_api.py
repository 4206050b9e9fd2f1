"""The Python API (cobelrun.run / rerun / load / load_sweep), the end-of-run summary, rerun."""

from __future__ import annotations

import json
import subprocess
import sys

import pandas as pd
import pytest

import cobelrun
from cobelrun.errors import ConfigError
from tests import inprocess

cli = inprocess.cli  # fixture: cobel in this process

TINY = ["task.runs=2", "task.protocol.phases.0.trials=12", "task.protocol.phases.1.trials=12",
        "task.record.mcap=false", "task.save_agents=false"]  # fmt: skip


@pytest.fixture(scope="module")
def api_run(tmp_path_factory) -> cobelrun.Run:
    out = tmp_path_factory.mktemp("api") / "run"
    return cobelrun.run("tmaze_extinction", overrides=[*TINY, "seed=5"], out=out)


def test_run_returns_tables_manifest_and_plot(api_run, tmp_path):
    assert isinstance(api_run, cobelrun.Run)
    assert api_run.manifest["status"] == "completed"
    assert api_run.manifest["task"] == "tmaze_extinction"
    trials = api_run.trials
    assert len(trials) == 2 * 24
    assert set(trials["phase"]) == {"acquisition", "extinction"}
    assert {"run", "trial", "reward", "steps", "response"} <= set(trials.columns)
    assert {"x", "y", "action"} <= set(api_run.steps.columns)
    assert set(api_run.manifest["phase_wall_time_s"]) == {"acquisition", "extinction"}
    png = api_run.plot(tmp_path / "p.png")
    assert png.is_file() and png.stat().st_size > 1000
    again = cobelrun.load(api_run.path)
    pd.testing.assert_frame_equal(again.trials, trials)


def test_api_matches_cli_tables(api_run, cli, tmp_path):
    """The API composes exactly as `cobel run` does: same overrides, identical trials."""
    out = tmp_path / "cli"
    proc = cli("run", "task=tmaze_extinction", *TINY, "seed=5", f"hydra.run.dir={out}",
                 "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "folder:" not in proc.stderr  # --quiet: no summary
    log = (out / "cobel.log").read_text()  # the run's log lines, not an empty file
    assert "task tmaze_extinction, seed 5" in log and "status completed" in log
    assert "phase extinction: runs 2, trials 12" in log
    pd.testing.assert_frame_equal(pd.read_parquet(out / "trials.parquet"), api_run.trials)


def test_summary_per_phase(api_run):
    s = api_run.summary()
    assert list(s["phase"]) == ["acquisition", "extinction"]
    assert list(s["runs"]) == [2, 2] and list(s["trials"]) == [12, 12]
    t = api_run.trials
    last = t[(t["phase"] == "extinction") & (t["trial"] > 24 - 10)]
    assert s.loc[1, "reward"] == pytest.approx(last["reward"].mean())
    assert s.loc[1, "latency"] == pytest.approx(last["steps"].mean())
    assert s.loc[1, "response"] == pytest.approx(last["response"].mean())


def test_bad_input_writes_nothing(tmp_path):
    with pytest.raises(ConfigError, match=r"agent\.epsilonn"):
        cobelrun.run("tmaze_extinction", ["agent.epsilonn=0.1"], out=tmp_path / "x")
    with pytest.raises(ConfigError, match="unknown task"):
        cobelrun.run("tmaze_extinctio", out=tmp_path / "x")
    with pytest.raises(ConfigError, match="list of strings"):
        cobelrun.run("tmaze_extinction", "seed=1", out=tmp_path / "x")  # type: ignore[arg-type]
    assert not (tmp_path / "x").exists()


def test_rerun_identical_tables_and_overrides(api_run, tmp_path):
    same = cobelrun.rerun(api_run.path, out=tmp_path / "same")
    pd.testing.assert_frame_equal(same.trials, api_run.trials)
    pd.testing.assert_frame_equal(same.steps, api_run.steps)
    other = cobelrun.rerun(api_run.path, ["seed=6"], out=tmp_path / "other")
    assert other.manifest["seed"] == 6
    assert not other.trials["steps"].equals(api_run.trials["steps"])
    with pytest.raises(ConfigError, match=r"not in struct|agent\.epsilonn"):
        cobelrun.rerun(api_run.path, ["agent.epsilonn=0.1"], out=tmp_path / "bad")
    with pytest.raises(ConfigError, match="cobel run"):
        cobelrun.rerun(api_run.path, ["agent=mfec"], out=tmp_path / "bad")
    assert not (tmp_path / "bad").exists()


def test_cli_summary_and_rerun(api_run, cli, tmp_path):
    proc = cli("rerun", str(api_run.path), "--out", str(tmp_path / "r"))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == str(tmp_path / "r")
    for text in ("acquisition", "extinction", "mean reward", "latency", "folder:", "cobel plot"):
        assert text in proc.stderr, proc.stderr
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "r" / "trials.parquet"),
                                  api_run.trials)  # fmt: skip
    bad = cli("rerun", str(tmp_path / "nowhere"))
    assert bad.returncode == 2 and "not a run folder" in bad.stderr


def test_cli_config_dir_runs_the_saved_config(cli, tmp_path):
    """`cobel run -cd RUN/.hydra -cn config` runs that config, not the default one."""
    first = tmp_path / "first"
    proc = cli("run", "task=tmaze_extinction", *TINY, "seed=9", "agent.epsilon=0.3",
                 f"hydra.run.dir={first}", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    second = tmp_path / "second"
    proc = cli("run", "-cd", str(first / ".hydra"), "-cn", "config",
                 f"hydra.run.dir={second}", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    cfg = json.loads((second / "manifest.json").read_text())["config"]
    assert cfg["agent"]["epsilon"] == 0.3 and cfg["seed"] == 9
    pd.testing.assert_frame_equal(pd.read_parquet(second / "trials.parquet"),
                                  pd.read_parquet(first / "trials.parquet"))  # fmt: skip
    # a sweep over the saved config is a cobel sweep: indexed, every job done
    sweep = tmp_path / "sweep"
    proc = cli("run", "-m", "-cd", str(first / ".hydra"), "-cn", "config", "seed=9,10",
                 f"hydra.sweep.dir={sweep}", "hydra/launcher=basic", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    index = pd.read_csv(sweep / "jobs.csv")
    assert list(index["status"]) == ["done", "done"] and list(index["seed"]) == [9, 10]
    pd.testing.assert_frame_equal(pd.read_parquet(sweep / "0" / "trials.parquet"),
                                  pd.read_parquet(first / "trials.parquet"))  # fmt: skip
    # a user's folder with its own task next to the built-in groups
    user = tmp_path / "myconf"
    (user / "task").mkdir(parents=True)
    (user / "task" / "mine.yaml").write_text(
        "# @package _global_\ndefaults:\n  - tmaze_extinction\n  - _self_\n"
        "task:\n  name: mine\n  runs: 1\n"
    )
    proc = cli("run", "-cd", str(user), "task=mine", *TINY[1:], f"hydra.run.dir={tmp_path / 'm'}",
                 "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "m" / "manifest.json").read_text())["task"] == "mine"
    missing = cli("run", "-cd", str(tmp_path / "nope"), "--quiet")
    assert missing.returncode == 2 and "does not exist" in missing.stderr


def test_hydra_help_names_the_real_command(cobel):
    proc = cobel("run", "--hydra-help")
    assert proc.returncode == 0, proc.stderr
    assert 'eval "$(cobel -sc install=bash)"' in proc.stdout


def test_import_is_light():
    code = (
        "import sys, cobelrun; cobelrun.run; import cobelrun.api;"
        "bad = [m for m in ('torch', 'stable_baselines3', 'pybullet') if m in sys.modules];"
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_shell_completion_through_cobel(cobel):
    """The command --hydra-help prints works, and completes overrides after `cobel run`."""
    install = cobel("-sc", "install=bash")
    assert install.returncode == 0, install.stderr
    assert "hydra_bash_completion" in install.stdout
    line = "cobel run task=tmaze_ext"
    query = cobel("-sc", "query=bash", env={"COMP_LINE": line, "COMP_POINT": str(len(line))})
    assert query.returncode == 0, query.stderr
    assert "task=tmaze_extinction" in query.stdout


def test_training_log_of_deep_agents(tmp_path):
    """record.training_log: SB3's logger writes one CSV row per trial into training/run_NNNN."""
    pytest.importorskip("stable_baselines3")
    r = cobelrun.run("two_afc", ["task.runs=1", "task.protocol.phases.0.trials=6",
                                 "task.record.training_log=true"], out=tmp_path / "r")  # fmt: skip
    log = pd.read_csv(r.folder.training_log(0) / "progress.csv")
    assert len(log) == 6
    assert {"train/loss", "train/q_max", "rollout/exploration_rate",
            "rollout/ep_rew_mean"} <= set(log.columns)  # fmt: skip
    assert log["train/loss"].notna().any()
    with pytest.raises(ConfigError, match="needs a deep"):
        cobelrun.run("tmaze_extinction", ["task.record.training_log=true"], out=tmp_path / "x")


TB_RUN = ["run", "task=two_afc", "task.runs=2", "task.protocol.phases.0.trials=5",
          "task.record.training_log=true", "task.record.mcap=false", "--quiet"]  # fmt: skip


def test_training_log_writes_tensorboard_events(cli, tmp_path):
    """With tensorboard installed, each run's folder also holds event files with the CSV's
    curves (read back through tensorboard's public EventAccumulator)."""
    pytest.importorskip("stable_baselines3")
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    proc = cli(*TB_RUN, f"hydra.run.dir={tmp_path / 'r'}")
    assert proc.returncode == 0, proc.stderr
    assert "TensorBoard output skipped" not in proc.stderr
    for run in (0, 1):
        folder = tmp_path / "r" / "training" / f"run_{run:04d}"
        assert len(list(folder.glob("events.out.tfevents.*"))) == 1
        events = EventAccumulator(str(folder))
        events.Reload()
        csv = pd.read_csv(folder / "progress.csv")
        for tag in ("train/loss", "train/q_max", "rollout/exploration_rate"):
            logged = [e.value for e in events.Scalars(tag)]
            assert logged == pytest.approx(csv[tag].dropna().tolist(), rel=1e-6)
        assert len(events.Scalars("rollout/exploration_rate")) == 5  # one per trial


def test_training_log_without_tensorboard(cobel, tmp_path):
    """tensorboard blocked (a sitecustomize that maps it to None, as if not installed): the
    run still writes the CSV logs and says once, in one line, that TensorBoard was skipped."""
    pytest.importorskip("stable_baselines3")
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text("import sys\nsys.modules['tensorboard'] = None\n")
    proc = cobel(*TB_RUN, f"hydra.run.dir={tmp_path / 'r'}", env={"PYTHONPATH": str(site)})
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if "TensorBoard output skipped" in line]
    assert len(lines) == 1, proc.stderr  # once per task, not once per run
    assert "pip install tensorboard" in lines[0] and "progress.csv" in lines[0]
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    for run in (0, 1):
        folder = tmp_path / "r" / "training" / f"run_{run:04d}"
        assert len(pd.read_csv(folder / "progress.csv")) == 5
        assert not list(folder.glob("events.out.tfevents.*"))
    assert "TensorBoard output skipped" in (tmp_path / "r" / "cobel.log").read_text()
    # the Python API prints the same line (Python's last-resort handler, no logging set up)
    code = ("import sys; sys.modules['tensorboard'] = None\nimport cobelrun\n"
            f"cobelrun.run('two_afc', {TB_RUN[2:6]!r}, out={str(tmp_path / 'api')!r})\n")  # fmt: skip
    api = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert api.returncode == 0, api.stderr
    assert api.stderr.count("TensorBoard output skipped") == 1, api.stderr


@pytest.mark.parametrize(
    "override",
    ["a.b=3", "a.c=[1,2]", "+a.new=x", "++a.b=5", "++z=1", "~a.b", "~a.b=2", "~a.b=9", "~nope",
     "+a.b=1", "+a={q:1}", "a.nope=1", "a.b={x:1}", "s=str", "lst.0=7", "lst=[3]", "~lst",
     "a@pkg=1", "a.b=null", "+lst=[9]", "d.k=${a.b}", "a.c.x=1", "a.b.c=1"],
)  # fmt: skip
def test_rerun_overrides_behave_as_in_hydra(override):
    """cobel applies value overrides to a saved config with OmegaConf's public API; the result
    (or the error's first line) is what Hydra's own composition gives (imported here, in a
    test only, to compare)."""
    import copy

    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    from cobelrun.config import apply_overrides

    base = OmegaConf.create({"a": {"b": 2, "c": [0]}, "s": "t", "lst": [1, 2], "d": {"k": 0}})
    OmegaConf.set_struct(base, True)
    parsed = OverridesParser.create().parse_overrides([override])
    ours, theirs = copy.deepcopy(base), copy.deepcopy(base)
    try:
        ConfigLoaderImpl._apply_overrides_to_config(parsed, theirs)
        expected = None
    except HydraException as exc:
        expected = str(exc).strip().splitlines()[0]
    except ValueError:  # Hydra lets it through; cobel says which override
        expected = f"Error merging override {override}"
    if expected is None:
        apply_overrides(ours, parsed)
        assert OmegaConf.to_container(ours) == OmegaConf.to_container(theirs)
        assert ours != base
    else:
        with pytest.raises(ConfigError) as err:
            apply_overrides(ours, parsed)
        assert str(err.value) == expected
