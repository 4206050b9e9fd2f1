"""``cobel show``: many places are not named over each other unless asked (``--labels``)."""

from __future__ import annotations

from pathlib import Path

import pytest

import cobelrun.figures
from cobelrun.commands.show import MAX_LABELS, show


@pytest.fixture
def drawn(monkeypatch: pytest.MonkeyPatch) -> list:
    figs: list = []
    real = cobelrun.figures.save_figure

    def keep(fig, out, **kw):
        figs.append((fig.axes[0].get_title(), len(fig.axes[0].texts), fig.get_size_inches()[0],
                     fig.axes[0].get_xlabel()))  # fmt: skip
        return real(fig, out, **kw)

    monkeypatch.setattr(cobelrun.figures, "save_figure", keep)
    return figs


def test_hex_maze_labels_on_demand(drawn: list, tmp_path: Path) -> None:
    show(["env=hex_3d"], tmp_path / "a.png")
    title, texts, width, xlabel = drawn[-1]
    assert texts == 0 and "77 places; --labels names them" in title and xlabel == "x [m]"
    show(["env=hex_3d"], tmp_path / "b.png", labels=True)
    title, texts, width2, _ = drawn[-1]
    assert texts == 77 and width2 > width  # a bigger figure for 77 names


def test_small_maze_named_by_default(drawn: list, tmp_path: Path) -> None:
    show(["env=tmaze_paper"], tmp_path / "t.png")
    _, texts, _, xlabel = drawn[-1]
    assert 0 < texts <= MAX_LABELS and xlabel == "x [cells]"
