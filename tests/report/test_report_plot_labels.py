"""Plot labels a surveyor can read (issue 28 point 5): labels of nearby points do not overlap
(deterministic offsets), the track plot's grey map is labelled as the prior map."""

from __future__ import annotations

import numpy as np


def test_label_offsets_stack_nearby_labels_only():
    from minegeo.report.localize_report import label_offsets

    # two candidates 0.1 m apart (the tube's ambiguous pair), one 50 m away, one beside the pair
    xy = np.array([[110.0, 0.0], [110.1, 0.0], [60.0, 0.0], [110.0, 0.5]])
    off = label_offsets(xy, min_sep=4.0)
    assert off == [(4.0, 4.0), (4.0, 14.0), (4.0, 4.0), (4.0, 24.0)]
    assert len(set(off[:2] + off[3:])) == 3  # the three nearby labels all differ
    assert label_offsets(xy, min_sep=4.0) == off  # deterministic


def test_track_plot_labels_the_prior_map(monkeypatch):
    from matplotlib.axes import Axes

    from minegeo.report.intersections_report import plot_track_png

    class KB:
        cloud_points = np.random.default_rng(0).uniform(0, 50, (500, 3))
        invariant_points = np.array([[10.0, 10.0, 0.0], [40.0, 10.0, 0.0]])

        def __len__(self):
            return 2

    labels = []
    real = Axes.legend
    monkeypatch.setattr(Axes, "legend", lambda self, *a, **k: (labels.extend(
        t for t in self.get_legend_handles_labels()[1]), real(self, *a, **k))[1])
    xy = np.column_stack([np.linspace(0, 50, 20), np.full(20, 10.0), np.zeros(20)])
    assert plot_track_png(KB(), xy, np.zeros((0, 3)), None) is not None
    assert any(t.startswith("prior map") for t in labels), labels
