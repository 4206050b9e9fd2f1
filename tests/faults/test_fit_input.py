"""`cobel fit` validates its data (issue 31, item 6; issue 36, bad input).

Each bad table is one ``cobel: error:`` line, a non-zero exit and no ``fit.json``. The CLI
runs in-process (typer's runner) so the cases stay fast.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from cobelrun.cli import app
from cobelrun.errors import CobelError
from cobelrun.fit import check_choices, simulate_choices


def _fit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, data: pd.DataFrame, *extra: str):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "choices.csv"
    data.to_csv(path, index=False)
    return CliRunner().invoke(
        app,
        ["fit", "task=two_afc", "agent=q_learning", f"data={path}", *extra],
        catch_exceptions=False,
    )


def _one_line(result) -> str:
    lines = [line for line in result.stderr.strip().splitlines() if line]
    assert result.exit_code != 0, result.stdout
    assert len(lines) == 1 and lines[0].startswith("cobel: error:"), result.stderr
    return lines[0]


GOOD = simulate_choices(60, 0.3, 4.0, seed=1)


@pytest.mark.parametrize(
    "column, values, message",
    [
        ("reward", {3: math.nan}, r"reward must be a finite number, got nan in row 3"),
        ("reward", {5: math.inf}, r"reward must be a finite number, got inf in row 5"),
        ("reward", {0: -math.inf}, r"reward must be a finite number, got -inf in row 0"),
        ("choice", {2: 0.7, 4: 1.7}, r"choice must be an integer \(an action index\), got 0.7 in row 2"),
        ("choice", {1: "left"}, r"choice must be a finite integer \(an action index\), got 'left' in row 1"),
        ("choice", {7: math.nan}, r"choice must be a finite integer"),
        ("state", {0: 1e12}, r"state must lie in 0..3, got 1e\+12 in row 0"),
        ("state", {9: -1}, r"state must lie in 0..3, got -1 in row 9"),
        ("choice", {9: 2}, r"choices 0..2 \(3 actions\) but task two_afc's env has 2 actions"),
    ],
)  # fmt: skip
def test_bad_values_are_one_line_and_write_nothing(tmp_path, monkeypatch, column, values, message):
    data = GOOD.copy().astype({column: object})
    for row, value in values.items():
        data.loc[row, column] = value
    line = _one_line(_fit(tmp_path, monkeypatch, data))
    assert re.search(message, line), line
    assert "choices.csv" in line
    assert not (tmp_path / "fit.json").exists()


@pytest.mark.parametrize(
    "data, message",
    [
        (GOOD.drop(columns="reward"), "has no reward column; it needs choice and reward"),
        (
            GOOD.assign(rt=0.4),
            "unknown column(s) rt; allowed: choice, reward, trial, state, session",
        ),
        (GOOD.iloc[:0], "has no trials"),
    ],
)
def test_bad_tables_are_one_line_and_write_nothing(tmp_path, monkeypatch, data, message):
    assert message in _one_line(_fit(tmp_path, monkeypatch, data))
    assert not (tmp_path / "fit.json").exists()


def test_two_choice_data_against_four_actions_is_refused(tmp_path, monkeypatch):
    """2-choice data was silently fitted against the T-maze's 4 actions."""
    line = _one_line(_fit(tmp_path, monkeypatch, GOOD, "task=tmaze_extinction"))
    assert "choices 0..1 (2 actions) but task tmaze_extinction's env has 4 actions" in line
    assert not (tmp_path / "fit.json").exists()


def test_good_data_writes_finite_numbers(tmp_path, monkeypatch):
    result = _fit(tmp_path, monkeypatch, GOOD)
    assert result.exit_code == 0, result.stderr
    fit = json.loads((tmp_path / "fit.json").read_text())
    assert all(np.isfinite(v) for v in fit["params"].values())
    assert np.isfinite(fit["nll"])


def test_check_choices_without_a_task_caps_the_state_count():
    with pytest.raises(CobelError, match=r"state must lie in 0..99999, got 1e\+12"):
        check_choices(GOOD.assign(state=1e12))


def test_junk_tables_give_a_cobel_error_or_finite_numbers():
    """Hypothesis: tables of mixed junk (strings, NaN, inf, huge and negative numbers, floats)
    in the choice/reward/state/session columns either fit to finite numbers or raise a
    CobelError; nothing else escapes."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from cobelrun.fit import fit_choices

    cell = st.one_of(st.integers(-3, 5), st.floats(allow_nan=True, allow_infinity=True),
                     st.sampled_from(["left", "", "1"]), st.just(1e12), st.none())  # fmt: skip

    @settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(st.tuples(cell, cell, cell, cell), min_size=0, max_size=12),
           st.sampled_from([("choice", "reward"), ("choice", "reward", "state"),
                            ("choice", "reward", "state", "session")]))  # fmt: skip
    def check(rows, cols):
        data = pd.DataFrame([r[: len(cols)] for r in rows], columns=list(cols))
        try:
            fit = fit_choices(data, n_actions=2, n_states=4, n_starts=1, polish=False)
        except CobelError:
            return
        d = fit.to_dict()
        assert np.isfinite(d["nll"]) and all(np.isfinite(v) for v in d["params"].values())
        json.dumps(d, allow_nan=False)

    check()
