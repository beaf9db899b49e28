"""What the figures show, read back from the matplotlib figure before it is saved: the
lowest point of each sweep curve marked and named, the front's designs as markers, the
heatmap's optimum starred, units on every axis, one style for all."""

import numpy as np
import pytest

from recoil_jax.apps import _figures


@pytest.fixture
def saved(monkeypatch):
    """The figures `_figures` saves, kept open for inspection."""
    figures = []

    def keep(fig, path):
        figures.append(fig)
        return path

    monkeypatch.setattr(_figures, "_save", keep)
    return figures


def test_sweep_curves_mark_and_name_their_lowest_point(saved):
    gap = np.linspace(0.0, 0.12, 121)
    force = 5500.0 + 2e5 * (gap - 0.062) ** 2
    _figures.plot_series(
        {"m = 1500 kg": (gap, force)},
        "unused.png",
        xlabel="gap (mm)",
        ylabel="peak anchoring force (N)",
        xscale=1e3,
        minima="N",
    )
    (ax,) = saved[0].axes
    (text,) = [t.get_text() for t in ax.get_legend().get_texts()]
    assert text == "m = 1500 kg: min 5500 N at 62"
    marker = [line for line in ax.lines if line.get_marker() == "v"]
    assert len(marker) == 1 and marker[0].get_xydata().tolist() == [[62.0, 5500.0]]
    assert ax.get_xlabel() == "gap (mm)" and ax.get_ylabel() == "peak anchoring force (N)"
    assert not ax.spines["top"].get_visible()  # the shared style


def test_front_points_carry_markers(saved):
    _figures.plot_series(
        {"best design": ([100.0, 500.0, 1500.0], [6900.0, 6500.0, 5324.0])},
        "unused.png",
        xlabel="m (kg)",
        ylabel="peak anchoring force (N)",
        markers=True,
    )
    (line,) = saved[0].axes[0].lines
    assert line.get_marker() == "o"


def test_heatmap_stars_the_lowest_point(saved):
    gap, mass = np.linspace(0.0, 0.12, 13), np.array([500.0, 1000.0, 1500.0])
    values = np.add.outer(-mass, 1e4 * (gap - 0.06) ** 2)  # lowest at m = 1500, gap = 0.06
    values[0, 0] = np.nan  # a failed point stays blank
    _figures.plot_heatmap(
        gap, mass, values, "unused.png", xlabel="gap (m)", ylabel="m (kg)", label="F (N)"
    )
    ax = saved[0].axes[0]
    (star,) = [line for line in ax.lines if line.get_marker() == "*"]
    np.testing.assert_allclose(star.get_xydata(), [[0.06, 1500.0]])
    assert "lowest: -1500 at gap (m) = 0.06, m (kg) = 1500" in ax.get_title()
