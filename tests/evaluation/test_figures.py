"""The report's figure functions on small arrays: frame colours, segment colours that
match between a query and its reference, recall curves against a direct count."""

from __future__ import annotations

import re

import numpy as np
import pytest
from PIL import Image

from vprflow.aggregation.segvlad import _source_index
from vprflow.evaluation import figures
from vprflow.stages.figures import segment_matches


def test_frames_are_green_for_correct_red_for_wrong_and_leave_the_inside():
    image = np.full((20, 30, 3), 0.5, np.float32)
    for correct, colour in ((True, figures.CORRECT), (False, figures.WRONG)):
        out = figures.framed(image, figures.frame_colour(correct), 3)
        border = np.ones((20, 30), bool)
        border[3:-3, 3:-3] = False
        expected = np.broadcast_to(np.float32(colour), (border.sum(), 3))
        np.testing.assert_array_equal(out[border], expected)  # stored as float32
        np.testing.assert_array_equal(out[~border], image[~border])
    assert figures.frame_colour(None) == figures.NEUTRAL
    # Green is green and red is red: the dominant channel.
    assert np.argmax(figures.CORRECT) == 1 and np.argmax(figures.WRONG) == 0
    np.testing.assert_array_equal(figures.framed(image, figures.WRONG, 0), image)


def test_upsampled_masks_use_segvlads_nearest_mapping():
    rng = np.random.default_rng(0)
    masks = rng.random((3, 5, 7)) > 0.5
    out = figures.upsample_masks(masks, 12, 17)
    rows, cols = _source_index(12, 5), _source_index(17, 7)
    for s in range(3):
        np.testing.assert_array_equal(out[s], masks[s][np.ix_(rows, cols)])


def test_the_segment_figure_numbers_the_most_similar_matched_pairs_only():
    matches = [figures.SegmentMatch(i, i % 3 if i % 4 else None, 0.5 + i / 100) for i in range(30)]
    shown = figures.shown_pairs(matches)
    assert len(shown) == figures.MAX_PAIRS
    assert all(m.reference_segment is not None for m in shown)
    kept = sorted((m.similarity for m in matches if m.reference_segment is not None), reverse=True)
    assert [m.similarity for m in shown] == kept[: figures.MAX_PAIRS]
    palette = figures.pair_palette()
    gaps = np.linalg.norm(palette[:, None] - palette[None], axis=2)[
        np.triu_indices(len(palette), 1)
    ]
    assert len(palette) == figures.MAX_PAIRS and gaps.min() > 0.2  # told apart


def test_outlined_segments_keep_the_scene_and_draw_their_edge_in_full_colour():
    image = np.full((12, 16, 3), 0.5, np.float32)
    masks = np.zeros((2, 6, 8), bool)
    masks[0, 1:5, 1:5] = True  # upsampled x2: rows 2..9, columns 2..9
    colour = np.array([1.0, 0.0, 0.0])
    out = figures.outline_segments(image, masks, {0: colour}, alpha=0.25)
    np.testing.assert_allclose(out[2, 5], colour, atol=1e-6)  # on the edge
    np.testing.assert_allclose(out[6, 6], 0.75 * 0.5 + 0.25 * colour, atol=1e-6)  # tinted
    np.testing.assert_array_equal(out[0, 0], image[0, 0])  # outside: untouched
    np.testing.assert_array_equal(out[:, 12:], image[:, 12:])  # segment 1 not drawn


def test_a_segment_number_sits_inside_its_segment_even_when_concave():
    mask = np.zeros((20, 20), bool)
    mask[2:18, 2:6] = True
    mask[14:18, 2:18] = True  # an L: its centroid lies outside it
    x, y = figures.label_point(mask)
    assert mask[int(y), int(x)]


def test_segment_matches_take_the_nearest_segment_inside_the_reference_image():
    rng = np.random.default_rng(1)
    descriptors = rng.normal(size=(20, 6)).astype(np.float32)
    # Query segments are rows 15..17; the top-1 reference owns rows 4..8.
    indices = np.array([[12, 6, 5, -1], [1, 2, 3, 9], [8, 4, -1, -1]])
    matches = segment_matches(range(15, 18), indices, range(4, 8), descriptors)
    assert [m.reference_segment for m in matches] == [2, None, 0]  # local numbers
    for match, row, ref in ((matches[0], 15, 6), (matches[2], 17, 4)):
        q, r = descriptors[row].astype(np.float64), descriptors[ref].astype(np.float64)
        expected = q @ r / (np.linalg.norm(q) * np.linalg.norm(r))
        assert match.similarity == pytest.approx(expected, abs=1e-12)


def test_recall_curve_counts_first_correct_ranks_of_evaluated_queries():
    rng = np.random.default_rng(2)
    first = rng.integers(-1, 30, size=200)
    evaluated = rng.random(200) > 0.2
    curve = figures.recall_curve(first, evaluated, 25)
    for n in (1, 5, 13, 25):
        direct = np.mean([0 <= f < n for f, e in zip(first, evaluated, strict=True) if e])
        assert curve[n - 1] == pytest.approx(direct, abs=1e-12)
    assert np.all(np.diff(curve) >= 0)
    assert figures.recall_curve(first, np.zeros(200, bool), 5).tolist() == [0.0] * 5


def test_sampled_queries_are_deterministic_sorted_and_from_the_candidates():
    candidates = np.arange(3, 100, 2)
    a = figures.sample_queries(candidates, 7, seed=4)
    assert np.array_equal(a, figures.sample_queries(candidates, 7, seed=4))
    assert np.all(np.diff(a) > 0) and set(a) <= set(candidates)
    assert not np.array_equal(a, figures.sample_queries(candidates, 7, seed=5))
    np.testing.assert_array_equal(figures.sample_queries(candidates[:3], 7, 0), candidates[:3])


def test_figures_are_written_whole_as_png(tmp_path):
    rows = [
        figures.RetrievalRow(
            np.zeros((30, 40, 3), np.float32),
            "q0",
            [np.ones((30, 40, 3), np.float32)] * 2,
            ["r0", "r1"],
            [True, False],
        )
    ]
    out = tmp_path / "deep" / "montage.png"
    figures.save_figure(figures.retrieval_figure(rows, "test", height=24), out)
    with Image.open(out) as image:
        assert image.format == "PNG" and image.size[0] > 100
    assert [p.name for p in out.parent.iterdir()] == ["montage.png"]  # no temporary left
    curves = {"a": np.linspace(0.2, 1, 10), "b": np.linspace(0.1, 0.9, 10)}
    figures.save_figure(figures.recall_curve_figure(curves, "t", [1, 5, 10]), tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 1000


def test_recall_table_page_shows_each_method_its_recall_and_marks_the_best():
    rows = [
        {"dataset": "d", "method": "a<b", "aggregator": "x", "recall@1": "0.500000",
         "recall@5": "0.900000", "n_queries": "10", "ground_truth": "pairs"},
        {"dataset": "d", "method": "c", "aggregator": "y", "recall@1": "0.700000",
         "recall@5": "0.800000", "n_queries": "10", "ground_truth": "pairs"},
    ]  # fmt: skip
    page = figures.recall_table_html(rows, "d: Recall@N", ["counted: 10 queries"])
    assert page.count("<tr>") == 3  # header and one row per method
    assert "<td>a&lt;b</td>" in page  # names are escaped
    assert "<b>0.700</b>" in page and "<b>0.900</b>" in page
    assert "<b>0.500</b>" not in page and "<td>0.800</td>" in page
    assert "<th title='n_queries'>queries</th>" in page and "counted: 10 queries" in page
    assert "ground_truth'>" not in page  # one rule per dataset: said in the notes


def test_recall_table_page_shows_map_precision_recall_and_cost_and_bolds_only_scores():
    base = {
        "dataset": "d",
        "aggregator": "x",
        "recall@1": "0.5",
        "map@5": "0.4",
        "auc_pr": "0.6",
        "recall_at_100_precision": "0.1",
        "extended_precision": "0.55",
        "descriptor_bytes_per_image": "2048",
        "search_ms_per_query": "0.2",
        "rerank_ms_per_query": "",
        "segvlad.order": "3",
    }
    rows = [
        {**base, "method": "a", "reranker": ""},
        {**base, "method": "a+mnn", "reranker": "mnn", "auc_pr": "0.8",
         "descriptor_bytes_per_image": "4096", "rerank_ms_per_query": "12.5"},
    ]  # fmt: skip
    page = figures.recall_table_html(rows, "d", [])
    # Short headings, each titled with its CSV column (the method's row names its
    # aggregator and re-ranker).
    header = re.findall(r"<th title='([^']*)'>([^<]*)</th>", page)
    assert header == [
        ("method", "method"), ("recall@1", "R@1"), ("map@5", "mAP@5"), ("auc_pr", "AUC-PR"),
        ("recall_at_100_precision", "R at P=1"), ("extended_precision", "EP"),
        ("descriptor_bytes_per_image", "bytes / image"),
        ("search_ms_per_query", "search ms / query"),
        ("rerank_ms_per_query", "rerank ms / query"),
    ]  # fmt: skip
    assert "<b>0.800</b>" in page and "<td>0.600</td>" in page
    # Costs are shown as stored, never bolded (lower is better there).
    assert "<td>4096</td>" in page and "<td>12.5</td>" in page and "<b>4096" not in page


def test_the_recall_axis_starts_a_tenth_below_the_lowest_curve_and_shows_n_1_whole():
    high = {"a": np.array([0.66, 0.9, 1.0]), "b": np.array([0.71, 0.8, 0.95])}
    assert figures.recall_axis_floor(high) == pytest.approx(0.5)
    assert figures.recall_axis_floor({"a": np.array([0.05, 0.5])}) == 0.0
    figure = figures.recall_curve_figure(high, "t", [1, 3])
    (axes,) = figure.axes
    assert axes.get_ylim()[0] == pytest.approx(0.5) and axes.get_xlim()[0] < 1
    figures._pyplot().close("all")


def test_the_recall_figure_draws_precision_recall_curves_in_a_second_panel():
    curves = {"a": np.linspace(0.2, 1, 10), "a+mnn": np.linspace(0.4, 1, 10)}
    pr = {"a": (np.array([1.0, 0.5, 0.6]), np.array([0.5, 0.5, 1.0]))}
    figure = figures.recall_curve_figure(curves, "t", [1, 5], precision_recall=pr)
    left, right = figure.axes
    assert [line.get_label() for line in left.get_lines()] == ["a", "a+mnn"]
    (line,) = right.get_lines()  # a+mnn had no correct top-1: no curve
    # VPR-Bench's curve starts at (recall 0, precision 1).
    np.testing.assert_array_equal(line.get_xdata(), [0.0, 0.5, 0.5, 1.0])
    np.testing.assert_array_equal(line.get_ydata(), [1.0, 1.0, 0.5, 0.6])
    assert line.get_color() == left.get_lines()[0].get_color()
    assert len(figures.recall_curve_figure(curves, "t").axes) == 1
    figures._pyplot().close("all")


def test_every_curve_of_a_crowded_figure_has_its_own_style_and_rows_stay_with_their_method():
    """Roadscene's 17 rows on tab10 used to repeat colours (snsm and anyloc_vlad+ransac
    were both blue)."""
    methods = ["anyloc_vlad", "snsm", "segvlad", "segvlad_nopca", "segvlad_o0"]
    methods += ["segvlad_o0_nopca", "snsm_all8", "snsm_neg_l2", "snsm_token", "snsm_u6"]
    methods += ["gem", "average", "max", "anyloc_vlad+mnn", "anyloc_vlad+ransac"]
    methods += ["segvlad+mnn", "segvlad+ransac"]
    styles = figures.curve_styles(methods)
    looks = [(s["color"], s["marker"], str(s["linestyle"])) for s in styles.values()]
    assert len(set(looks)) == len(methods) == 17
    for row in ("anyloc_vlad+mnn", "anyloc_vlad+ransac"):
        assert styles[row]["color"] == styles["anyloc_vlad"]["color"]
        assert styles[row]["linestyle"] != styles["anyloc_vlad"]["linestyle"]
    # The legend lists each method followed by its re-ranked rows.
    order = list(styles)
    assert order[:3] == ["anyloc_vlad", "anyloc_vlad+mnn", "anyloc_vlad+ransac"]
    assert order.index("segvlad+ransac") == order.index("segvlad") + 2
    figure = figures.recall_curve_figure({m: np.linspace(0.1, 1, 20) for m in methods}, "t")
    (axes,) = figure.axes
    assert axes.get_legend() is None and len(figure.legends) == 1  # beside, not on, the data
    figure.draw_without_rendering()  # the layout is made when the figure is drawn
    legend_box = figure.legends[0].get_window_extent()
    assert legend_box.x0 >= axes.get_window_extent().x1
    figures._pyplot().close("all")


def test_the_recall_figures_legend_reads_as_large_as_its_axis_labels_inside_the_figure():
    """The report shows the figure at about its own size, where the legend's 8-point
    names were 7-pixel letters beside 10-point axis labels."""
    methods = ["anyloc_vlad", "anyloc_vlad+mnn", "anyloc_vlad+ransac", "segvlad_o0_nopca"]
    methods += [f"snsm_{i}" for i in range(13)]  # roadscene's 17 rows
    curves = {m: np.linspace(0.1, 1, 20) for m in methods}
    pr = {m: (np.linspace(1, 0.5, 5), np.linspace(0.2, 1, 5)) for m in methods}
    figure = figures.recall_curve_figure(curves, "t", [1, 5], precision_recall=pr)
    figure.draw_without_rendering()
    (legend,) = figure.legends
    label_size = figure.axes[0].xaxis.label.get_fontsize()
    assert all(text.get_fontsize() >= label_size for text in legend.get_texts())
    box, whole = legend.get_window_extent(), figure.bbox
    assert box.x0 >= figure.axes[1].get_window_extent().x1  # beside the panels
    assert whole.x0 <= box.x0 and box.x1 <= whole.x1 and whole.y0 <= box.y0 and box.y1 <= whole.y1
    figures._pyplot().close("all")


def test_a_16_bit_grayscale_image_keeps_its_range_in_a_thumbnail(tmp_path):
    from vprflow.data.images import read_image

    ramp = np.tile(np.linspace(0, 65535, 64).astype(np.uint16), (48, 1))
    path = tmp_path / "thermal16.png"
    Image.fromarray(ramp).save(path)
    thumb = figures.thumbnail(read_image(path), 24)
    assert thumb.shape == (24, 32, 3)
    # Read as 16-bit (not clipped to 8-bit white): dark on the left, bright on the right.
    assert thumb[:, 0].max() < 0.05 and thumb[:, -1].min() > 0.95
    assert np.all(np.diff(thumb[12, :, 0]) >= -1e-6)


@pytest.mark.parametrize(
    ("denominator", "said", "not_said"),
    [
        ("with_positives", "the others are left out", "is a miss)"),
        ("all", "is a miss)", "left out"),
    ],
)
def test_recall_table_page_states_which_queries_were_counted(tmp_path, denominator, said, not_said):
    from vprflow.stages.figures import write_recall_table

    table = tmp_path / "recall_d.csv"
    table.write_text(
        "dataset,method,aggregator,ground_truth,denominator,n_queries,recall@1\n"
        f"d,m,gem,pairs,{denominator},4,0.500000\n"
    )
    write_recall_table("d", str(table), str(tmp_path / "page.html"))
    page = (tmp_path / "page.html").read_text()
    assert said in page and not_said not in page
    assert "ground-truth rule pairs" in page and "recall_d.csv" in page


def test_support_maps_share_one_colour_scale_shown_by_a_colour_bar():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (32, 32, 3))
    rows = [("q.png", image, np.full((4, 4), 0.2), "r.png", image, np.full((4, 4), 0.9))]
    figure = figures.support_map_figure(rows, "t")
    *panels, bar = figure.axes
    assert len(panels) == 4 and bar.get_ylim() == pytest.approx((0.2, 0.9))
    query_map, reference_map = panels[1].get_images()[0], panels[3].get_images()[0]
    assert query_map.get_clim() == reference_map.get_clim() == pytest.approx((0.2, 0.9))
    figures._pyplot().close("all")


def test_every_figure_the_report_lists_has_one_drawing_function():
    from vprflow.planning.reports import FIGURES
    from vprflow.stages.figures import DRAW, draw_figure

    assert set(DRAW) == set(FIGURES)
    with pytest.raises(ValueError, match="unknown figure 'nonsense'"):
        draw_figure("nonsense", {}, "", "m", {}, "out.png")
