"""The figures stage (vprflow.stages.figures) drawing from the toy pipeline's stores."""

from __future__ import annotations

from pathlib import Path

import pytest
from toy_pipeline import stage_path


def figure_stores(pipeline, method: str, figure: str) -> dict[str, str]:
    """The stores a figure rule would get (vprflow.planning.reports.figure_inputs), as run here."""
    from vprflow.planning.reports import FIGURES

    return {name: stage_path(pipeline, name, method) for name in FIGURES[figure].inputs}


@pytest.mark.parametrize(
    ("method", "figure"),
    [
        ("anyloc_vlad", "retrievals"),
        ("anyloc_vlad+mnn", "retrievals"),  # re-ranked and retrieved rows
        ("segvlad", "segment_matches"),
        ("segment_gem", "segment_matches"),
        ("snsm", "support_maps"),
    ],
)
def test_figures_draw_from_the_method_stores(pipeline, tmp_path, method, figure):
    from PIL import Image

    from vprflow.planning.reports import figure_inputs
    from vprflow.stages.figures import draw_figure

    plan, _, _, root = pipeline
    # The plan names the same stores (by key) that this figure is drawn from.
    planned = figure_inputs(plan, "toy", method, figure)
    stores_used = figure_stores(pipeline, method, figure)
    assert planned.keys() == stores_used.keys()
    for name, path in planned.items():
        assert Path(path).name == Path(stores_used[name]).name, name
    settings = {"queries": 3, "top": 2, "wrong_only": False, "explained_queries": 2, "seed": 0}
    out = tmp_path / f"{figure}.png"
    draw_figure(figure, stores_used, str(root / "data"), method, {**settings, "height": 32}, out)
    with Image.open(out) as image:
        assert image.format == "PNG" and min(image.size) > 100


def test_the_recall_plot_draws_each_methods_precision_recall_curve_beside_recall(
    pipeline, tmp_path
):
    from PIL import Image

    from vprflow.stages.figures import plot_recall

    plan, _, recalls, _ = pipeline
    methods = [r.method for r in plan.runs["toy"]]
    out = tmp_path / "recall.png"
    plot_recall("toy", stage_path(pipeline, "dataset"), methods, recalls, str(out))
    with Image.open(out) as image:
        width, height = image.size
    assert width > 1.6 * height  # two panels side by side


def test_a_method_has_the_figures_of_its_aggregator(pipeline):
    from vprflow.core.errors import PlanError
    from vprflow.planning.reports import dataset_outputs, figure_inputs

    plan, _, _, _ = pipeline
    figures = {run.method: run.figures for run in plan.runs["toy"]}
    assert figures["segvlad"] == ("retrievals", "segment_matches")
    assert figures["snsm"] == ("retrievals", "support_maps")
    assert figures["gem"] == ("retrievals",)
    outputs = dataset_outputs(plan, "toy")
    assert "results/plots/recall_toy.png" in outputs
    assert "results/figures/toy/segment_matches/segvlad.png" in outputs
    with pytest.raises(PlanError, match="segment_matches.*'gem'"):
        figure_inputs(plan, "toy", "gem", "segment_matches")
