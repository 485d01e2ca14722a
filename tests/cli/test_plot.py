"""`robotmem plot`: the rolling window follows the memory, every point is drawn, every axis is labelled in words."""
from __future__ import annotations

import re

import pytest
import torch
from tensordict import TensorDict

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.cli.plot import memory_figures, plot_memory, rolling_success, success_window


def _memory(path, episodes, steps=5, env="FetchReach-v4"):
    """``episodes`` finished episodes of ``steps`` rows, every third one a success, FetchReach-shaped goals."""
    n = episodes * steps
    gen = torch.Generator().manual_seed(0)
    step = torch.arange(n) % steps
    done = (step == steps - 1).unsqueeze(-1)
    success = ((torch.arange(n) // steps) % 3 == 0).float() * (step == steps - 1)
    rows = TensorDict({"next": {"achieved_goal": torch.rand(n, 3, generator=gen), "done": done,
                                "is_success": success}}, [n])
    with ZarrStorage(path, 10_000, env=env, background=False) as st:
        st.set(slice(0, n), rows)
    return path


def _labels(fig):
    return [(ax.get_xlabel(), ax.get_ylabel()) for ax in fig.axes]


def _assert_words(fig):
    for xlabel, ylabel in _labels(fig):
        for text in (xlabel, ylabel):
            assert re.search(r"[a-z]{4,}", text), f"axis label without words: {text!r}"
            assert not re.fullmatch(r"\s*\[\d+\]\s*", text)


def test_twenty_episodes_draw_twenty_points_with_a_window_that_fits(tmp_path):
    path = _memory(str(tmp_path / "m.zarr"), episodes=20)
    figures = memory_figures(path)
    try:
        success = figures["success.png"]
        (ax,) = success.axes[:1]
        line = ax.get_lines()[0]
        assert len(line.get_xdata()) == len(line.get_ydata()) == 20  # before: 1 point (a 20-episode window)
        assert "rolling mean over 2 episodes" in line.get_label()
        assert ax.get_ylabel() == "success rate\n(rolling mean over 2 episodes)"
        assert ax.get_xlabel() == "finished episode (write order)"
        assert "over 2" in ax.get_title()
        expected = rolling_success(torch.tensor([1.0 if e % 3 == 0 else 0.0 for e in range(20)]).numpy(), 2)
        assert line.get_ydata().tolist() == pytest.approx(expected.tolist())
        goals = figures["goals.png"]
        assert _labels(goals) == [("achieved goal x (m), next/achieved_goal[0]",
                                   "achieved goal y (m), next/achieved_goal[1]")]
        for fig in figures.values():
            _assert_words(fig)
    finally:
        import matplotlib.pyplot as plt

        for fig in figures.values():
            plt.close(fig)


def test_window_grows_with_the_memory_and_can_be_given(tmp_path):
    assert [success_window(n) for n in (0, 5, 20, 200, 499, 500, 10_000)] == [1, 1, 2, 20, 49, 50, 50]
    assert success_window(20, window=50) == 20 and success_window(600, window=7) == 7
    path = _memory(str(tmp_path / "m.zarr"), episodes=600, steps=1, env="MyTask-v0")
    figures = memory_figures(path, window=7)
    try:
        ax = figures["success.png"].axes[0]
        assert len(ax.get_lines()[0].get_xdata()) == 600 and "over 7 episodes" in ax.get_ylabel()
        goal_ax = figures["goals.png"].axes[0]
        assert goal_ax.get_xlabel() == "achieved goal x, next/achieved_goal[0]"  # no unit claimed for an unknown env
    finally:
        import matplotlib.pyplot as plt

        for fig in figures.values():
            plt.close(fig)
    assert [p.rsplit("/", 1)[-1] for p in plot_memory(path, str(tmp_path / "out"))] == ["success.png", "goals.png"]
