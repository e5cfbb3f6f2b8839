"""Every stage function run directly, without Snakemake, on a synthetic dataset with the
weight-free DAISY features and SLIC segments, checked against direct computations."""

from __future__ import annotations

import csv
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from synthetic import make_dataset
from workflow_helpers import toy_config

from vprflow.core import stores
from vprflow.core.errors import DatasetError
from vprflow.data.images import read_image, resize_image
from vprflow.evaluation.rerank import reranker
from vprflow.planning.config import validate_config
from vprflow.planning.plan import SHARDED, build_plan
from vprflow.stages.dataset import build_images
from vprflow.stages.descriptors import compute_descriptors
from vprflow.stages.export import ranking_at_depth, write_pairs
from vprflow.stages.features import compute_features
from vprflow.stages.gather import gather
from vprflow.stages.jobs import (
    Job,
    built_shard_ranges,
    combine_shards,
    run_job,
    shard_ranges,
)
from vprflow.stages.readers import (
    Dataset,
    read_centres,
    read_features,
    read_masks,
    read_pca,
    read_search,
)
from vprflow.stages.recall import compute_recall
from vprflow.stages.report import write_predictions, write_recall_csv
from vprflow.stages.retrieval import retrieve
from vprflow.stages.search import compute_search

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
METHODS = ["anyloc_vlad", "segvlad", "gem", "snsm", "segment_gem"]
N_PLACES = 6


class Runner:
    """Runs a plan's stages in dependency order through the rules' own table
    (:mod:`vprflow.stages.jobs`): per-image stages in two shards (references, queries),
    the segment search in uneven shards of 4 references, then combined; segments in
    batches of 4 (a ragged last batch in each shard)."""

    # The top-level config's shard sizes: every per-image stage in shards of N_PLACES.
    SHARD_SIZES = {"shard_size": N_PLACES, "descriptors_shard_size": N_PLACES}
    SHARD_SIZES["search_shard_size"] = 4

    def __init__(self, plan, data_root: Path, out: Path):
        self.plan, self.data_root, self.out = plan, str(data_root), out
        self.done: dict[tuple[str, str], str] = {}

    def path(self, stage: str, key: str) -> str:
        if (stage, key) not in self.done:
            self.done[stage, key] = self._run(self.plan.get(stage, key))
        return self.done[stage, key]

    def _run(self, stage) -> str:
        inputs = {name: self.path(*ref) for name, ref in stage.inputs.items()}
        out = str(self.out / stage.stage / f"{stage.key}.zarr")
        job = Job(
            stage.record,
            inputs,
            out,
            data_root=self.data_root,
            run={"device": "cpu", "batch_size": 4},
            threads=2,
        )
        if stage.stage not in SHARDED:
            run_job(job)
            return out
        dataset = Dataset(inputs["images"])
        ranges = shard_ranges(stage.stage, dataset.n_reference, dataset.n_query, self.SHARD_SIZES)
        shards = [f"{out}.shards/{start}-{stop}.zarr" for start, stop in ranges]
        for (start, stop), shard in zip(ranges, shards, strict=True):
            run_job(replace(job, out=shard, start=start, stop=stop))
        combine_shards(shards, stage.record, out)
        return out


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    root = tmp_path_factory.mktemp("stages")
    make_dataset(root / "data" / "toy", n_places=N_PLACES, width=64, height=48)
    config = toy_config(
        root / "data",
        resolution=[64, 48],
        recall_at=[1, 3],
        methods=METHODS,
        defaults={"pca": {"dim": 8, "whiten": False}, "segvlad": {"order": 1}},
        rerank={"anyloc_vlad": ["mnn"], "segvlad": ["ransac"]},
    )
    config["rerankers"] = {
        "mnn": {"kind": "mnn", "features": "daisy", "top_k": 4},
        "ransac": {"kind": "ransac", "features": "daisy", "min_similarity": 0.5},
    }
    config["vocabulary"].update(n_clusters=3, n_iter=5)
    config["segmenters"]["slic"].update(n_segments=6, resolution_scale=1.0)
    config = validate_config(config, SCHEMA)
    plan = build_plan(config)
    runner = Runner(plan, root / "data", root / "cache")
    recalls = [runner.path("recall", run.recall_key) for run in plan.runs["toy"]]
    return plan, runner, recalls, root


def stage_path(pipeline, stage: str, method: str = "segvlad") -> str:
    plan, runner, _, _ = pipeline
    run = {r.method: r for r in plan.runs["toy"]}[method]
    users = {}
    from vprflow.planning.store_index import stage_users

    for (name, key), rows in stage_users(plan).items():
        if name == stage and ("toy", method) in rows:
            users[key] = runner.path(name, key)
    assert len(users) == 1, (stage, method, run)
    return next(iter(users.values()))


def test_dataset_lists_images_and_truth(pipeline):
    dataset = Dataset(stage_path(pipeline, "dataset"))
    assert (dataset.n_reference, dataset.n_query) == (N_PLACES, N_PLACES)
    assert [list(t) for t in dataset.truth()][:2] == [[0, 1], [0, 1, 2]]
    assert dataset.paths[0] == "toy/ref/0000.png"


def test_sharded_daisy_features_equal_the_backbone_on_each_image(pipeline):
    from vprflow.models.backbones import DaisyBackbone

    _, _, _, root = pipeline
    group = stores.open_store(stage_path(pipeline, "features"))
    assert group["features"].shape == (2 * N_PLACES, 6, 8, 104)
    # The image ranges it was gathered from, which the workflow asks for again.
    assert group.attrs["shards"] == [[0, N_PLACES], [N_PLACES, 2 * N_PLACES]]
    assert built_shard_ranges(stage_path(pipeline, "features")) == [
        (0, N_PLACES),
        (N_PLACES, 2 * N_PLACES),
    ]
    # Gathered with the shards' codecs: float features are stored with the checksum alone.
    assert group["features"].raw.compressors == stores.CHECKSUM_ONLY
    backbone = DaisyBackbone(patch_size=8, radius=12)
    dataset = Dataset(stage_path(pipeline, "dataset"), str(root / "data"))
    for index in (0, N_PLACES + 1):  # one image of each shard
        pixels = resize_image(read_image(dataset.paths[index]), 64, 48, "linear")
        expected = backbone.features(pixels[None])[0]
        # Stored as float16: half-precision rounding of unit-norm values.
        np.testing.assert_allclose(read_features(group, index), expected, atol=1e-3)


def test_slic_segments_partition_every_image(pipeline):
    group = stores.open_store(stage_path(pipeline, "segments"))
    assert int(group["masks_offsets"][-1]) == group["masks"].shape[0]
    for index in range(2 * N_PLACES):
        masks = read_masks(group, index)
        assert masks.shape[1:] == (48, 64)
        np.testing.assert_array_equal(masks.sum(axis=0), 1)  # SLIC labels every pixel once


def test_the_feature_reader_gives_each_images_features_read_only(pipeline):
    from vprflow.stages.readers import FeatureReader

    group = stores.open_store(stage_path(pipeline, "features", "anyloc_vlad"))
    per_image = 4 * int(np.prod(group["features"].shape[1:]))
    for block_bytes in (0, 3 * per_image, 64 << 20):  # one image, 3, all of them a read
        reader = FeatureReader(group, block_bytes)
        for index in [0, 1, 5, 4, 11, 2]:  # forwards, back, across blocks
            grid = reader(index)
            np.testing.assert_array_equal(grid, read_features(group, index))
            assert grid.dtype == np.float32 and not grid.flags.writeable
            with pytest.raises(ValueError, match="read-only"):
                grid += 1


def test_vocabulary_and_pca_shapes(pipeline):
    centres = read_centres(stage_path(pipeline, "vocabulary"))
    assert centres.shape == (3, 104)
    pca = read_pca(stage_path(pipeline, "pca"))
    assert pca.components.shape == (8, 3 * 104)


def test_segvlad_descriptors_are_the_projected_segment_vlads(pipeline):
    """The descriptors stage equals image_segvlad + the PCA projection, per image."""
    from vprflow.aggregation.aggregators import vlad_input
    from vprflow.aggregation.segvlad import image_segvlad

    features = stores.open_store(stage_path(pipeline, "features"))
    segments = stores.open_store(stage_path(pipeline, "segments"))
    centres = read_centres(stage_path(pipeline, "vocabulary"))
    pca = read_pca(stage_path(pipeline, "pca"))
    group = stores.open_store(stage_path(pipeline, "descriptors"))
    offsets = np.asarray(group["descriptors_offsets"][...])
    for index in (1, 2 * N_PLACES - 1):
        vectors = image_segvlad(
            vlad_input(read_features(features, index), {"normalize_descriptors": True}),
            read_masks(segments, index),
            centres,
            (48, 64),
            8,
            1,
        )
        stored = np.asarray(group["descriptors"][offsets[index] : offsets[index + 1]])
        np.testing.assert_allclose(stored, pca.transform(vectors), rtol=1e-5, atol=1e-5)


def test_segment_gem_descriptors_are_each_segments_gem_projected(pipeline):
    """A second per-segment aggregator on SegVLAD's segment path: its descriptors equal a
    float64 GeM over each segment's patches (channel-normalised tokens), L2-normalised,
    then its own PCA, per image; its recall comes from the segment search and voting."""
    from vprflow.aggregation.segvlad import mask_patch_membership

    features = stores.open_store(stage_path(pipeline, "features", "segment_gem"))
    segments = stores.open_store(stage_path(pipeline, "segments", "segment_gem"))
    pca = read_pca(stage_path(pipeline, "pca", "segment_gem"))
    group = stores.open_store(stage_path(pipeline, "descriptors", "segment_gem"))
    offsets = np.asarray(group["descriptors_offsets"][...])
    for index in (0, 2 * N_PLACES - 2):
        grid = read_features(features, index).astype(np.float64)
        tokens = (grid / (np.linalg.norm(grid, axis=(0, 1)) + 1e-10)).reshape(-1, grid.shape[2])
        members = mask_patch_membership(read_masks(segments, index), (48, 64), (6, 8), 8)
        expected = []
        for member in members:
            mean = (tokens[member] ** 3).mean(axis=0)
            pooled = np.sign(mean) * np.abs(mean) ** (1 / 3)
            expected.append(pooled / np.linalg.norm(pooled))
        stored = np.asarray(group["descriptors"][offsets[index] : offsets[index + 1]])
        np.testing.assert_allclose(stored, pca.transform(np.array(expected)), atol=2e-5)
    recall = stores.open_store(stage_path(pipeline, "recall", "segment_gem"))
    assert "search" in dict(recall.attrs["record"]["inputs"])


def test_global_recall_matches_a_direct_ranking(pipeline):
    """Recall@N of a global method from a float64 brute-force L2 ranking in the test."""
    descriptors = np.asarray(
        stores.open_store(stage_path(pipeline, "descriptors", "anyloc_vlad"))["descriptors"][...],
        dtype=np.float64,
    )
    ref, query = descriptors[:N_PLACES], descriptors[N_PLACES:]
    truth = Dataset(stage_path(pipeline, "dataset")).truth()
    distances = ((query[:, None, :] - ref[None, :, :]) ** 2).sum(-1)
    order = np.argsort(distances, axis=1, kind="stable")
    # Ties closer than float32 precision would make the order arbitrary: none here.
    gaps = np.diff(np.sort(distances, axis=1), axis=1)
    assert gaps.min() > 1e-4 * distances.max()
    result = stores.open_store(stage_path(pipeline, "recall", "anyloc_vlad"))
    for n in (1, 3):
        direct = np.mean([bool(set(order[q, :n]) & set(truth[q])) for q in range(N_PLACES)])
        assert result.attrs["recall"][str(n)] == pytest.approx(direct, abs=1e-12)
    np.testing.assert_array_equal(np.asarray(result["ranking"][...])[:, :3], order[:, :3])


def rerank_store(pipeline, method: str):
    plan, runner, _, _ = pipeline
    run = {r.method: r for r in plan.runs["toy"]}[method]
    return stores.open_store(runner.path(*plan.get("recall", run.recall_key).inputs["rerank"]))


def test_reranked_rows_sort_the_retrieval_top_k_by_directly_counted_mutual_matches(pipeline):
    """anyloc_vlad+mnn: each candidate's score is the number of mutual nearest patch
    pairs, counted here in float64 with loops; the order is the retrieval's top 4
    sorted by that count, ties kept in retrieval order."""
    reranked = rerank_store(pipeline, "anyloc_vlad+mnn")
    features = stores.open_store(stage_path(pipeline, "features", "anyloc_vlad"))
    patches = np.asarray(features["features"][...], dtype=np.float64)
    patches = patches.reshape(len(patches), -1, patches.shape[-1])
    retrieved = np.asarray(reranked["retrieval_ranking"][...])
    recall = stores.open_store(stage_path(pipeline, "recall", "anyloc_vlad"))
    # As deep as the retrieval's ranking; the top 4 re-ordered, the rest kept in order.
    assert retrieved.shape == (N_PLACES, N_PLACES)
    np.testing.assert_array_equal(retrieved, np.asarray(recall["ranking"][...]))
    np.testing.assert_array_equal(reranked["ranking"][:, 4:], retrieved[:, 4:])
    retrieved = retrieved[:, :4]

    def mutual_pairs(a, b):
        sim = a @ b.T
        return sum(
            1
            for i in range(len(a))
            for j in range(len(b))
            if sim[i, j] == sim[i].max() and sim[i, j] == sim[:, j].max()
        )

    for q in range(N_PLACES):
        counts = [mutual_pairs(patches[N_PLACES + q], patches[r]) for r in retrieved[q]]
        order = sorted(range(4), key=lambda c: -counts[c])  # stable: retrieval order on ties
        np.testing.assert_array_equal(reranked["ranking"][q, :4], retrieved[q][order])
        np.testing.assert_array_equal(reranked["scores"][q, :4], np.array(counts)[order])
    assert reranked.attrs["score"] == "matches"


def test_the_matches_store_holds_each_candidates_mutual_pairs_and_rerank_scores_them(pipeline):
    """segvlad+ransac (top 100 of 6 references, min_similarity 0.5): the matches store's
    candidates are the retrieval's, each candidate's pairs all those of
    mutual_nearest_neighbours on the features store (min_similarity acts when scoring),
    and the rerank store's scores those of ransac_inliers over the pairs it keeps."""
    from vprflow.evaluation.rerank import mutual_nearest_neighbours, patch_centres, ransac_inliers
    from vprflow.stages.readers import Matches

    plan, runner, _, _ = pipeline
    run = {r.method: r for r in plan.runs["toy"]}["segvlad+ransac"]
    rerank = plan.get(*plan.get("recall", run.recall_key).inputs["rerank"])
    matches = Matches(runner.path(*rerank.inputs["matches"]))
    reranked = rerank_store(pipeline, "segvlad+ransac")
    features = stores.open_store(stage_path(pipeline, "features", "segvlad"))
    patches = np.asarray(features["features"][...], dtype=np.float32)
    patches = patches.reshape(len(patches), -1, patches.shape[-1])
    assert matches.grid == tuple(features.attrs["grid"]) and matches.top_k == N_PLACES
    np.testing.assert_array_equal(matches.retrieval_ranking, reranked["retrieval_ranking"][...])
    settings = reranker("ransac").settings(rerank.record["params"]["options"])
    assert settings["min_similarity"] == 0.5
    centres = patch_centres(*matches.grid, matches.patch)
    pixels = settings["threshold"] * matches.patch
    fit = {k: settings[k] for k in ("seed", "model", "max_iters", "confidence")}
    for q in range(N_PLACES):
        candidates = matches.candidates(q)
        np.testing.assert_array_equal(candidates, matches.retrieval_ranking[q, :N_PLACES])
        pairs = matches.pairs(q)
        assert len(pairs) == len(candidates)
        scores = np.zeros(len(candidates))
        for k, (r, stored) in enumerate(zip(candidates, pairs, strict=True)):
            i, j, similarity = direct = mutual_nearest_neighbours(patches[N_PLACES + q], patches[r])
            for got, want in zip(stored, direct, strict=True):
                np.testing.assert_array_equal(got, want)
            kept = similarity >= settings["min_similarity"]
            scores[k] = ransac_inliers(centres[i[kept]], centres[j[kept]], pixels, **fit)
        row = np.asarray(reranked["ranking"][q])
        order = np.argsort(-scores, kind="stable")
        np.testing.assert_array_equal(row[: len(candidates)], candidates[order])
        np.testing.assert_array_equal(reranked["scores"][q, : len(candidates)], scores[order])
    # Read a few pairs a block (each query's at least): the same pairs, in any order.
    small = Matches(runner.path(*rerank.inputs["matches"]))
    small._block = 5
    for q in [*range(N_PLACES), 0, N_PLACES - 1, 1]:
        for got, want in zip(small.pairs(q), matches.pairs(q), strict=True):
            for a, b in zip(got, want, strict=True):
                np.testing.assert_array_equal(a, b)
    cost = reranked.attrs["ms_per_query"] - matches.group.attrs["ms_per_query"]
    assert cost > 0  # the scoring's own time, beside the matching's
    assert reranked.attrs["search_ms_per_query"] == matches.group.attrs["search_ms_per_query"]


def test_reranking_on_one_thread_stores_what_two_threads_store(pipeline, tmp_path):
    """The rerank stage scores queries on job.threads threads (the pipeline runs 2):
    one thread stores the same ranking and scores."""
    plan, runner, _, _ = pipeline
    for method in ("anyloc_vlad+mnn", "segvlad+ransac"):
        run = {r.method: r for r in plan.runs["toy"]}[method]
        stage = plan.get(*plan.get("recall", run.recall_key).inputs["rerank"])
        inputs = {name: runner.path(*ref) for name, ref in stage.inputs.items()}
        out = str(tmp_path / f"{stage.key}.zarr")
        run_job(Job(stage.record, inputs, out, run={"device": "cpu"}, threads=1))
        one, two = stores.open_store(out), rerank_store(pipeline, method)
        for name in ("ranking", "scores", "retrieval_ranking"):
            np.testing.assert_array_equal(one[name][...], two[name][...])


def test_reranked_recall_reads_the_reranked_ranking_and_states_its_cost(pipeline):
    plan, runner, _, _ = pipeline
    truth = Dataset(stage_path(pipeline, "dataset")).truth()
    for method in ("anyloc_vlad+mnn", "segvlad+ransac"):
        run = {r.method: r for r in plan.runs["toy"]}[method]
        result = stores.open_store(runner.path("recall", run.recall_key))
        reranked = rerank_store(pipeline, method)
        ranking = np.asarray(reranked["ranking"][...])
        np.testing.assert_array_equal(result["ranking"][...], ranking)
        # What was re-ordered is kept for the report's before/after montage.
        np.testing.assert_array_equal(
            result["retrieval_ranking"][...], reranked["retrieval_ranking"][...]
        )
        direct = np.mean([ranking[q, 0] in truth[q] for q in range(N_PLACES)])
        assert result.attrs["recall"]["1"] == pytest.approx(direct, abs=1e-12)
        assert result.attrs["cost"]["rerank_ms_per_query"] > 0
    retrieval = stores.open_store(stage_path(pipeline, "recall", "anyloc_vlad"))
    assert retrieval.attrs["cost"]["rerank_ms_per_query"] is None
    assert "retrieval_ranking" not in retrieval
    dim = retrieval.attrs["descriptor_dim"]
    assert retrieval.attrs["cost"]["descriptor_bytes_per_image"] == 4 * dim


def retrieval_paths(pipeline, run) -> dict[str, str]:
    """The descriptors and (per-segment methods) search stores of a row's recall."""
    plan, runner, _, _ = pipeline
    inputs = plan.get("recall", run.recall_key).inputs
    return {
        f"{name}_path": runner.path(*inputs[name])
        for name in ("descriptors", "search")
        if name in inputs
    }


def test_pairs_files_list_each_querys_ranking_as_hloc_and_kapture_read_them(pipeline, tmp_path):
    plan, _, recalls, _ = pipeline
    dataset = Dataset(stage_path(pipeline, "dataset"))
    for run, path in zip(plan.runs["toy"], recalls, strict=True):
        pairs, kapture = tmp_path / f"{run.method}.txt", tmp_path / f"{run.method}.kapture"
        # 20 deep, past the toy's 6 references: every ranked reference.
        write_pairs(
            stage_path(pipeline, "dataset"),
            path,
            str(pairs),
            str(kapture),
            20,
            **retrieval_paths(pipeline, run),
        )
        result = stores.open_store(path)
        ranking, scores = np.asarray(result["ranking"]), np.asarray(result["scores"])
        expected = [
            (dataset.names[dataset.n_reference + q], dataset.names[r], scores[q, k])
            for q in range(dataset.n_query)
            for k, r in enumerate(ranking[q])
            if r >= 0 and (ranking[q, :k] >= 0).all()
        ]
        assert [tuple(line.split(" ")) for line in pairs.read_text().splitlines()] == [
            (query, reference) for query, reference, _ in expected
        ]
        lines = kapture.read_text().splitlines()
        assert lines[0] == "# kapture format: 1.0" and lines[2].startswith("# score: ")
        rows = [line.split(", ") for line in lines if not line.startswith("#")]
        assert [(q, r) for q, r, _ in rows] == [(q, r) for q, r, _ in expected]
        np.testing.assert_allclose(
            [float(v) for *_, v in rows], [v for *_, v in expected], rtol=1e-5
        )


def cut_recall_store(path: str, out: Path, width: int) -> str:
    """A copy of the recall store at ``path`` whose ranking and scores end after
    ``width`` columns, as a recall of fewer references than the pairs ask for."""
    result = stores.open_store(path)
    with stores.atomic_store(out, dict(result.attrs)) as group:
        for name in ("ranking", "scores"):
            stores.write_array(group, name, np.asarray(result[name][...])[:, :width])
    return str(out)


def test_the_pairs_depth_cuts_the_recalls_ranking_or_continues_it_with_the_retrieval(
    pipeline, tmp_path
):
    """Shallower than the recall's ranking: its first columns. Deeper (a recall store cut
    to 2 of the toy's 6 references): the recall's columns, then the method's own
    retrieval without the references already ranked; a re-ranked row's continuation
    scores as its lowest score."""
    plan, _, recalls, _ = pipeline
    dataset = Dataset(stage_path(pipeline, "dataset"))
    rows = {r.method: (r, path) for r, path in zip(plan.runs["toy"], recalls, strict=True)}
    for method in ("anyloc_vlad", "anyloc_vlad+mnn", "segvlad", "segvlad+ransac"):
        run, path = rows[method]
        paths = retrieval_paths(pipeline, run)
        result = stores.open_store(path)
        ranking, scores = np.asarray(result["ranking"]), np.asarray(result["scores"])
        shallow = ranking_at_depth(dataset, path, 3, **paths)
        np.testing.assert_array_equal(shallow[0], ranking[:, :3])
        np.testing.assert_array_equal(shallow[1], scores[:, :3])
        cut = cut_recall_store(path, tmp_path / f"{method}.zarr", 2)
        deep, deep_scores, kind = ranking_at_depth(dataset, cut, 6, **paths)
        assert deep.shape == (N_PLACES, 6) and kind == result.attrs["score"]
        np.testing.assert_array_equal(deep[:, :2], ranking[:, :2])
        retrieved = retrieve(
            dataset, paths["descriptors_path"], 6, paths.get("search_path"),
            result.attrs["record"]["params"].get("vote_ranking"),
        )  # fmt: skip
        for q in range(N_PLACES):
            rest = [r for r in retrieved[0][q] if r >= 0 and r not in ranking[q, :2]]
            assert list(deep[q, 2:]) == rest + [-1] * (4 - len(rest)), (method, q)
            if "+" in method:
                assert set(deep_scores[q, 2 : 2 + len(rest)]) <= {scores[q, :2].min()}
            elif (ranking[q] >= 0).all():  # the retrieval's own order and scores
                np.testing.assert_array_equal(deep[q], ranking[q])
                np.testing.assert_allclose(deep_scores[q], scores[q], rtol=1e-6)


def test_report_writes_one_row_per_method_and_every_prediction(pipeline, tmp_path):
    plan, _, recalls, _ = pipeline
    runs = [{"method": r.method, "params": r.row_params} for r in plan.runs["toy"]]
    csv_out, predictions_out = tmp_path / "recall.csv", tmp_path / "predictions.csv"
    dataset = stage_path(pipeline, "dataset")
    write_recall_csv("toy", runs, recalls, str(csv_out))
    write_predictions(dataset, runs, recalls, str(predictions_out))
    with open(csv_out) as f:
        rows = list(csv.DictReader(f))
    # Each method's row, its re-ranked rows right after it.
    rows_expected = [
        m
        for m in METHODS
        for m in (
            m,
            *{"anyloc_vlad": ["anyloc_vlad+mnn"], "segvlad": ["segvlad+ransac"]}.get(m, []),
        )
    ]
    assert [r["method"] for r in rows] == rows_expected
    for row, path in zip(rows, recalls, strict=True):
        attrs = stores.open_store(path).attrs
        assert float(row["recall@1"]) == pytest.approx(attrs["recall"]["1"], abs=1e-6)
        for name, value in attrs["precision_recall"].items():
            assert float(row[name]) == pytest.approx(value, abs=1e-6)
        assert (row["reranker"] != "") == ("+" in row["method"])
        assert (row["rerank_ms_per_query"] != "") == ("+" in row["method"])
    with open(predictions_out) as f:
        predictions = list(csv.DictReader(f))
    assert len(predictions) == len(rows_expected) * N_PLACES
    # Same inputs, same bytes.
    again = tmp_path / "again.csv"
    write_recall_csv("toy", runs, recalls, str(again))
    assert again.read_bytes() == csv_out.read_bytes()


def test_gather_of_one_shard_renames_it_with_the_gathered_attributes(tmp_path):
    shard = tmp_path / "x.shards" / "0-3.zarr"
    rows = np.arange(12, dtype=np.float32).reshape(6, 2)
    with stores.atomic_store(shard, {"stage": "descriptors", "start": 0, "stop": 3}) as group:
        writer = stores.RaggedWriter(group, "descriptors", (2,), np.float32, chunk_rows=4)
        for block in (rows[:1], rows[1:1], rows[1:]):
            writer.append(block)
        writer.close()
    out = tmp_path / "x.zarr"
    gather([str(shard)], {"stage": "descriptors", "key": "x"}, str(out))
    assert not shard.exists()
    group = stores.open_store(out)
    assert dict(group.attrs) == {
        "stage": "descriptors",
        "record": {"stage": "descriptors", "key": "x"},
        "shards": [[0, 3]],
    }
    np.testing.assert_array_equal(group["descriptors"][...], rows)
    np.testing.assert_array_equal(group["descriptors_offsets"][...], [0, 1, 1, 6])


def test_sharded_search_equals_one_faiss_search_over_all_references(pipeline):
    """Three reference shards merged give the lists of one exact search (ties by index)."""
    from vprflow.search.flat import flat_knn

    group = stores.open_store(stage_path(pipeline, "descriptors"))
    offsets = np.asarray(group["descriptors_offsets"][...])
    split = int(offsets[N_PLACES])
    vectors = np.asarray(group["descriptors"][...])
    distances, indices = read_search(stage_path(pipeline, "search"))
    expected_d, expected_i = flat_knn(vectors[:split], vectors[split:], 50)
    np.testing.assert_array_equal(distances, expected_d)
    np.testing.assert_array_equal(indices, expected_i)
    # Against float64: every list holds the true nearest segments.
    exact = ((vectors[split:, None, :].astype(np.float64) - vectors[None, :split]) ** 2).sum(-1)
    k = indices.shape[1]
    for row in range(len(exact)):
        kth = np.sort(exact[row])[k - 1]
        assert (exact[row, indices[row]] <= kth + 1e-4).all()


def test_float16_segment_descriptors_are_the_float32_ones_rounded(pipeline, tmp_path):
    plan, runner, _, _ = pipeline
    (stage,) = [
        s
        for s in plan.stages["descriptors"].values()
        if s.record["params"]["aggregator"] == "segvlad"
    ]
    inputs = {name: runner.path(*ref) for name, ref in stage.inputs.items()}
    params = {**stage.record, "params": {**stage.record["params"], "store_dtype": "float16"}}
    out = str(tmp_path / "half.zarr")
    compute_descriptors(Job(params, inputs, out))
    half = stores.open_store(out)["descriptors"]
    full = stores.open_store(stage_path(pipeline, "descriptors"))["descriptors"]
    assert half.dtype == np.float16
    np.testing.assert_array_equal(np.asarray(half[...]), np.asarray(full[...]).astype(np.float16))


@pytest.mark.parametrize("way", ["as probed", "on the pool", "on the calling thread"])
@pytest.mark.parametrize("method", ["segvlad", "anyloc_vlad"])
def test_descriptors_are_the_same_bits_with_more_threads(
    pipeline, tmp_path, monkeypatch, method, way
):
    """Images computed with three threads, on a pool of them or on the calling thread
    (whichever the probes find faster), store what the sharded one-thread runs stored."""
    from vprflow.stages import descriptors

    forced = {
        "on the pool": descriptors.in_order,
        "on the calling thread": lambda pool, function, items, workers: map(function, items),
    }
    if way in forced:
        monkeypatch.setattr(descriptors, "fastest_in_order", forced[way])
    plan, runner, _, _ = pipeline
    (stage,) = [
        s for s in plan.stages["descriptors"].values() if s.record["params"]["aggregator"] == method
    ]
    inputs = {name: runner.path(*ref) for name, ref in stage.inputs.items()}
    out = str(tmp_path / "threads.zarr")
    compute_descriptors(Job(stage.record, inputs, out, threads=3))
    threaded = stores.open_store(out)
    stored = stores.open_store(stage_path(pipeline, "descriptors", method))
    for name, array in stores.array_items(stored):
        np.testing.assert_array_equal(np.asarray(threaded[name]), np.asarray(array), err_msg=name)


def test_descriptor_stores_are_compressed_fast_and_read_back_as_zarr_reads_them(pipeline):
    """Every descriptors store (global, per segment, projected) uses FAST_COMPRESSORS;
    vprflow's row reader returns the bits zarr's own read does."""
    for method in ("segvlad", "anyloc_vlad", "segment_gem", "gem", "snsm"):
        group = stores.open_store(stage_path(pipeline, "descriptors", method))
        assert tuple(group["descriptors"].raw.compressors) == stores.FAST_COMPRESSORS, method
        rows = np.asarray(group["descriptors"][...])
        assert rows.tobytes() == np.asarray(group["descriptors"].raw[...]).tobytes(), method


class Ticks:
    """A clock that advances only when told: an item computed on the ``slow`` way (the
    pool's threads or the caller's) costs ``cost`` ticks, on the other 1."""

    def __init__(self, slow: str, cost: float = 10):
        import threading

        self.now, self.slow, self.cost, self.lock = 0, slow, cost, threading.Lock()

    def __call__(self) -> float:
        return self.now

    def compute(self, item: int) -> tuple[int, str]:
        import threading

        on_pool = threading.current_thread().name.startswith("probe-pool")
        with self.lock:
            self.now += self.cost if on_pool == (self.slow == "pool") else 1
        return item * item, "pool" if on_pool else "caller"


@pytest.mark.parametrize("slow", ["pool", "caller"])
@pytest.mark.parametrize(("cost", "rounds_run"), [(10, 1), (1.2, 3)])
@pytest.mark.parametrize("n_items", [0, 1, 5, 30, 200])
def test_fastest_in_order_yields_every_result_in_order_computed_the_faster_way(
    slow, cost, rounds_run, n_items
):
    """One way 10 times slower is clear after one round of probes; 1.2 times slower
    takes all three."""
    from concurrent.futures import ThreadPoolExecutor

    from vprflow.stages.descriptors import fastest_in_order

    ticks = Ticks(slow, cost)
    probe, rounds = 4, 3
    with ThreadPoolExecutor(2, thread_name_prefix="probe-pool") as pool:
        got = list(fastest_in_order(pool, ticks.compute, range(n_items), 2, probe, rounds, ticks))
    assert [value for value, _ in got] == [i * i for i in range(n_items)]
    ways = [way for _, way in got]
    # The first item alone on the calling thread, then the probes in turn, then the
    # faster way for the rest.
    expected = ["caller"] + (["caller"] * probe + ["pool"] * probe) * rounds_run
    faster = "caller" if slow == "pool" else "pool"
    expected += [faster] * max(0, n_items - len(expected))
    assert ways == expected[:n_items]


@pytest.mark.parametrize(
    ("index", "options"),
    [("exact_fast", {"block_database": 40}), ("ivf_flat", {"nlist": 4, "nprobe": 4})],
)
def test_other_indexes_search_the_same_descriptors(pipeline, tmp_path, index, options):
    """exact_fast gives the flat lists (float32 re-scored distances); an IVF index that
    probes every list is exhaustive too; with an approximate index, recall also reports
    the exact search's Recall@N, which equals the flat method's."""
    plan, runner, _, _ = pipeline
    (search,) = [
        s
        for s in plan.stages["search"].values()
        if runner.path(*s.inputs["descriptors"]) == stage_path(pipeline, "descriptors", "segvlad")
    ]
    inputs = {name: runner.path(*ref) for name, ref in search.inputs.items()}
    spec = {**search.record["params"], "index": index, "params": options}
    out = str(tmp_path / "search.zarr")
    compute_search(Job({**search.record, "params": spec}, inputs, out))
    distances, indices = read_search(out)
    flat_distances, flat_indices = read_search(stage_path(pipeline, "search"))
    np.testing.assert_array_equal(indices, flat_indices)
    np.testing.assert_allclose(distances, flat_distances, rtol=1e-5, atol=1e-5)
    (recall,) = [
        s
        for s in plan.stages["recall"].values()
        if s.inputs.get("search") == ("search", search.key) and "rerank" not in s.inputs
    ]
    result = str(tmp_path / "recall.zarr")
    dataset = stage_path(pipeline, "dataset")
    both = {"search": out, "exact_search": out}
    compute_recall(
        Job(
            recall.record,
            {"dataset": dataset, "descriptors": inputs["descriptors"], **both},
            result,
        )
    )
    attrs = stores.open_store(result).attrs
    flat = stores.open_store(stage_path(pipeline, "recall", "segvlad")).attrs
    assert attrs["recall_exact"] == attrs["recall"] == flat["recall"]


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


# ------------------------------------------------------------------ what the key covers


def small_plan(root: Path, memo: dict | None = None, make: bool = True):
    """A validated plan of one global method on a 3-place toy dataset (made fresh)."""
    if make:
        make_dataset(root / "data" / "toy", n_places=3, width=32, height=24)
    config = toy_config(root / "data", resolution=[32, 24], methods=["gem"])
    return build_plan(validate_config(config, SCHEMA), memo)


def test_an_image_changed_after_the_dataset_stage_fails_the_stage_reading_it(tmp_path):
    plan = small_plan(tmp_path)
    dataset_stage = plan.get("images", plan.images_keys["toy"])
    dataset_path = str(tmp_path / "dataset.zarr")
    build_images(Job(dataset_stage.record, {}, dataset_path, data_root=str(tmp_path / "data")))
    features = next(iter(plan.stages["features"].values()))
    changed = tmp_path / "data/toy/query/0001.jpg"
    changed.write_bytes((tmp_path / "data/toy/query/0002.jpg").read_bytes())
    out = tmp_path / "features.zarr"
    with pytest.raises(DatasetError, match=r"query/0001\.jpg changed after the images stage"):
        compute_features(
            Job(
                features.record,
                {"images": dataset_path},
                str(out),
                data_root=str(tmp_path / "data"),
                run={"device": "cpu"},
            )
        )
    assert not out.exists()


def test_a_vits_features_are_the_same_bits_in_batches_of_one_four_or_auto(tmp_path):
    from tiny_models import save_tiny_dinov2

    make_dataset(tmp_path / "data" / "toy", n_places=3, width=64, height=48)
    config = toy_config(
        tmp_path / "data", resolution=[64, 48], methods=["gem"], defaults={"features": "vit"}
    )
    model = save_tiny_dinov2(tmp_path / "vit", hidden_size=32, image_size=56, seed=0)
    config["backbones"]["vit"] = {"backbone": "dinov2", "model": str(model), "layer": 1}
    plan = build_plan(validate_config(config, SCHEMA))
    dataset = str(tmp_path / "dataset.zarr")
    images = plan.get("images", plan.images_keys["toy"])
    build_images(Job(images.record, {}, dataset, data_root=str(tmp_path / "data")))
    features = next(iter(plan.stages["features"].values()))
    stored = {}
    for size in (1, 4, "auto"):  # 6 images: 4 then a ragged 2
        out = str(tmp_path / f"features-{size}.zarr")
        run = {"device": "cpu", "batch_size": size}
        root = str(tmp_path / "data")
        job = Job(features.record, {"images": dataset}, out, data_root=root, run=run, threads=2)
        compute_features(job)
        group = stores.open_store(out)
        stored[size] = np.asarray(group["features"][...]), dict(group.attrs)
    (alone, attrs), *others = stored.values()
    assert alone.shape == (6, 3, 4, 32)
    for batched, batched_attrs in others:
        np.testing.assert_array_equal(batched, alone)
        assert batched_attrs == attrs


def test_a_batch_size_neither_whole_nor_auto_is_refused_naming_it(tmp_path):
    plan = small_plan(tmp_path)
    dataset = str(tmp_path / "dataset.zarr")
    images = plan.get("images", plan.images_keys["toy"])
    build_images(Job(images.record, {}, dataset, data_root=str(tmp_path / "data")))
    features = next(iter(plan.stages["features"].values()))
    run = {"device": "cpu", "batch_size": "max"}
    with pytest.raises(ValueError, match="batch_size.*'max'"):
        compute_features(Job(features.record, {"images": dataset}, str(tmp_path / "f"), run=run))


def test_an_image_changed_after_planning_fails_the_dataset_stage_naming_it(tmp_path):
    from vprflow.planning.fingerprints import save_fingerprints

    memo = {}
    plan = small_plan(tmp_path, memo=memo)
    save_fingerprints(memo, tmp_path / "fingerprints.json")
    changed = tmp_path / "data/toy/ref/0002.png"
    changed.write_bytes((tmp_path / "data/toy/ref/0000.png").read_bytes())
    stage = plan.get("images", plan.images_keys["toy"])
    out = tmp_path / "dataset.zarr"
    with pytest.raises(DatasetError, match=r"changed after this run planned it.*ref/0002\.png"):
        build_images(
            Job(
                stage.record,
                {},
                str(out),
                data_root=str(tmp_path / "data"),
                fingerprints=str(tmp_path / "fingerprints.json"),
            )
        )
    assert not out.exists()


def test_a_query_that_is_a_copy_of_a_reference_is_refused(tmp_path):
    small_plan(tmp_path)
    toy = tmp_path / "data/toy"
    (toy / "query/0001.jpg").unlink()
    (toy / "query/0001.png").write_bytes((toy / "ref/0001.png").read_bytes())
    plan = small_plan(tmp_path, make=False)
    stage = plan.get("images", plan.images_keys["toy"])
    with pytest.raises(DatasetError, match=r"byte-identical.*query/0001\.png = .*ref/0001\.png"):
        build_images(
            Job(stage.record, {}, str(tmp_path / "d.zarr"), data_root=str(tmp_path / "data"))
        )


def test_images_are_read_upright_everywhere_as_their_exif_orientation_says(tmp_path):
    from PIL import Image

    make_dataset(tmp_path / "data" / "toy", n_places=3, width=32, height=24)
    toy = tmp_path / "data/toy"
    upright = np.asarray(Image.open(toy / "ref/0001.png"))
    exif = Image.Exif()
    exif[0x0112] = 6  # stored turned; "rotate 90 degrees clockwise to view"
    Image.fromarray(np.ascontiguousarray(np.rot90(upright, k=1))).save(
        toy / "ref/0001.png", exif=exif.tobytes()
    )
    plan = small_plan(tmp_path, make=False)
    stage = plan.get("images", plan.images_keys["toy"])
    build_images(Job(stage.record, {}, str(tmp_path / "d.zarr"), data_root=str(tmp_path / "data")))
    dataset = Dataset(str(tmp_path / "d.zarr"), str(tmp_path / "data"))
    np.testing.assert_array_equal(dataset.read_image(1), upright.astype(np.float32) / 255.0)
    # A method whose published reader ignores the tag (SNSM) reads the stored pixels.
    stored = np.rot90(upright, k=1).astype(np.float32) / 255.0
    np.testing.assert_array_equal(dataset.read_image(1, "ignore"), stored)
    sizes = np.asarray(dataset.group["image_sizes"][...])
    assert sizes[1].tolist() == [24, 32]  # height, width after the orientation


def test_the_dataset_stage_lists_images_as_planned(tmp_path):
    # follow_links and recursive reach the dataset stage (they are in its key): a linked
    # image folder elsewhere is read when asked, and a nested folder left out when not.
    make_dataset(tmp_path / "elsewhere" / "toy", n_places=3, width=32, height=24)
    toy = tmp_path / "data" / "toy"
    toy.mkdir(parents=True)
    (toy / "ref").symlink_to(tmp_path / "elsewhere/toy/ref")
    (toy / "query").mkdir()
    (toy / "query/run1").symlink_to(tmp_path / "elsewhere/toy/query")
    (toy / "ground_truth_new.npy").symlink_to(tmp_path / "elsewhere/toy/ground_truth_new.npy")
    make_dataset(tmp_path / "nested" / "toy", n_places=3, width=32, height=24)
    (tmp_path / "nested/toy/query/old").mkdir()
    (tmp_path / "nested/toy/query/0000.jpg").rename(tmp_path / "nested/toy/query/old/0000.jpg")
    for root, overrides in (
        (tmp_path / "data", {"follow_links": True}),
        (tmp_path / "nested", {"recursive": False, "ground_truth": {"kind": "none"}}),
    ):
        config = toy_config(root, resolution=[32, 24], methods=["gem"], **overrides)
        plan = build_plan(validate_config(config, SCHEMA))
        stage = plan.get("images", plan.images_keys["toy"])
        out = tmp_path / f"{root.name}.zarr"
        build_images(Job(stage.record, {}, str(out), data_root=str(root)))
        names = Dataset(str(out)).names
        expected = ["run1/0000.jpg", "run1/0001.jpg", "run1/0002.jpg"]
        if root.name == "nested":
            expected = ["0001.jpg", "0002.jpg"]
        assert [n.removeprefix("query/") for n in names[3:]] == expected


def test_a_new_aggregator_is_its_compute_function_and_nothing_in_the_stages(pipeline):
    """An entry's ``compute`` runs over each image's patch grid with the method's
    options, as every aggregator's does: GeM of the channel-normalised tokens this way
    gives the gem method's stored descriptors bit for bit."""
    from vprflow.aggregation.aggregators import Aggregator
    from vprflow.stages.image_descriptors import image_descriptor

    path = stage_path(pipeline, "features", "gem")
    stored = stores.open_store(stage_path(pipeline, "descriptors", "gem"))["descriptors"]
    new = Aggregator("gem_again", (), "global", _normalised_gem)
    options = {"aggregator": "gem_again", "p": 3.0, "normalization": "channel"}
    describe = image_descriptor(new, options, {"features": path})
    for index in (0, 2 * N_PLACES - 1):
        np.testing.assert_array_equal(describe(index), stored[index])


def _normalised_gem(grid: np.ndarray, options: dict) -> np.ndarray:
    from vprflow.aggregation.pooling import gem
    from vprflow.aggregation.snsm import normalize_tokens

    return gem(normalize_tokens(grid, options["normalization"]), p=options["p"])


def test_an_auto_batch_is_sized_from_the_first_images_memory_and_halved_when_out_of_memory(
    monkeypatch,
):
    """The CUDA path of ``batch_size: auto`` with torch.cuda's memory counters faked: the
    first image alone takes 1 GiB of activations beside 8 GiB free (so batches of 6 at
    80%), and a batch of more than 4 runs out of memory (so 6 is halved to 3)."""
    import torch

    from vprflow.stages import features

    gib, peak = 2**30, {"bytes": 0}
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: None)
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", lambda device=None: None)
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: None)
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device=None: 0)
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda device=None: 0)
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda device=None: peak["bytes"])
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (8 * gib, 80 * gib))
    calls = []

    def extract(pixels):
        calls.append(len(pixels))
        if len(pixels) > 4:
            raise torch.cuda.OutOfMemoryError("CUDA out of memory")
        peak["bytes"] = len(pixels) * gib
        return pixels[:, :1, :1, :1] * 2

    sizes = features._batch_sizes("auto", torch.device("cuda"), extract)
    with ThreadPoolExecutor(2) as pool:
        ahead = features._ReadAhead(pool, lambda i: np.full((2, 2, 3), i, np.float32), range(14))
        done, outputs = 0, []
        while done < 14:
            grids, count = sizes.run(ahead, 14 - done)
            outputs.append(grids)
            done += count
    assert calls == [1, 6, 3, 3, 3, 3, 1]
    np.testing.assert_array_equal(np.concatenate(outputs)[:, 0, 0, 0], 2 * np.arange(14))
    assert sizes.size == 3


def test_segments_come_in_image_order_with_the_next_batch_read_while_one_is_segmented():
    import threading

    from vprflow.stages.segments import _segmented

    second_read = threading.Event()

    def read(indices):
        if indices[0] == 2:
            second_read.set()
        return [np.full((index + 1, 2, 2), True) for index in indices]

    def segment(images):
        if len(images[0]) == 1:  # the first batch waits until the second is being read
            assert second_read.wait(timeout=60), "the next batch was not read ahead"
        return images

    out = list(_segmented(read, segment, [0, 1, 2, 3, 4], batch_size=2))
    assert [index for index, _ in out] == [0, 1, 2, 3, 4]
    assert [len(masks) for _, masks in out] == [1, 2, 3, 4, 5]
