"""Pictures of results: recall curves, retrieval montages, SegVLAD segment matches and
SNSM support maps.

Plain functions over arrays. Images are float RGB ``[H, W, 3]`` in ``[0, 1]`` as
:func:`vprflow.data.images.read_image` returns them (so 16-bit and grayscale files display
like any other); colours are RGB triples in ``[0, 1]``. Only the ``*_figure``
functions touch matplotlib (Agg backend, no screen), and :func:`save_figure` writes a
PNG to a temporary name first, so an interrupted job leaves no complete-looking file.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from html import escape
from pathlib import Path

import numpy as np

from vprflow.core.files import atomic_path
from vprflow.core.lazy import lazy_import
from vprflow.data.images import resize_image
from vprflow.evaluation.precision_recall import SUMMARY
from vprflow.evaluation.recall import COST_COLUMNS

matplotlib = lazy_import("matplotlib")
pyplot = lazy_import("matplotlib.pyplot")
ticker = lazy_import("matplotlib.ticker")
ndimage = lazy_import("scipy.ndimage")
segmentation = lazy_import("skimage.segmentation")

CORRECT = (0.0, 0.75, 0.0)  # frame of a retrieved reference that is a true positive
WRONG = (0.9, 0.0, 0.0)  # frame of one that is not
NEUTRAL = (0.55, 0.55, 0.55)  # frame of the query, and of references with no truth known
FRAME_FRACTION = 0.06  # frame width as a fraction of the thumbnail height


def thumbnail(image: np.ndarray, height: int) -> np.ndarray:
    """``image [H, W, 3]`` scaled to ``height`` rows, aspect kept (antialiased)."""
    width = max(1, round(image.shape[1] * height / image.shape[0]))
    return resize_image(image, width, height, method="antialias")


def framed(image: np.ndarray, colour: Sequence[float], width: int) -> np.ndarray:
    """A copy of ``image [H, W, 3]`` whose outer ``width`` pixels are ``colour``."""
    out = np.array(image, dtype=np.float32, copy=True)
    if width <= 0:
        return out
    out[:width] = colour
    out[-width:] = colour
    out[:, :width] = colour
    out[:, -width:] = colour
    return out


def frame_colour(correct: bool | None) -> tuple[float, float, float]:
    """Green for a true positive, red for a wrong reference, grey when unknown."""
    if correct is None:
        return NEUTRAL
    return CORRECT if correct else WRONG


def upsample_masks(masks: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour upsampling of bool ``masks [S, Hm, Wm]`` to ``[S, height, width]``
    (the mapping SegVLAD uses from mask to image pixels)."""
    s, hm, wm = masks.shape
    rows = np.minimum((np.arange(height) * hm) // height, hm - 1)
    cols = np.minimum((np.arange(width) * wm) // width, wm - 1)
    return masks[:, rows][:, :, cols]


def recall_curve(first_correct: np.ndarray, evaluated: np.ndarray, n_max: int) -> np.ndarray:
    """Recall@N for ``N = 1 .. n_max``: the fraction of evaluated queries whose first
    correct reference is within the top N.

    ``first_correct [Q]``: 0-based rank of the first true positive, -1 for none in the
    ranking; ``evaluated [Q]`` bool: queries with at least one positive (the others are
    not counted, as in the results table). Returns float64 ``[n_max]``.
    """
    ranks = np.asarray(first_correct)[np.asarray(evaluated, dtype=bool)]
    if len(ranks) == 0:
        return np.zeros(n_max)
    hits = np.bincount(ranks[ranks >= 0], minlength=n_max)[:n_max]
    return np.cumsum(hits) / len(ranks)


def sample_queries(candidates: np.ndarray, count: int, seed: int) -> np.ndarray:
    """``count`` of the ``candidates`` (query indices), chosen by ``seed`` and sorted: the
    same queries for every method given the same candidates."""
    candidates = np.asarray(candidates)
    if count >= len(candidates):
        return np.sort(candidates)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(candidates, size=count, replace=False))


# The HTML table's counting columns, after its scores and costs.
TABLE_COUNTS = ("descriptor_dim", "n_queries", "n_short_rankings", "n_queries_without_positive")


# The HTML table's headings where the CSV's column names are long (the CSV keeps them).
_HEADINGS = {
    "auc_pr": "AUC-PR",
    "recall_at_100_precision": "R at P=1",
    "extended_precision": "EP",
    "descriptor_bytes_per_image": "bytes / image",
    "search_ms_per_query": "search ms / query",
    "rerank_ms_per_query": "rerank ms / query",
    "descriptor_dim": "dim",
    "n_queries": "queries",
    "n_short_rankings": "short rankings",
    "n_queries_without_positive": "without positive",
}


def _heading(column: str) -> str:
    for prefix, short in (("exact_recall@", "exact R@"), ("recall@", "R@"), ("map@", "mAP@")):
        if column.startswith(prefix):
            return short + column.removeprefix(prefix)
    return _HEADINGS.get(column, column)


def recall_table_html(rows: list[dict[str, str]], title: str, notes: Sequence[str] = ()) -> str:
    """An HTML page of a results table (``rows`` as read from the CSV): the method, its
    Recall@N and mAP@N columns and the precision-recall summary (the best of each column
    in bold), then the cost and counting columns, under short headings; every other
    column of the CSV stays in the CSV. ``notes`` are paragraphs under the title."""
    # The results table's own column names (vprflow.stages.report).

    columns = list(rows[0]) if rows else []
    scored = [c for c in columns if c.startswith(("recall@", "map@", "exact_recall@"))]
    scored += [c for c in SUMMARY if c in columns]
    costs = [c for c in (*COST_COLUMNS, *TABLE_COUNTS) if c in columns]
    shown = ["method", *scored, *costs]
    best = {c: max((float(r[c]) for r in rows if r[c] != ""), default=None) for c in scored}
    # Short headings keep the table within a laptop's width; each one's title (shown on
    # hover) is the CSV's column name.
    head = "".join(f"<th title='{escape(c)}'>{escape(_heading(c))}</th>" for c in shown)
    body = []
    for row in rows:
        cells = []
        for column in shown:
            value = row.get(column, "")
            text = escape(value)
            if column in best and value != "":
                text = f"{float(value):.3f}"
                if float(value) == best[column]:
                    text = f"<b>{text}</b>"
            cells.append(f"<td>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    paragraphs = "".join(f"<p>{escape(note)}</p>" for note in notes)
    style = (
        "body{font-family:sans-serif;font-size:14px}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:3px 6px;text-align:right}"
        "th{font-size:12px;max-width:6em;vertical-align:bottom}"
        "td:first-child,th:first-child{text-align:left;white-space:nowrap}"
    )
    return (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{escape(title)}</title>"
        f"<style>{style}</style></head><body><h3>{escape(title)}</h3>{paragraphs}"
        f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"
        "</body></html>\n"
    )


# ------------------------------------------------------------------ matplotlib figures


def _pyplot():
    """pyplot, on the Agg backend (chosen before pyplot is first imported)."""
    matplotlib.use("Agg")
    return pyplot


def save_figure(figure, path: str | Path, dpi: int = 100) -> None:
    """Write ``figure`` as a PNG at ``path`` via a temporary file, then close it."""
    with atomic_path(path) as tmp:
        try:
            figure.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
        finally:
            _pyplot().close(figure)


def recall_axis_floor(curves: dict[str, np.ndarray]) -> float:
    """The Recall@N axis's lower end: 0.1 below the lowest value drawn, rounded down to
    a tenth (0 at most), so curves that all lie high are not squeezed into the top."""
    lowest = min((float(np.min(c)) for c in curves.values() if len(c)), default=0.0)
    return max(0.0, np.floor((lowest - 0.1) * 10) / 10)


# A method's colour and marker, and a re-ranked row's line style: a row ``m+r`` keeps the
# colour and marker of ``m`` and takes the dashes of its re-ranker, so each method reads
# as one family and no two curves look alike (tab10 has ten colours; markers tell apart
# the methods beyond ten).
_MARKERS = ("o", "s", "^", "D", "v", "P", "X")
_DASHES = ("-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1)), (0, (1, 3)))


# The recall figure's legend: its names in points (the axes' labels are 10; the report
# shows the figure at about its own size, where 8 points read as 7-pixel letters) and
# its line samples in font sizes, long enough to tell the re-rankers' dashes apart.
LEGEND_FONT = 11
LEGEND_HANDLE = 4


def curve_styles(methods: Sequence[str]) -> dict[str, dict]:
    """``{method: {"color", "marker", "linestyle"}}`` for the rows of a recall figure, in
    legend order: each method (the part of a row's name before ``+``) in order of first
    appearance, followed by its re-ranked rows. Distinct for up to 70 methods and six
    line styles (a method and five re-rankers)."""
    palette = matplotlib.colormaps["tab10"].colors
    families: dict[str, list[str]] = {}
    for method in methods:
        families.setdefault(method.split("+", 1)[0], []).append(method)
    styles = {}
    for index, (base, rows) in enumerate(families.items()):
        # The base row first, then the re-ranked ones in their order.
        rows = sorted(rows, key=lambda row: row != base)
        for depth, row in enumerate(rows):
            styles[row] = {
                "color": palette[index % len(palette)],
                "marker": _MARKERS[index // len(palette) % len(_MARKERS)],
                "linestyle": _DASHES[depth % len(_DASHES)],
            }
    return styles


def recall_curve_figure(
    curves: dict[str, np.ndarray],
    title: str,
    marks: Sequence[int] = (),
    precision_recall: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
):
    """One line per method: ``curves[method] [n_max]`` is Recall@1..n_max. ``marks`` are
    the table's N values, drawn as points. With ``precision_recall[method] = (precision
    [T], recall [T])`` (a method may lack one: no correct top-1 match), a second panel
    beside it draws those curves from the point (recall 0, precision 1), as VPR-Bench
    plots them. Styles from :func:`curve_styles`; the legend sits right of the panels,
    off the data."""
    plt = _pyplot()
    panels = 2 if precision_recall is not None else 1
    styles = curve_styles(list(curves))
    # The legend's width in inches (a line sample and the longest name), added to the
    # panels' 6 inches each so they keep their size; constrained layout places it.
    legend_width = (LEGEND_HANDLE + 2 + 0.6 * max((len(m) for m in curves), default=0)) * (
        LEGEND_FONT / 72
    )
    figure, all_axes = plt.subplots(
        1, panels, figsize=(6 * panels + legend_width, 4.5), squeeze=False, layout="constrained"
    )
    axes = all_axes[0, 0]
    handles = {}
    for method, curve in curves.items():
        n = np.arange(1, len(curve) + 1)
        at = [m - 1 for m in marks if 1 <= m <= len(curve)]
        (handles[method],) = axes.plot(
            n, curve, label=method, linewidth=1.5, markevery=at, ms=4, **styles[method]
        )
    axes.xaxis.set_major_locator(ticker.MaxNLocator(integer=True))
    axes.set_xlabel("N (references retrieved)")
    axes.set_ylabel("Recall@N")
    axes.set_ylim(recall_axis_floor(curves), 1.02)
    # Half a step of room each side, so the points at N = 1 and the last N are whole.
    axes.set_xlim(0.5, max((len(c) for c in curves.values()), default=1) + 0.5)
    axes.grid(alpha=0.3)
    if precision_recall is not None:
        axes = all_axes[0, 1]
        for method, (precision, recall) in precision_recall.items():
            axes.plot(
                np.concatenate([[0.0], recall]),
                np.concatenate([[1.0], precision]),
                label=method,
                linewidth=1.5,
                markevery=0.2,  # a few markers, evenly spaced along the curve
                ms=3,
                **styles[method],
            )
        axes.set_xlabel("recall (of the correct top-1 matches)")
        axes.set_ylabel("precision (of the accepted top-1 matches)")
        axes.set_xlim(0, 1.02)
        axes.set_ylim(0, 1.02)
        axes.grid(alpha=0.3)
        axes.set_title("top-1 precision-recall over a score threshold", fontsize=10)
    figure.suptitle(title, fontsize=11)
    ordered = [handles[m] for m in styles]
    figure.legend(
        ordered,
        list(styles),
        loc="outside right upper",
        fontsize=LEGEND_FONT,
        handlelength=LEGEND_HANDLE,
        frameon=False,
    )
    return figure


@dataclass
class RetrievalRow:
    """One query of a retrieval montage: its image and name, and its top references
    (images, names, whether each is a true positive: None when the truth is unknown)."""

    query: np.ndarray
    query_name: str
    references: list[np.ndarray]
    reference_names: list[str]
    correct: list[bool | None]
    label: str = "query"  # the query cell's caption, before its name


def retrieval_figure(rows: list[RetrievalRow], title: str, height: int = 120):
    """Rows of query | top references, each reference framed green (correct) or red
    (wrong); names under each thumbnail."""
    plt = _pyplot()
    n_cols = 1 + max((len(r.references) for r in rows), default=0)
    border = max(2, round(FRAME_FRACTION * height))
    height_in = 1.7 * len(rows) + 0.9
    figure, axes = plt.subplots(len(rows), n_cols, figsize=(1.9 * n_cols, height_in), squeeze=False)
    # The title's 0.5 inches above the first row's two-line labels (0.4 inches), not
    # matplotlib's 12 % of the height (inches on a tall figure).
    figure.subplots_adjust(top=1 - 0.9 / height_in)
    for axis in axes.ravel():
        axis.axis("off")
    for r, row in enumerate(rows):
        cells = [(row.query, f"{row.label}\n{row.query_name}", None)]
        cells += [
            (image, f"{rank}. {name}", ok)
            for rank, (image, name, ok) in enumerate(
                zip(row.references, row.reference_names, row.correct, strict=True), start=1
            )
        ]
        for c, (image, label, ok) in enumerate(cells):
            axes[r, c].imshow(framed(thumbnail(image, height), frame_colour(ok), border))
            axes[r, c].set_title(label, fontsize=7)
    figure.suptitle(title, fontsize=10)
    return figure


@dataclass
class SegmentMatch:
    """A query segment, the reference segment that matched it in the top-1 reference
    image (None when none of its nearest segments lies there), and their cosine
    similarity."""

    query_segment: int
    reference_segment: int | None
    similarity: float | None


@dataclass
class SegmentExplanation:
    """One query explained: its image and masks ``[Sq, Hm, Wm]``, its top-1 reference's
    image and masks ``[Sr, Hm, Wm]``, the matches, a title, and whether the reference is
    a true positive (None when unknown)."""

    query: np.ndarray
    query_masks: np.ndarray
    reference: np.ndarray
    reference_masks: np.ndarray
    matches: list[SegmentMatch]
    title: str
    correct: bool | None


# Pairs a segment figure draws: the most similar ones, each in a colour of matplotlib's
# "tab10" (ten hues told apart at a glance, also by most colour-blind readers).
MAX_PAIRS = 10


def pair_palette() -> np.ndarray:
    """``[MAX_PAIRS, 3]`` colours of the numbered pairs (matplotlib's tab10)."""
    return np.asarray(matplotlib.colormaps["tab10"].colors[:MAX_PAIRS], dtype=np.float64)


def outline_segments(
    image: np.ndarray, masks: np.ndarray, colours: dict[int, np.ndarray], alpha: float = 0.25
) -> np.ndarray:
    """``image [H, W, 3]`` with each segment ``s`` in ``colours`` (``masks [S, Hm, Wm]``,
    any resolution) tinted at ``alpha`` and outlined in its colour (2 pixels wide), so
    the scene stays visible; the other segments are left as they are."""
    height, width = image.shape[:2]
    out = np.array(image, dtype=np.float32, copy=True)
    for s, colour in colours.items():
        mask = upsample_masks(np.asarray(masks[s : s + 1], dtype=bool), height, width)[0]
        colour = np.asarray(colour, np.float32)
        out[mask] = (1 - alpha) * out[mask] + alpha * colour
        edge = ndimage.binary_dilation(segmentation.find_boundaries(mask, mode="inner")) & mask
        out[edge] = colour
    return out


def label_point(mask: np.ndarray) -> tuple[float, float]:
    """``(x, y)`` of the pixel of bool ``mask [H, W]`` farthest from its border: where a
    segment's number is written (a centroid can fall outside a concave segment)."""
    distance = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
    y, x = np.unravel_index(int(np.argmax(distance)), mask.shape)
    return float(x), float(y)


def shown_pairs(matches: list[SegmentMatch]) -> list[SegmentMatch]:
    """The pairs a segment figure numbers: matched ones, most similar first, at most
    :data:`MAX_PAIRS`."""
    found = [m for m in matches if m.reference_segment is not None]
    return sorted(found, key=lambda m: -m.similarity)[:MAX_PAIRS]


def segment_match_figure(explanations: list[SegmentExplanation], title: str):
    """Per explanation, one row: the query and its top-1 reference (framed green or red)
    with the :func:`shown_pairs` numbered 1.. in both images, each pair tinted and
    outlined in its own colour, and under them the pairs' cosine similarities; the row's
    heading says how many pairs matched and how many are shown."""
    plt = _pyplot()
    palette = pair_palette()
    figure = plt.figure(figsize=(11, 5.2 * len(explanations) + 0.5), layout="constrained")
    rows = figure.subfigures(len(explanations), 1, squeeze=False)[:, 0]
    for row, item in zip(rows, explanations, strict=True):
        pairs = shown_pairs(item.matches)
        n_matched = sum(m.reference_segment is not None for m in item.matches)
        query_colours = {m.query_segment: palette[i] for i, m in enumerate(pairs)}
        reference_colours: dict[int, np.ndarray] = {}
        numbers: dict[int, list[str]] = {}
        for i, m in enumerate(pairs):
            # A reference segment several query segments found keeps the best's colour.
            reference_colours.setdefault(m.reference_segment, palette[i])
            numbers.setdefault(m.reference_segment, []).append(str(i + 1))
        axes = row.subplots(1, 2)
        border = max(2, round(FRAME_FRACTION * item.reference.shape[0] / 2))
        query = outline_segments(item.query, item.query_masks, query_colours)
        reference = outline_segments(item.reference, item.reference_masks, reference_colours)
        axes[0].imshow(query)
        axes[1].imshow(framed(reference, frame_colour(item.correct), border))
        query_numbers = {m.query_segment: [str(i + 1)] for i, m in enumerate(pairs)}
        labelled = (
            (axes[0], item.query, item.query_masks, query_numbers, query_colours),
            (axes[1], item.reference, item.reference_masks, numbers, reference_colours),
        )
        for axis, image, masks, names, colours in labelled:
            height, width = image.shape[:2]
            for s, text in names.items():
                mask = upsample_masks(np.asarray(masks[s : s + 1], dtype=bool), height, width)[0]
                x, y = label_point(mask)
                box = {"boxstyle": "round,pad=0.2", "facecolor": colours[s], "edgecolor": "none"}
                axis.text(
                    x, y, ",".join(text), fontsize=10, fontweight="bold", color="white",
                    ha="center", va="center", bbox=box,
                )  # fmt: skip
            axis.axis("off")
        axes[0].set_title("query", fontsize=10)
        verdict = {True: "a true positive", False: "wrong", None: "not judged"}[item.correct]
        axes[1].set_title(f"top-1 reference ({verdict})", fontsize=10)
        cut = (
            f"the {len(pairs)} most similar are numbered"
            if n_matched > len(pairs)
            else "all are numbered"
        )
        row.suptitle(
            f"{item.title}\n{n_matched} of {len(item.matches)} query segments matched a "
            f"segment of this reference; {cut}",
            fontsize=10,
        )
        similarities = "   ".join(f"{i + 1}: {m.similarity:.3f}" for i, m in enumerate(pairs))
        row.supxlabel(f"cosine similarity of each numbered pair   {similarities}", fontsize=9)
    figure.suptitle(title, fontsize=11)
    return figure


def support_map_figure(
    rows: list[tuple[str, np.ndarray, np.ndarray, str, np.ndarray, np.ndarray]], title: str
):
    """SNSM support maps: per row ``(query name, query image, its support map, reference
    name, reference image, its support map)``, the images beside their maps."""
    plt = _pyplot()
    figure, axes = plt.subplots(len(rows), 4, figsize=(10.6, 2.6 * len(rows) + 0.5), squeeze=False)
    # One colour scale for every map, so a colour means one similarity throughout. Its
    # range is the maps' interiors': a border token has fewer neighbours, so its support
    # is lower by construction and would take most of the scale (shown as the end colour).
    maps = [m for row in rows for m in (row[2], row[5])]
    inner = [m[1:-1, 1:-1] if min(m.shape) > 2 else m for m in maps]
    low = min((float(np.min(m)) for m in inner), default=0.0)
    high = max((float(np.max(m)) for m in inner), default=1.0)
    for r, (q_name, q_image, q_map, r_name, r_image, r_map) in enumerate(rows):
        panels = [
            (q_image, f"query {q_name}", None, q_image),
            (q_map, "query support map", "viridis", q_image),
            (r_image, f"reference {r_name}", None, r_image),
            (r_map, "reference support map", "viridis", r_image),
        ]
        for c, (picture, label, cmap, image) in enumerate(panels):
            # A map covers the image it was computed from (resized to the features'
            # input size): drawn over that image's extent, so both have its shape.
            extent = (0, image.shape[1], image.shape[0], 0)
            scale = {"vmin": low, "vmax": high} if cmap else {}
            shown = axes[r, c].imshow(picture, cmap=cmap, extent=extent, **scale)
            axes[r, c].set_title(label, fontsize=8)
            axes[r, c].axis("off")
    if rows:
        bar = figure.colorbar(
            shown, ax=axes.ravel().tolist(), fraction=0.025, pad=0.02, extend="min"
        )
        bar.set_label("support (similarity to the token's neighbours)", fontsize=8)
    figure.suptitle(title, fontsize=10)
    return figure
