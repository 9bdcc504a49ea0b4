"""Plots that explain themselves: the prior behind the intervals, the identified body named,
clearance.png titled with what the distance is between and the phases shaded, Fig. 5's method named."""

import numpy as np
import pytest
from safesysid import report


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions would save, kept open for inspection."""
    kept = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path: kept.append(fig) or path)
    return kept


def _labels(fig):
    return {text for ax in fig.axes for text in ax.get_legend_handles_labels()[1]}


PRIOR = (np.array([1.2, -0.4, -0.4, -1.0] + [-0.2] * 6), np.array([5.2, 0.4, 0.4, -0.1] + [0.2] * 6))


def test_the_identified_body_is_named():
    text = report.identified_body_text(3.094, "4lb", 1.814)
    assert text == "identified body: last link + gripper 1.280 kg + 4lb dumbbell 1.814 kg = 3.094 kg"
    assert "no payload" in report.identified_body_text(1.28, None, None)


def test_intervals_and_mass_show_the_prior(figures):
    nominal, lo, hi = np.full(10, 0.1), PRIOR[0] / 2, PRIOR[1] / 2
    report.plot_intervals("x.png", nominal, lo, upper=hi, truth=nominal, title="t", prior=PRIOR)
    report.plot_estimate_history(
        "m.png", [0.0, 1.5], [nominal] * 2, lower=[PRIOR[0], lo], upper=[PRIOR[1], hi], prior=PRIOR, title="body"
    )
    assert all("prior" in _labels(fig) for fig in figures)
    assert figures[1].axes[0].get_title() == "body"


def test_clearance_names_what_it_measures_and_shades_the_phases(figures):
    phases = [("identification", 0.0, 7.5), ("task", 7.5, 10.0)]
    report.plot_clearance("c.png", np.linspace(0, 10, 50), np.full(50, 0.1), phases=phases)
    ax = figures[0].axes[0]
    assert "links' own shapes" in ax.get_title() and "obstacles" in ax.get_title()
    assert len([p for p in ax.patches if p.get_alpha() is not None]) == len(phases)


def test_a_single_method_keeps_its_label(figures):
    report.plot_intervals_side_by_side("f.png", {"ours": (np.zeros(10), -np.ones(10), np.ones(10))})
    assert [t.get_text() for t in figures[0].axes[0].get_xticklabels()] == ["ours"]
