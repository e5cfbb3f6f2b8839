"""The real Snakefile end to end on a synthetic dataset, and what reruns when."""

from __future__ import annotations

import copy
import csv
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from synthetic import make_dataset
from workflow_helpers import (
    REPO,
    SNAKEFILE,
    dry_run,
    expected_rows,
    read_rows,
    scheduled_outputs,
    scheduled_stages,
    snakemake,
    snakemake_command,
    toy_config,
    untimed_table,
    write_config,
)

from vprflow.core.paths import PREDICTIONS_CSV, RECALL_CSV, RECALL_PLOT, RECALL_TABLE
from vprflow.core.stores import array_items
from vprflow.planning.plan import EXECUTION_ONLY, STAGES

pytestmark = pytest.mark.workflow
TARGET = "results/recall_toy.csv"
# segment_gem: a per-segment aggregator other than SegVLAD takes the segment path.
METHODS = [
    "anyloc_vlad",
    "segvlad_o0_nopca",
    "segvlad_o0",
    "segvlad_nopca",
    "segvlad",
    "segment_gem",
]
RERANK = {"anyloc_vlad": ["mnn", "ransac"], "segvlad": ["mnn"]}  # config.yaml's re-rankers
# The table: each method's row, then its re-ranked rows.
ROWS = expected_rows({"methods": METHODS, "rerank": RERANK})


@pytest.fixture(scope="module")
def toy_run(tmp_path_factory):
    """One complete run of the workflow on the toy dataset (shared by the tests below)."""
    workdir = tmp_path_factory.mktemp("workflow")
    make_dataset(workdir / "data" / "toy")
    config = toy_config(workdir / "data", methods=METHODS, rerank=RERANK)
    config_path = write_config(workdir, config)
    snakemake(workdir, config_path, TARGET)
    return workdir, config


def test_csv_has_one_row_per_method_with_parameters_and_recall(toy_run):
    workdir, config = toy_run
    rows = read_rows(workdir / TARGET)
    assert [r["method"] for r in rows] == ROWS
    header = list(rows[0])
    # The results lead, then what was counted, then the parameters (the HTML table's
    # order too).
    assert header[:22] == [
        "dataset",
        "method",
        "recall@1",
        "recall@5",
        "recall@10",
        "recall@20",
        "map@1",
        "map@5",
        "map@10",
        "map@20",
        "auc_pr",
        "recall_at_100_precision",
        "extended_precision",
        "n_queries",
        "n_short_rankings",
        "n_queries_without_positive",
        "ground_truth",
        "denominator",
        "descriptor_dim",
        "descriptor_bytes_per_image",
        "search_ms_per_query",
        "rerank_ms_per_query",
    ]
    assert "aggregator" in header[22:]
    for row in rows:
        assert row["dataset"] == "toy"
        assert row["ground_truth"] == "vprbench:ground_truth_new.npy"
        assert row["n_queries"] == "10"
        # Global methods rank every reference; per-segment ones only the voted ones.
        assert row["n_short_rankings"] == "0" or row["aggregator"] in ("segvlad", "segment_gem")
        assert 0 <= int(row["n_short_rankings"]) <= 10
        recalls = [float(row[f"recall@{n}"]) for n in (1, 5, 10, 20)]
        assert all(0.0 <= r <= 1.0 for r in recalls)
        assert recalls == sorted(recalls)
        assert row["denominator"] == "with_positives"
        # mAP@1 is Recall@1 (the top reference is right or not); mAP@N <= Recall@N.
        assert float(row["map@1"]) == float(row["recall@1"])
        assert all(float(row[f"map@{n}"]) <= float(row[f"recall@{n}"]) for n in (5, 10, 20))
    by_method = {r["method"]: r for r in rows}
    assert by_method["segvlad"]["segvlad.order"] == "3"
    assert by_method["segvlad_o0"]["segvlad.order"] == "0"
    assert by_method["segvlad_nopca"]["pca.enabled"] == "false"
    assert by_method["segvlad"]["pca.dim"] == "16"
    # At most the asked 16: PCA is capped at its sample's numerical rank (order-3
    # neighbourhoods of 10 small images repeat themselves).
    assert 1 <= int(by_method["segvlad"]["descriptor_dim"]) <= 16
    daisy = config["backbones"]["daisy"]
    daisy_dim = (daisy["rings"] * daisy["histograms"] + 1) * daisy["orientations"]
    n_clusters = config["vocabulary"]["n_clusters"]
    assert by_method["segvlad_nopca"]["descriptor_dim"] == str(n_clusters * daisy_dim)
    assert by_method["anyloc_vlad"]["segvlad.order"] == ""  # not a parameter of that row
    # The segment path's settings are the voting section's, whichever aggregator.
    for name in ("segvlad", "segment_gem"):
        assert by_method[name]["voting.top_segments"] != ""
        assert by_method[name]["voting.vote_ranking"] != ""
    assert by_method["segment_gem"]["aggregator"] == "segment_gem"
    assert by_method["segment_gem"]["segvlad.order"] == ""
    # The toy places are distinctive: the classical pipeline must beat chance (3/10) clearly.
    assert float(by_method["anyloc_vlad"]["recall@1"]) >= 0.6
    assert float(by_method["segvlad_nopca"]["recall@1"]) >= 0.6
    for name in ROWS:
        row = by_method[name]
        reranker = name.partition("+")[2]
        assert row["reranker"] == reranker
        assert (row["rerank.kind"] == reranker) if reranker else (row["rerank.kind"] == "")
        assert (row["rerank_ms_per_query"] != "") == bool(reranker)
        assert 0 <= float(row["auc_pr"]) <= 1 and 0 <= float(row["extended_precision"]) <= 1
        assert float(row["descriptor_bytes_per_image"]) > 0
    predictions = read_rows(workdir / "results" / "predictions_toy.csv")
    assert len(predictions) == 10 * len(ROWS)
    assert len(predictions[0]["top"].split()) == 10
    assert len(predictions[0]["top_scores"].split()) == 10
    assert predictions[0]["top_images"].split()[0].startswith("ref/")


def test_every_rule_wrote_a_log(toy_run):
    workdir, _ = toy_run
    stages = ("images", "dataset", "features", "segments", "vocabulary", "pca", "descriptors")
    for stage in (*stages, "recall"):
        logs = list((workdir / "logs" / stage).glob("*/*.log"))
        assert logs, f"no log for {stage}"
    assert (workdir / "logs" / "recall_csv" / "toy.log").exists()


def test_index_and_log_links_name_the_dataset_and_methods(toy_run):
    """results/cache/index.tsv maps every store to its stage, dataset and methods, and
    logs/by-method/<dataset>/<method>/<stage> leads to that store's logs."""
    workdir, _ = toy_run
    with open(workdir / "results" / "cache" / "index.tsv") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    by_key = {(r["stage"], r["key"]): r for r in rows}
    for stage, key in by_key:
        assert (workdir / by_key[stage, key]["store"]).is_dir(), (stage, key)
    features = [r for r in rows if r["stage"] == "features"]
    assert len(features) == 1 and features[0]["dataset"] == "toy"
    # One backbone, shared by the methods and their re-rankers.
    assert features[0]["methods"].split(",") == sorted(ROWS)
    pcas = {r["methods"] for r in rows if r["stage"] == "pca"}
    # A PCA per SegVLAD order, and segment_gem's own (fitted on its descriptors); the
    # re-ranked row re-orders segvlad's retrieval, so it uses segvlad's.
    assert pcas == {"segvlad_o0", "segvlad,segvlad+mnn", "segment_gem"}
    for method in ROWS:
        recall_log = workdir / "logs" / "by-method" / "toy" / method / "recall"
        assert list(recall_log.glob("*.log")), method
    link = workdir / "logs" / "by-method" / "toy" / "segvlad" / "pca"
    (pca_row,) = [r for r in rows if r["stage"] == "pca" and r["methods"].startswith("segvlad,")]
    assert link.resolve() == (workdir / pca_row["logs"]).resolve()


def test_stages_are_shared_and_self_describing(toy_run):
    workdir, _ = toy_run
    cache = workdir / "results" / "cache"
    stages = [s for s in cache.iterdir() if s.is_dir() and s.name in STAGES]
    counts = {s.name: len(list(s.glob("*.zarr"))) for s in stages}
    # Six methods share one features and segments store, five one vocabulary; PCA is
    # fitted once per SegVLAD neighbourhood order that uses it (orders 0 and 3), as
    # published, and once for segment_gem. Each re-ranked row adds a rerank and a recall;
    # the re-rankers of one method on the same features share one matches store.
    assert counts == {
        "images": 1,
        "dataset": 1,
        "features": 1,
        "segments": 1,
        "vocabulary": 1,
        "pca": 3,
        "descriptors": 6,
        "search": 5,  # one segment search per per-segment method
        "matches": 2,
        "rerank": 3,
        "recall": 9,
    }
    store = zarr.open_group(str(next((cache / "features").glob("*.zarr"))), mode="r")
    assert store.attrs["record"]["params"]["backbone"] == "daisy"
    assert store["features"].shape[:3] == (20, 9, 12)
    assert not list(cache.glob("*/*.tmp")), "temporary stores left behind"


def test_changing_order_rebuilds_pca_descriptors_and_recall_only(toy_run):
    workdir, config = toy_run
    changed = copy.deepcopy(config)
    changed["segvlad"]["order"] = 2
    path = write_config(workdir, changed, "order2.yaml")
    # segvlad+mnn re-ranks segvlad's retrieval, so its rerank reruns too.
    assert scheduled_stages(workdir, path, TARGET) == {
        "pca",
        "descriptors",
        "search",
        "matches",
        "rerank",
        "recall",
        "recall_csv",
    }
    changed["pca"]["fit_order"] = 3  # a fixed fit order keeps the order-3 PCA
    path = write_config(workdir, changed, "order2_fit3.yaml")
    assert scheduled_stages(workdir, path, TARGET) == {
        "descriptors",
        "search",
        "matches",
        "rerank",
        "recall",
        "recall_csv",
    }


def test_changing_segmenter_rebuilds_segments_pca_descriptors_not_features(toy_run):
    workdir, config = toy_run
    changed = copy.deepcopy(config)
    changed["segmenter"] = "felzenszwalb"
    path = write_config(workdir, changed, "felzenszwalb.yaml")
    assert scheduled_stages(workdir, path, TARGET) == {
        "segments",
        "pca",
        "descriptors",
        "search",
        "matches",
        "rerank",
        "recall",
        "recall_csv",
    }


def test_a_fresh_checkout_of_the_workflow_reruns_nothing(toy_run, tmp_path):
    """Its scripts are newer than every store (a clone, a worktree, an upgrade that
    rewrites stage.py): the keys decide, so nothing reruns; Snakemake's code trigger,
    which the workflow profile leaves out, would rerun every stage."""
    workdir, config = toy_run
    path = write_config(workdir, config, "fresh_checkout.yaml")
    checkout = tmp_path / "checkout" / "workflow"
    shutil.copytree(REPO / "workflow", checkout, copy_function=shutil.copy)  # new mtimes
    command = [str(checkout / "Snakefile") if Path(a) == SNAKEFILE else a
               for a in snakemake_command(workdir, path, "-n", TARGET)]  # fmt: skip
    for triggers, expected in (([], "Nothing to be done"), (["code", "mtime"], "rule images")):
        extra = ["--rerun-triggers", *triggers] if triggers else []
        result = dry_run(command + extra, workdir)
        assert result.returncode == 0, result.stderr[-3000:]
        assert expected in result.stdout + result.stderr, triggers


def with_execution_settings_flipped(config: dict, device: str) -> dict:
    """``config`` with every setting that shapes no result changed: the device, the shard
    sizes and each model entry's execution-only keys (:data:`EXECUTION_ONLY`)."""
    changed = copy.deepcopy(config)
    changed.update(device=device, shard_size=3, descriptors_shard_size=5, search_shard_size=4)
    for section in ("backbones", "segmenters"):
        for entry in changed[section].values():
            size = entry.get("batch_size", 1)
            entry["batch_size"] = 3 if size == "auto" else size + 2
            if "model" in entry:  # the entries that load weights read a cache
                entry["cache_dir"] = "/elsewhere/models"
    assert {"batch_size", "cache_dir"} == set(EXECUTION_ONLY)
    return changed


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_changing_any_execution_setting_after_a_finished_run_plans_nothing(toy_run, device):
    """Device, batch sizes, shard sizes, model cache and cores are in no key, and must
    not reach Snakemake's params or input triggers either: switching between a local
    `device: auto` run and a CPU cluster run (`device=cpu`) once reran 58 of 60 jobs."""
    workdir, config = toy_run
    path = write_config(workdir, with_execution_settings_flipped(config, device), "run.yaml")
    result = dry_run(snakemake_command(workdir, path, "-n", TARGET, cores=1), workdir)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Nothing to be done" in result.stdout + result.stderr, result.stdout[-3000:]


def test_a_table_copied_without_snakemakes_records_is_rebuilt_when_its_stores_change(
    toy_run, tmp_path
):
    """Snakemake keeps an existing table whose input stores are missing when it has no
    record of its job (a results/ folder copied without `.snakemake`): after a change
    of setting (or of a stage's format version) the old table stood as current, with
    "Nothing to be done". Changed back, nothing reruns."""
    source, config = toy_run
    workdir = tmp_path / "copy"
    shutil.copytree(source, workdir, symlinks=True, ignore=shutil.ignore_patterns(".snakemake"))
    changed = copy.deepcopy(config)
    changed["datasets"]["toy"]["recall_at"] = [1, 2]
    path = write_config(workdir, changed, "recall_at.yaml")
    result = dry_run(snakemake_command(workdir, path, "-n", TARGET), workdir)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-3000:]
    assert f"vprflow: {TARGET}: built from other stores than this plan's" in output
    assert "rule recall_csv:" in output and "Nothing to be done" not in output
    path = write_config(workdir, config, "as_built.yaml")
    result = dry_run(snakemake_command(workdir, path, "-n", TARGET), workdir)
    assert "Nothing to be done" in result.stdout + result.stderr, result.stdout[-3000:]


def test_changing_a_reranker_reruns_only_its_reranks_and_their_recall(toy_run):
    workdir, config = toy_run
    changed = copy.deepcopy(config)
    changed["rerankers"]["mnn"]["min_similarity"] = 0.5
    path = write_config(workdir, changed, "mnn_min_similarity.yaml")
    outputs = scheduled_outputs(workdir, path, TARGET)
    assert scheduled_stages(workdir, path, TARGET) == {"rerank", "recall", "recall_csv"}
    # anyloc_vlad+mnn and segvlad+mnn: one rerank and one recall each; ransac's stay.
    assert sum("results/cache/rerank/" in line for line in outputs) == 2
    assert sum("results/cache/recall/" in line for line in outputs) == 2


def test_changing_the_ground_truth_reruns_the_truth_store_and_recall_but_no_model_stage(toy_run):
    # The truth store and recall are all a ground-truth change shapes (the figures read
    # recall, so `all` would redraw them too): no images listing, features, segments or
    # vocabulary.
    workdir, config = toy_run
    changed = copy.deepcopy(config)
    changed["datasets"]["toy"]["ground_truth"] = {"kind": "frame_window", "radius": 1}
    path = write_config(workdir, changed, "frame_window.yaml")
    assert scheduled_stages(workdir, path, TARGET) == {"dataset", "recall", "recall_csv"}
    changed["datasets"]["toy"]["denominator"] = "all"
    path = write_config(workdir, changed, "frame_window_all.yaml")
    assert scheduled_stages(workdir, path, TARGET) == {"dataset", "recall", "recall_csv"}


def test_changing_a_value_and_back_schedules_at_most_the_csv(toy_run):
    workdir, config = toy_run
    original = write_config(workdir, config, "original.yaml")
    changed = copy.deepcopy(config)
    # One method's own value (its descriptors, search and recall rebuild, no PCA).
    changed["methods"]["segvlad_nopca"]["segvlad"] = {"order": 1}
    snakemake(workdir, write_config(workdir, changed, "order1.yaml"), TARGET)
    rows = {r["method"]: r for r in read_rows(workdir / TARGET)}
    assert rows["segvlad_nopca"]["segvlad.order"] == "1" and rows["segvlad"]["segvlad.order"] == "3"
    assert scheduled_stages(workdir, original, TARGET) <= {"recall_csv"}
    snakemake(workdir, original, TARGET)
    assert scheduled_stages(workdir, original, TARGET) == set()


def test_figures_are_drawn_and_a_figure_setting_reruns_only_figures(toy_run):
    workdir, config = toy_run
    original = write_config(workdir, config, "original.yaml")
    snakemake(workdir, original)  # the default target: `targets` datasets with figures
    figures = workdir / "results" / "figures" / "toy"
    assert sorted(p.name for p in (figures / "retrievals").iterdir()) == sorted(
        f"{m}.png" for m in ROWS
    )
    # Every per-segment method gets the segment-match figure, segment_gem included.
    per_segment = [m for m in METHODS if m != "anyloc_vlad"]
    assert sorted(p.name for p in (figures / "segment_matches").iterdir()) == sorted(
        f"{m}.png" for m in per_segment
    )
    assert (workdir / "results" / "plots" / "recall_toy.png").exists()
    assert (workdir / "logs" / "figures" / "toy" / "retrievals" / "segvlad.log").exists()
    changed = copy.deepcopy(config)
    changed["figures"]["queries"] = 2
    outputs = scheduled_outputs(workdir, write_config(workdir, changed, "fig.yaml"), "all")
    assert outputs and all(o.startswith("results/figures/toy/") for o in outputs), outputs
    assert scheduled_outputs(workdir, original, "all") == []


def test_export_writes_a_methods_descriptors_to_one_npz(toy_run):
    workdir, config = toy_run
    path = write_config(workdir, config, "original.yaml")
    targets = [f"results/export/toy/{m}.npz" for m in ("anyloc_vlad", "segvlad")]
    snakemake(workdir, path, *targets)
    index = read_rows_tsv(workdir / "results" / "cache" / "index.tsv")
    for method, target in zip(("anyloc_vlad", "segvlad"), targets, strict=True):
        store = next(
            r["store"]
            for r in index
            if r["stage"] == "descriptors" and method in r["methods"].split(",")
        )
        group = zarr.open_group(str(workdir / store), mode="r")
        with np.load(workdir / target, allow_pickle=False) as exported:
            np.testing.assert_array_equal(exported["descriptors"], group["descriptors"][...])
            assert len(exported["names"]) == len(exported["is_query"])
            assert exported["names"][0] == "ref/0000.png" and exported["is_query"][-1]
            assert str(exported["kind"]) == group.attrs["kind"]
            if method == "segvlad":
                np.testing.assert_array_equal(
                    exported["offsets"], group["descriptors_offsets"][...]
                )
    result = snakemake(workdir, path, "results/export/toy/nosuch.npz", check=False)
    assert result.returncode != 0 and "no method 'nosuch' on dataset 'toy'" in result.stderr


def test_pairs_files_are_pairs_depth_deep_and_a_new_depth_rewrites_only_them(toy_run):
    workdir, config = toy_run
    shallow = copy.deepcopy(config)
    shallow["pairs_depth"] = 2
    rows = ("anyloc_vlad", "anyloc_vlad+mnn", "segvlad")
    targets = [f"results/pairs/toy/{row}/pairs.txt" for row in rows]
    snakemake(workdir, write_config(workdir, shallow, "pairs2.yaml"), *targets)
    for row, target in zip(rows, targets, strict=True):
        queries = [line.split(" ")[0] for line in (workdir / target).read_text().splitlines()]
        per_query = {q: queries.count(q) for q in queries}
        # SegVLAD ranks only images that got a vote: a query may have fewer.
        assert len(per_query) == 10 and max(per_query.values()) == 2, row
        if row != "segvlad":
            assert set(per_query.values()) == {2}, row
    deeper = copy.deepcopy(config)
    deeper["pairs_depth"] = 3
    outputs = scheduled_outputs(workdir, write_config(workdir, deeper, "pairs3.yaml"), targets[1])
    assert outputs == [
        "results/pairs/toy/anyloc_vlad+mnn/pairs.txt, "
        "results/pairs/toy/anyloc_vlad+mnn/predictions.txt"
    ]


def read_rows_tsv(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f, delimiter="\t"))


def test_a_flipped_byte_in_a_descriptors_store_stops_the_recall_naming_the_store(toy_run, tmp_path):
    """A cached descriptors chunk damaged on disk: the recall stage that reads it fails
    with an error naming the store and the remedy, and no table is written (it used to
    rank whatever the chunk decoded to, NaN included)."""
    source, config = toy_run
    workdir = tmp_path / "run"
    shutil.copytree(source, workdir, symlinks=True)  # mtimes kept: nothing else is stale
    config_path = write_config(workdir, config)
    store = next(
        r["store"]
        for r in read_rows_tsv(workdir / "results" / "cache" / "index.tsv")
        if r["stage"] == "descriptors" and "anyloc_vlad" in r["methods"].split(",")
    )
    chunks = sorted((workdir / store / "descriptors" / "c").rglob("*"))
    chunk = next(p for p in chunks if p.is_file())
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    shutil.rmtree(workdir / "results" / "cache" / "recall")
    for table in (RECALL_CSV, PREDICTIONS_CSV, RECALL_TABLE, RECALL_PLOT):
        (workdir / table.format(dataset="toy")).unlink(missing_ok=True)
    result = snakemake(workdir, config_path, TARGET, check=False)
    assert result.returncode != 0
    named = f"StoreCorruptError: store {store}: array 'descriptors' cannot be decoded"
    remedy = f"Delete the store (rm -r {store}) and run snakemake again to rebuild it"
    output = result.stdout + result.stderr
    assert named in output and remedy in output, output[-3000:]
    logs = [p.read_text() for p in (workdir / "logs" / "recall").glob("*/*.log")]
    assert any(named in log and remedy in log for log in logs)
    assert not (workdir / TARGET).exists()
    assert not (workdir / PREDICTIONS_CSV.format(dataset="toy")).exists()


def test_a_dataset_without_ground_truth_gets_predictions_and_figures_not_a_table(tmp_path):
    make_dataset(tmp_path / "data" / "toy", n_places=6)
    # A global and a per-segment method (no PCA: not what this shows).
    methods = ["anyloc_vlad", "segvlad_nopca"]
    config = toy_config(tmp_path / "data", ground_truth={"kind": "none"}, methods=methods)
    path = write_config(tmp_path, config)
    snakemake(tmp_path, path)  # the default target: predictions and figures
    rows = read_rows(tmp_path / "results" / "predictions_toy.csv")
    assert len(rows) == 2 * 6
    assert all(r["positives"] == "" and r["first_correct_rank"] == "" for r in rows)
    assert all(len(r["top_scores"].split()) == len(r["top"].split()) > 0 for r in rows)
    assert {r["score_kind"] for r in rows} == {"squared_l2", "votes"}
    figures = (
        "retrievals/anyloc_vlad",
        "retrievals/segvlad_nopca",
        "segment_matches/segvlad_nopca",
    )
    for figure in figures:
        assert (tmp_path / "results" / "figures" / "toy" / f"{figure}.png").exists()
    assert not (tmp_path / "results" / "recall_toy.csv").exists()
    result = snakemake(tmp_path, path, "results/recall_toy.csv", check=False)
    assert result.returncode != 0
    assert "has ground_truth kind 'none': there is no recall to tabulate" in result.stderr


def test_same_inputs_give_a_byte_identical_csv_and_sharding_changes_nothing(toy_run, tmp_path):
    """The toy run again in shards, with a global and a per-segment method (each sharded
    stage's own path: global and ragged descriptors, segment search): the same rows and
    predictions but the timings, the same stores bit for bit."""
    workdir, config = toy_run
    make_dataset(tmp_path / "data" / "toy")
    sharded = copy.deepcopy(config)
    sharded["data_root"] = str(tmp_path / "data")
    methods = ["anyloc_vlad", "segvlad_nopca"]  # the PCA is not sharded
    sharded["datasets"]["toy"]["methods"] = methods
    # 20 images in shards of 13 and 7 (a short last one); 10 references: segment search
    # in 2 jobs, merged.
    sharded["shard_size"] = sharded["descriptors_shard_size"] = 13
    sharded["search_shard_size"] = 5
    snakemake(tmp_path, write_config(tmp_path, sharded), TARGET)
    # Byte for byte but the milliseconds a query, which time this run's stores; the
    # unsharded table has the other methods' rows and parameter columns too.
    header, rows = untimed_table(tmp_path / TARGET)
    _, unsharded = untimed_table(workdir / TARGET)
    names = expected_rows(sharded["datasets"]["toy"])  # the methods and their re-ranked rows
    assert [row["method"] for row in rows] == names
    assert rows == [
        {column: row[column] for column in header} for row in unsharded if row["method"] in names
    ]
    predictions = (tmp_path / "results" / "predictions_toy.csv").read_text().splitlines()
    unsharded = (workdir / "results" / "predictions_toy.csv").read_text().splitlines()
    assert predictions[0] == unsharded[0]  # the header, then the rows in the plan's order
    assert sorted(predictions[1:]) == sorted(
        line for line in unsharded[1:] if line.split(",")[0] in names
    )
    # Same keys (shard size is an execution setting), same arrays bit for bit.
    for stage, shards in (("features", 2), ("segments", 2), ("descriptors", 2), ("search", 2)):
        twins = sorted((tmp_path / "results" / "cache" / stage).glob("*.zarr"))
        assert twins, stage
        for twin in twins:
            store = workdir / "results" / "cache" / stage / twin.name
            a, b = zarr.open_group(str(store), mode="r"), zarr.open_group(str(twin), mode="r")
            assert len(b.attrs["shards"]) == shards and len(a.attrs["shards"]) == 1
            for name, array in array_items(a):
                np.testing.assert_array_equal(np.asarray(array[...]), np.asarray(b[name][...]))
