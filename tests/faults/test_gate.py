"""The instantiation gate (issue 31, item 1): configs are data, not code.

Every ``_target_`` of a config (command line, ``./conf``, ``-cd``, a run folder's
``config.yaml``) is checked against an allowlist before anything is imported or built. The
code-execution cases of the issue run a real payload (``touch CANARY``, ``shutil.copyfile``)
that must not happen: the canary file must not appear, the exit code is 2 with one line, and no
run folder is written.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from cobelrun.compose import composer, validate
from cobelrun.config import factory, instantiate, validate_node
from cobelrun.errors import ConfigError
from cobelrun.targets import (
    BUILTIN,
    ENV_VAR,
    allow,
    check_config,
    check_target,
    is_allowed,
    parse_patterns,
)
from tests.conftest import ROOT

TINY = ["task=tmaze_extinction", "task.runs=1", "task.protocol.phases.0.trials=3",
        "task.protocol.phases.1.trials=3"]  # fmt: skip
REFUSED = "is not an allowed target"


@pytest.fixture(autouse=True)
def _no_user_patterns(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


def one_line_error(proc) -> str:
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert len(lines) == 1 and lines[0].startswith("cobel: error:"), proc.stderr
    return lines[0]


def _targets(node, found):
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "_target_":
                found.append(value)
            _targets(value, found)
    elif isinstance(node, list):
        for value in node:
            _targets(value, found)
    return found


# -- the allowlist ----------------------------------------------------------------------------
def test_every_target_in_conf_is_allowed():
    files = sorted((ROOT / "conf").rglob("*.yaml"))
    found = []
    for path in files:
        found += _targets(OmegaConf.to_container(OmegaConf.load(path)), [])
    assert len(set(found)) >= 30, sorted(set(found))
    assert [t for t in found if not is_allowed(t)] == []


def test_builtin_targets_resolve_to_real_callables():
    """The curated list names things that exist (a typo there would refuse a real config)."""
    from hydra.utils import get_object

    for path in BUILTIN:
        assert callable(get_object(path)), path


@pytest.mark.parametrize(
    "choice",
    ["hydra/launcher=joblib", "hydra/launcher=local", "hydra/launcher=slurm",
     "hydra/launcher=submitit_local", "hydra/launcher=submitit_slurm", "hydra/launcher=basic",
     "hydra/sweeper=basic", "hydra/sweeper=optuna", "hydra/sweeper=cobel",
     "hydra/sweeper/sampler=random", "hydra/sweeper/sampler=cmaes"],
)  # fmt: skip
def test_hydra_launchers_and_sweepers_are_allowed(choice):
    extra = ["hydra/sweeper=optuna"] if choice.startswith("hydra/sweeper/sampler") else []
    with composer() as compose:  # the gate runs inside compose: a refusal would raise here
        cfg = compose([*TINY, *extra, choice], return_hydra_config=True)
    targets = _targets(OmegaConf.to_container(cfg.hydra), [])
    assert targets and all(is_allowed(t) for t in targets), targets


@pytest.mark.parametrize(
    "target",
    ["hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher",
     "hydra_plugins.hydra_ray_launcher.ray_aws_launcher.RayAWSLauncher",
     "hydra.experimental.callbacks.LogJobReturnCallback"],
)  # fmt: skip
def test_documented_plugins_not_installed_here_are_allowed(target):
    assert is_allowed(target)


DANGEROUS = [
    "uuid._get_command_stdout", "shutil.copyfile", "shutil.rmtree", "os.system", "os.remove",
    "builtins.eval", "builtins.exec", "builtins.open", "subprocess.run", "pickle.loads",
    "importlib.import_module", "pathlib.Path.write_text",
    "cobelrun.io.atomic.atomic_write_text", "cobelrun.io.atomic.atomic_path",
    "cobelrun.io.manifest.Manifest", "cobelrun.runner.run", "cobelrun.api.run",
    "cobelrun.api.rerun", "cobelrun.io.sweep_collect.collect", "cobelrun.hydra_app.launch",
    "cobelrun.envs.world.np.save", "cobelrun.envs.GridWorldEnv.__init__",
]  # fmt: skip


@pytest.mark.parametrize("target", DANGEROUS)
def test_dangerous_targets_are_refused(target):
    assert not is_allowed(target)
    with pytest.raises(ConfigError, match=f"env._target_ '{target}' {REFUSED}"):
        check_target("env._target_", target)


def test_the_refusal_says_how_to_allow_it():
    with pytest.raises(ConfigError) as err:
        check_target("env._target_", "mypkg.envs.MyEnv")
    msg = str(err.value)
    assert "--allow-target mypkg.envs.MyEnv" in msg and f"{ENV_VAR}=mypkg.envs.MyEnv" in msg
    assert "cobel.targets" in msg and "\n" not in msg


def test_user_patterns_and_wildcards(monkeypatch):
    monkeypatch.setenv(ENV_VAR, "mypkg.envs.*,other.Thing:third.*")
    assert is_allowed("mypkg.envs.MyEnv") and is_allowed("mypkg.envs.sub.MyEnv")
    assert is_allowed("other.Thing") and is_allowed("third.x")
    assert not is_allowed("other.Thing2") and not is_allowed("mypkg.envsX.A")
    # a wildcard never reaches private or dunder parts
    assert not is_allowed("mypkg.envs._private") and not is_allowed("mypkg.envs.A.__init__")
    assert not is_allowed("mypkg.envs")  # the package itself is no callable to build


@pytest.mark.parametrize("bad", ["*", "mypkg.*.x", "a..b", "os.system()", "x y.*z"])
def test_malformed_patterns_are_one_line(bad):
    with pytest.raises(ConfigError, match="is not a target pattern"):
        parse_patterns([bad], "--allow-target")


def test_allow_extends_the_environment_for_child_processes(monkeypatch):
    monkeypatch.setenv(ENV_VAR, "a.B")
    allow(["c.*", "a.B"])
    assert os.environ[ENV_VAR] == "a.B,c.*"


def test_a_wildcard_does_not_reach_imports_through_a_nested_node(monkeypatch, tmp_path):
    """The same for a target Hydra builds itself (in a list inside a node): checked after the
    import too, before Hydra calls it."""
    from cobelrun.config import instantiate

    monkeypatch.setenv(ENV_VAR, "pathlib.*")
    node = {"_target_": "cobelrun.monitors.RewardMonitor",
            "x": [{"_target_": "pathlib.urlquote_from_bytes", "_args_": [b"a"]}]}  # fmt: skip
    with pytest.raises(ConfigError, match=r"x\[0\]\._target_ 'pathlib.urlquote_from_bytes' is "
                       r"defined in urllib\.parse, not in pathlib"):  # fmt: skip
        instantiate("task.monitors.m", node)


def test_a_wildcard_does_not_reach_what_the_package_imports(monkeypatch):
    """``pathlib.*`` allows what pathlib defines, not ``pathlib.urlquote_from_bytes`` (defined in
    urllib.parse, which pathlib imports): the object's module is checked after the import."""
    monkeypatch.setenv(ENV_VAR, "pathlib.*")
    validate_node("env", {"_target_": "pathlib.PurePosixPath"})
    with pytest.raises(ConfigError, match=r"is defined in urllib\.parse, not in pathlib"):
        validate_node("env", {"_target_": "pathlib.urlquote_from_bytes"})


# -- the gate walks the whole config before anything is built -----------------------------------
@pytest.mark.parametrize(
    "override, where",
    [
        ("env._target_=shutil.copyfile", "env._target_"),
        ("+task.monitors.x={_target_: cobelrun.monitors.RewardMonitor, y: [{_target_: os.getcwd}]}",
         r"task.monitors.x.y\[0\]._target_"),
        ("+env.extra=[[{_target_: builtins.eval}]]", r"env.extra\[0\]\[0\]._target_"),
        ("+hydra.callbacks.x._target_=shutil.copyfile", "hydra.callbacks.x._target_"),
        ("hydra.launcher._target_=os.system", "hydra.launcher._target_"),
        ("hydra.sweeper._target_=os.system", "hydra.sweeper._target_"),
    ],
)  # fmt: skip
def test_targets_anywhere_are_refused_while_composing(override, where):
    with pytest.raises(ConfigError, match=f"{where} .* {REFUSED}"):
        validate([*TINY, override], multirun=False)


@pytest.mark.parametrize(
    "override, where",
    [("+hydra.job_logging.handlers.x.class=shutil.copyfile", "logging class"),
     ("+hydra.hydra_logging.handlers.x.class=os.system", "logging class"),
     ("hydra.job_logging.handlers.console.stream=ext://antigravity", "logging object")],
)  # fmt: skip
def test_logging_config_classes_are_gated(override, where):
    with pytest.raises(ConfigError, match=f"is not an allowed {where}"):
        validate([*TINY, override], multirun=False)


def test_an_interpolated_target_is_refused():
    """A ``_target_`` is a literal dotted path: an interpolation could pick any value."""
    with pytest.raises(
        ConfigError, match=r"env\._target_ must name a class or function as a dotted"
    ):
        validate([*TINY, "env._target_='${oc.env:HOME}'"], multirun=False)


@pytest.mark.parametrize(
    "override, message",
    [("hydra.job_logging.handlers.file.filename=/tmp/x/.bashrc",
      "hydra.job_logging.handlers.file.filename must name a log file inside the run folder"),
     ("hydra.job_logging.handlers.file.filename='${hydra.runtime.output_dir}/../../x.log'",
      "must name a log file inside the run folder"),
     ("hydra.output_subdir=/tmp/x", "hydra.output_subdir must be a folder name inside the run"),
     ("hydra.output_subdir=../..", "hydra.output_subdir must be a folder name inside the run")],
)  # fmt: skip
def test_hydra_cannot_be_made_to_write_outside_the_run_folder(override, message):
    with pytest.raises(ConfigError, match=message):
        validate([*TINY, override], multirun=False)


def test_hydras_own_logging_choices_pass():
    for choice in ("hydra/hydra_logging=hydra_debug", "hydra/job_logging=default",
                   "hydra/job_logging=stdout"):  # fmt: skip
        validate([*TINY, choice], multirun=False)


def test_logging_factories_are_gated():
    """``()`` (a factory in logging.config.dictConfig) cannot be given as an override; a
    ``-cd`` folder or ``./conf`` can write it."""
    cfg = {"hydra": {"job_logging": {"formatters": {"x": {"()": "os.getcwd"}}}}}
    with pytest.raises(ConfigError, match=r"hydra.job_logging.formatters.x.\(\) 'os.getcwd'"):
        check_config(OmegaConf.create(cfg))
    check_config(OmegaConf.create({"hydra": {"job_logging": {"formatters": {"x": {
        "()": "colorlog.ColoredFormatter"}}}}}))  # fmt: skip


def test_every_swept_target_is_checked_not_only_the_first_jobs():
    with pytest.raises(ConfigError, match=f"'uuid._get_command_stdout' {REFUSED}"):
        validate([*TINY, "env._target_=cobelrun.envs.GridWorldEnv,uuid._get_command_stdout"],
                 multirun=True)  # fmt: skip


def test_a_swept_node_with_a_target_fails_its_job_only(cobel, tmp_path):
    """A swept value that is a whole node (not a ``_target_`` key) is checked in the job: that
    job fails with the one line, the others run, the payload never does."""
    canary = tmp_path / "pwned"
    sweep = tmp_path / "sweep"
    bad = f"{{_target_: uuid._get_command_stdout, _args_: [touch, '{canary}']}}"
    good = "{_target_: cobelrun.monitors.RewardMonitor}"
    proc = cobel("run", "-m", *TINY, f"++task.monitors.reward=choice({good},{bad})",
                 f"hydra.sweep.dir={sweep}", "hydra/launcher=basic", "--quiet")  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    import json

    jobs = [json.loads((sweep / str(i) / "job.json").read_text()) for i in (0, 1)]
    assert [j["status"] for j in jobs] == ["completed", "failed"]
    assert "'uuid._get_command_stdout' is not an allowed target" in jobs[1]["error"]
    assert not canary.exists()


def test_instantiate_and_factory_refuse_too(tmp_path):
    """Defence in depth: the library's own builders refuse, whoever calls them."""
    canary = tmp_path / "canary"
    node = {"_target_": "uuid._get_command_stdout", "_args_": ["touch", str(canary)]}
    for build in (instantiate, factory):
        with pytest.raises(ConfigError, match=REFUSED):
            build("env", node)
    nested = {"_target_": "cobelrun.monitors.RewardMonitor", "x": {"y": [node]}}
    with pytest.raises(ConfigError, match=REFUSED):
        instantiate("task.monitors.m", nested)
    assert not canary.exists()


def test_check_config_passes_a_whole_builtin_config():
    with composer() as compose:
        cfg = compose(["task=place_cells"], return_hydra_config=True)
    check_config(cfg)


# -- the cases through the real CLI, with canaries ------------------------------------
def test_cli_shell_through_a_helper_is_refused(cobel, tmp_path):
    canary = tmp_path / "pwned"
    proc = cobel("run", *TINY, "env._target_=uuid._get_command_stdout", "~env.world",
                 f"+env._args_=[touch,{canary}]")  # fmt: skip
    line = one_line_error(proc)
    assert "env._target_ 'uuid._get_command_stdout' is not an allowed target" in line
    assert "--allow-target uuid._get_command_stdout" in line
    assert not canary.exists()
    assert not (tmp_path / "results").exists()


def test_cli_copyfile_is_refused(cobel, tmp_path):
    src, dst = tmp_path / "secret", tmp_path / "copied"
    src.write_text("x")
    proc = cobel("run", *TINY, "env._target_=shutil.copyfile", "~env.world",
                 f"+env.src={src}", f"+env.dst={dst}")  # fmt: skip
    assert "'shutil.copyfile' is not an allowed target" in one_line_error(proc)
    assert not dst.exists() and not (tmp_path / "results").exists()


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    from cobelrun.api import run

    out = tmp_path_factory.mktemp("run") / "run"
    run("tmaze_extinction", ["task.runs=1", "task.protocol.phases.0.trials=2",
                             "task.protocol.phases.1.trials=2"], out)  # fmt: skip
    return out


def _tampered(run_folder: Path, where: Path, canary: Path) -> Path:
    import shutil

    folder = where / "shared"
    shutil.copytree(run_folder, folder)
    cfg = OmegaConf.load(folder / "config.yaml")
    cfg.env = {"_target_": "uuid._get_command_stdout", "_args_": ["touch", str(canary)]}
    OmegaConf.save(cfg, folder / "config.yaml")
    return folder


def test_rerun_of_a_tampered_run_folder_is_refused(cobel, tmp_path, run_folder):
    canary = tmp_path / "pwned"
    folder = _tampered(run_folder, tmp_path, canary)
    before = sorted(p.name for p in folder.iterdir())
    proc = cobel("rerun", str(folder), "--out", str(tmp_path / "again"))
    line = one_line_error(proc)
    assert f"{folder / 'config.yaml'}: env._target_ 'uuid._get_command_stdout'" in line
    assert not canary.exists() and not (tmp_path / "again").exists()
    assert sorted(p.name for p in folder.iterdir()) == before


def test_run_with_a_tampered_folder_as_config_dir_is_refused(cobel, tmp_path, run_folder):
    canary = tmp_path / "pwned"
    folder = _tampered(run_folder, tmp_path, canary)
    proc = cobel("run", "-cd", str(folder), "-cn", "config")
    assert "'uuid._get_command_stdout' is not an allowed target" in one_line_error(proc)
    assert not canary.exists() and not (tmp_path / "results").exists()


def test_api_rerun_is_gated(tmp_path, run_folder):
    from cobelrun.api import rerun

    canary = tmp_path / "pwned"
    folder = _tampered(run_folder, tmp_path, canary)
    with pytest.raises(ConfigError, match=REFUSED):
        rerun(folder, [], tmp_path / "again")
    assert not canary.exists() and not (tmp_path / "again").exists()


def test_a_run_folder_cannot_allow_its_own_targets(cobel, tmp_path, run_folder):
    """Nothing inside a folder widens the list: a .env-like file or a key in config.yaml is
    just data."""
    canary = tmp_path / "pwned"
    folder = _tampered(run_folder, tmp_path, canary)
    cfg = OmegaConf.load(folder / "config.yaml")
    cfg.allow_targets = ["uuid.*"]
    OmegaConf.save(cfg, folder / "config.yaml")
    (folder / ENV_VAR).write_text("uuid.*")
    proc = cobel("rerun", str(folder), "--out", str(tmp_path / "again"), cwd=folder)
    assert REFUSED in one_line_error(proc) and not canary.exists()


# -- plugins: the entry-point group cobel.targets ---------------------------------------------
PLUGIN = '''
import pyarrow as pa
from cobelrun.monitors import Monitor, Table


class StepsTwiceMonitor(Monitor):
    """Twice each trial's steps, as a column of the trials table."""

    def tables(self):
        return [Table("trials", (pa.field("steps_twice", pa.int64()),))]

    def on_batch(self, batch, info):
        return {"trials": {"steps_twice": 2 * batch.steps}}
'''


def _plugin(where: Path) -> Path:
    site = where / "site"
    (site / "cobelplug").mkdir(parents=True)
    (site / "cobelplug" / "__init__.py").write_text(PLUGIN)
    info = site / "cobelplug-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: cobelplug\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[cobel.targets]\ncobelplug = cobelplug\n")
    return site


def test_a_plugin_registers_its_targets_through_entry_points(cobel, tmp_path):
    import pandas as pd

    site = _plugin(tmp_path)
    out = tmp_path / "run"
    args = ["run", *TINY, "+task.monitors.twice._target_=cobelplug.StepsTwiceMonitor",
            f"hydra.run.dir={out}", "--quiet"]  # fmt: skip
    refused = cobel(*args)  # without the plugin installed: refused, nothing written
    assert "'cobelplug.StepsTwiceMonitor' is not an allowed target" in one_line_error(refused)
    assert not out.exists()
    proc = cobel(*args, env={"PYTHONPATH": str(site)})
    assert proc.returncode == 0, proc.stderr
    trials = pd.read_parquet(out / "trials.parquet")
    assert (trials["steps_twice"] == 2 * trials["steps"]).all()


def test_entry_points_are_read_without_importing_the_plugin(tmp_path):
    site = _plugin(tmp_path)
    (site / "cobelplug" / "__init__.py").write_text("raise SystemExit('imported!')\n")
    code = ("from cobelrun.targets import allowed, is_allowed; "
            "print(is_allowed('cobelplug.Anything'), is_allowed('cobelplug._x'), "
            "[s for p, s in allowed() if p == 'cobelplug.*'])")  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": f"{site}{os.pathsep}{ROOT}"},
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "True False [\"entry point 'cobelplug' of cobelplug\"]"


def test_cli_allow_target_option_and_environment(cobel, tmp_path):
    site = _plugin(tmp_path / "p")
    (site / "cobelplug-0.1.dist-info" / "entry_points.txt").unlink()  # not a plugin now
    out = tmp_path / "run"
    args = ["run", *TINY, "+task.monitors.twice._target_=cobelplug.StepsTwiceMonitor",
            f"hydra.run.dir={out}", "--quiet"]  # fmt: skip
    env = {"PYTHONPATH": str(site)}
    assert cobel(*args, "--allow-target", "cobelplug.*", env=env).returncode == 0
    out2 = tmp_path / "run2"
    args[-2] = f"hydra.run.dir={out2}"
    proc = cobel(*args, env={**env, ENV_VAR: "cobelplug.StepsTwiceMonitor"})
    assert proc.returncode == 0, proc.stderr
    bad = cobel(*args, "--allow-target", "cobelplug.*.x")
    assert "is not a target pattern" in one_line_error(bad)


# -- values that are code by another route ---------------------------------------------------
@pytest.mark.parametrize("name", ["PYTHONPATH", "LD_PRELOAD", "PATH", "COBEL_ALLOW_TARGETS",
                                  "BASH_ENV", "ld_audit"])  # fmt: skip
def test_env_set_may_not_choose_the_code_a_job_loads(name):
    """``hydra.job.env_set`` is applied in each job: a config (a ``-cd`` folder, ``./conf``)
    must not point Python or the dynamic linker at other code, nor widen the gate."""
    with composer() as compose, pytest.raises(ConfigError, match=rf"may not set {name}"):
        compose([*TINY, f"+hydra.job.env_set.{name}=/tmp/elsewhere"], return_hydra_config=True)


def test_env_set_of_ordinary_variables_is_kept():
    with composer() as compose:
        cfg = compose([*TINY, "+hydra.job.env_set.OMP_NUM_THREADS=1"], return_hydra_config=True)
    assert cfg.hydra.job.env_set.OMP_NUM_THREADS == "1"


def test_a_sweep_names_the_shell_lines_its_launcher_runs(capsys):
    """submitit's ``setup`` lines are shell code by design: a sweep says which it will run."""
    validate([*TINY, "seed=0,1", "hydra/launcher=slurm",
              "hydra.launcher.setup=[module load python,echo ready]"], multirun=True)  # fmt: skip
    err = capsys.readouterr().err
    assert (
        "hydra.launcher.setup runs these shell lines in every job: 'module load python'; 'echo ready'"
        in err
    )
