"""Regenerate docs/datasets.md from the presets (src/vprflow/data/presets.yaml): every
preset's layout, protocol, source and published recall.

python scripts/write_datasets_doc.py
"""

from __future__ import annotations

from pathlib import Path

from vprflow.data.ground_truth import ground_truth_rule
from vprflow.data.presets import presets

REPO = Path(__file__).resolve().parents[1]


def datasets_doc() -> str:
    """docs/datasets.md: every preset's layout, protocol, source and published recall."""
    lines = [
        "# Datasets: the papers' datasets as presets",
        "",
        "<!-- Generated from src/vprflow/data/presets.yaml by scripts/write_datasets_doc.py;"
        " edit that file. -->",
        "",
        "Put a dataset under `data_root/<preset>/` in the layout below and run",
        "`snakemake --cores 2 results/recall_<preset>.csv`: the preset sets the layout, the",
        "ground-truth rule, the resolution, which queries count and the vocabulary. A",
        "`datasets` entry of the same name in your config changes only the keys it gives",
        "(a `ground_truth` with another `kind`, or a `defaults.vocabulary` with another",
        "`source`, replaces the preset's); the table's `protocol` column then lists the",
        "protocol keys you changed. A preset joins the plan when its folder exists, when",
        "`targets` names it or when `datasets` has an entry of its name. When the preset's",
        "folder exists but holds another layout (one level down, the downloader's where",
        "the authors' is expected, raw MSLS `train_val/`), the error shows the layout below,",
        "says which one it found and how to convert it (each preset's section lists the",
        "other published layouts it knows).",
        "",
        "Settings tied to a preset's DINOv2 ViT-G/14 features follow the features you choose.",
        "With `datasets: {pitts30k: {defaults: {features: daisy, segmenter: slic}}}` the",
        "published vocabulary (1,536-d DINOv2-G centres) gives way to your config's",
        "`vocabulary` section (fitted on the map by default; set the entry's",
        "`defaults.vocabulary` for another), and each re-ranker on DINOv2-G features is",
        "replaced by your config's re-ranker of the same kind and options on the chosen",
        "features (`mnn_dinov2` by `mnn` on `daisy`), or dropped where there is none (set",
        "the entry's `rerank` to choose); the log says what followed. PCA is no preset",
        "setting: the config's `pca` applies, and the log says that its 1024 whitened",
        "components are sized for DINOv2-G (set the entry's `defaults.pca`). A `dinov2_vitg14`",
        "entry redefined to another model, layer or facet drops the published vocabulary",
        "the same way (its re-rankers follow it by name). A method with features",
        "of its own (`anyloc_vlad_dinov3`) on a preset that keeps its published vocabulary",
        "stops planning, naming the keys to set (`methods.<method>.vocabulary.source`), rather",
        "than fail in the vocabulary stage after the fetch and the features. A full entry",
        "(every required key) that bears a preset's name is still merged with the preset:",
        "the log says so and the tables' `protocol` column reads `merged with preset",
        "<name>`; `preset: false` in the entry uses it alone (`own entry`).",
        "",
        "Where the papers counted a dataset differently, each protocol is a preset of its",
        "own on one folder, and each published number sits under the protocol it was",
        "computed with: `17places` is Revisit-Anything's (+-15 frames, queries with a",
        "positive: SegVLAD's 95.3 Recall@1, the README's `results/recall_17places.csv`),",
        "`17places_anyloc` AnyLoc's (VPR-Bench's +-2 frames file, all queries: its 65.0);",
        "`vp_air` searches the 2,706 reference views (SegVLAD's 69.8), `vp_air_anyloc`",
        "those followed by the 10,000 distractors, every query counted (AnyLoc's 66.7).",
        "",
        "The DINOv2 presets also re-rank AnyLoc-VLAD's and SegVLAD's top 100 by local",
        "matches of the same DINOv2 features (rows `<method>+mnn_dinov2` and",
        "`<method>+ransac_dinov2`, docs/methods.md \u00a78); the papers do not, and the",
        "retrieval rows are theirs. `rerank: {anyloc_vlad: [], segvlad: []}` in the",
        "dataset's entry turns it off.",
        "",
        "Published recall (percent) is for orientation: what the papers report with the",
        "authors' weights, DINOv2 ViT-G/14 (layer 31, value facet) for AnyLoc-VLAD and",
        "SegVLAD-PreT, a fine-tuned DINOv2 ViT-B/14 for SegVLAD-FineT (its checkpoint is",
        "the authors' own file). (M) marks the map vocabulary, (D) the domain vocabulary",
        "the presets use by default. The numbers were transcribed from the papers' tables",
        '(named with each); check them against the paper before you cite them. "none',
        'found" means neither the AnyLoc nor the Revisit Anything paper reports the',
        "dataset, no trained model's README reports it at vprflow's variant and split, and",
        "the SNSM paper's tables could not be read here.",
        "",
        "The trained models' rows (MixVPR, Conv-AP, BoQ, SALAD: docs/methods.md \u00a711)",
        "are their authors' README tables (`repository @ commit: README.md`), at the",
        "variant config/trained.yaml loads, listed only where the README's split is the",
        "preset's (the Nordland rows are VPR-Bench's 2,760 queries, not the downloader's",
        "27,592, and stay out). Each row's `vprflow row` is the method whose row of",
        "`results/recall_<preset>.csv` reproduces it at the preset's settings (`-`: none",
        "in vprflow, such as SegVLAD-FineT's fine-tuned checkpoint or the (M) vocabulary).",
        "A preset runs the training-free ones already; with `trained_baselines: true` in",
        "the config, which config/trained.yaml sets, it also runs the trained ones its",
        "rows name, after its own methods, so one run rebuilds the table:",
        "`snakemake --cores 2 results/recall_pitts30k.csv --configfile config/config.yaml",
        "config/trained.yaml` (the checkpoints where config/trained.yaml says).",
        "`results/published_<preset>.csv` (asked for by name) sets each published row",
        "beside its `vprflow row`'s Recall@1 / @5 from that table, in percent, with the",
        "row's `protocol` column (which says whether the config changed the preset's),",
        "followed, where this run makes the row otherwise than the preset with the",
        "shipped config/config.yaml, by every stage setting that differs (`not the",
        "published setting: features: backbone daisy (published: dinov2); ...`).",
        "",
        "`native` size: every image as stored (its size, the first image's, must be every",
        "image's). Each preset's section names the code its layout and rule were read from.",
        "",
        "| preset | dataset | positives | queries counted | size | vocabulary |"
        " published R@1 / R@5 |",
        "|---|---|---|---|---|---|---|",
    ]
    for preset in presets().values():
        entry = preset.dataset
        published = "; ".join(
            f"{p['method']} {p['recall@1']} / {p['recall@5']} ({p['paper']})"
            for p in preset.published
        )
        size = entry["resolution"]
        size = "native" if size == "native" else f"{size[0]} x {size[1]}"
        lines.append(
            f"| `{preset.name}` | {preset.title} | `{_rule(entry['ground_truth'])}` | "
            f"{entry['denominator']} | {size} | {_vocabulary(entry)} | "
            f"{published or 'none found'} |"
        )
    for preset in presets().values():
        lines += [
            "",
            f"## `{preset.name}`: {preset.title}",
            "",
            preset.protocol,
            "",
            f"Follows: {preset.code}.",
            "",
            f"Get it: {preset.dataset['source']}",
            "",
            "```",
            preset.layout,
            "```",
        ]
        for other in preset.other_layouts:
            lines += ["", f"In {other['name']}: {other['convert']}"]
        if preset.published:
            lines += [
                "",
                "| method | paper | R@1 | R@5 | vprflow row |",
                "|---|---|---|---|---|",
            ]
            lines += [
                f"| {p['method']} | {p['paper']} | {p['recall@1']} | {p['recall@5']} | "
                + (f"`{p['row']}` |" if "row" in p else "- |")
                for p in preset.published
            ]
    return "\n".join(lines) + "\n"


def _vocabulary(entry: dict) -> str:
    vocabulary = (entry.get("defaults") or {}).get("vocabulary") or {}
    if vocabulary.get("source") == "published":
        return f"published `{vocabulary['name']}`"
    return "-"  # the methods' own (SNSM and the pooling baselines use none)


def _rule(truth: dict) -> str:
    return ground_truth_rule(truth)  # presets state every key their rule names


if __name__ == "__main__":
    (REPO / "docs" / "datasets.md").write_text(datasets_doc())
