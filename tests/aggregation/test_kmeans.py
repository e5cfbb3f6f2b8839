"""vprflow's spherical k-means (vprflow.aggregation.kmeans) against Lloyd's iterations
written out in float64 here, and against faiss's ``Kmeans(spherical=True)``, whose start
and empty-cluster splits it takes.

Tolerances: the centroids within 1e-12 of the formula's (both float64; the sums differ
only in their order: the module adds a cluster's points one after another, numpy's
``sum`` pairwise), the labels and iterations equal. Against faiss (float32 sums in
another order), 1e-6 after one iteration on points whose products are exact.
tests/workflow/test_code_paths.py runs the k-means on the shipped data under every code path.
"""

from __future__ import annotations

from dataclasses import replace

import faiss
import numpy as np
import pytest
import torch
from synthetic import make_dataset
from workflow_helpers import SCHEMA, repo_config, toy_config

from vprflow.aggregation import kmeans, vlad
from vprflow.aggregation.kmeans import TIE, spherical_kmeans
from vprflow.aggregation.vlad import fit_spherical_kmeans
from vprflow.core import stores
from vprflow.models.kinds import model_kind
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.jobs import Job, run_job
from vprflow.stages.readers import read_centres

EXACT = 1e-12


def unit_points(n, d, seed):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, d))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def repeated_patterns(n, d, pool, seed):
    """``n`` points drawn from ``pool`` distinct unit patterns of four +-1/2 entries:
    repeated points (so repeated initial centroids, exact ties, then empty clusters)
    and products that are exact in float32 and float64."""
    rng = np.random.default_rng(seed)
    patterns = np.zeros((pool, d), dtype=np.float32)
    for row in patterns:
        row[rng.choice(d, 4, replace=False)] = rng.choice([-0.5, 0.5], 4)
    return patterns[rng.integers(0, pool, n)]


def lloyd(x, k, n_iter, seed):
    """The k-means written out: faiss's first points, then per iteration each point to
    the lowest-index centroid within TIE of its best float64 product, a centroid the
    float64 mean of its points (an empty one split as faiss splits it), normalised;
    stop when no point moves -> (centroids, labels, iterations)."""
    x = x.astype(np.float64)
    perm = np.empty(len(x), dtype=np.int32)
    faiss.rand_perm(faiss.swig_ptr(perm), len(x), seed + 1)
    c = x[perm[:k]] / np.linalg.norm(x[perm[:k]], axis=1, keepdims=True)

    def labels_of(c):
        products = np.einsum("nd,kd->nk", x, c)
        tied = products >= products.max(axis=1, keepdims=True) - TIE
        return np.array([np.flatnonzero(row)[0] for row in tied])

    labels = None
    for iteration in range(1, n_iter + 1):
        moved = labels_of(c)
        if labels is not None and (moved == labels).all():
            return c, labels, iteration
        labels = moved
        counts = np.array([(labels == j).sum() for j in range(k)])
        c = np.stack([x[labels == j].sum(axis=0) / max(counts[j], 1) for j in range(k)])
        for ci, cj in kmeans.split_clusters(counts.astype(np.float32), len(x)):
            c[ci] = c[cj] * np.resize([1 + 1 / 1024, 1 - 1 / 1024], x.shape[1])
            c[cj] = c[cj] * np.resize([1 - 1 / 1024, 1 + 1 / 1024], x.shape[1])
        norms = np.linalg.norm(c, axis=1, keepdims=True)
        c = np.where(norms > 0, c / np.where(norms > 0, norms, 1), 0)
    return c, labels_of(c), n_iter


def assert_is_lloyd(x, k, n_iter, seed, device=None):
    expected, labels, iterations = lloyd(x, k, n_iter, seed)
    centroids, actual_labels, actual_iterations = spherical_kmeans(x, k, n_iter, seed, device)
    assert centroids.dtype == np.float64
    assert actual_iterations == iterations
    np.testing.assert_array_equal(actual_labels, labels)
    np.testing.assert_allclose(centroids, expected, rtol=0, atol=EXACT)


@pytest.mark.parametrize(("n", "d", "k"), [(2000, 16, 8), (2500, 64, 32)])
@pytest.mark.parametrize("seed", [0, 1])
def test_the_kmeans_is_lloyds_iterations_written_in_float64(n, d, k, seed):
    assert_is_lloyd(unit_points(n, d, seed), k, 100, seed)


@pytest.mark.parametrize(("n", "d", "k", "pool"), [(400, 16, 8, 40), (2000, 64, 20, 60)])
def test_repeated_points_tie_to_the_lowest_index_and_empty_clusters_are_split(n, d, k, pool):
    """Two initial centroids on one point tie exactly for every point: the lowest index
    takes them all, the other ends empty and is split off a donor."""
    splits = []
    original = kmeans.split_clusters

    def counting(counts, n):
        done = original(counts, n)
        splits.extend(done)
        return done

    for seed in (0, 2):
        x = repeated_patterns(n, d, pool, seed)
        expected = lloyd(x, k, 50, seed)
        kmeans.split_clusters = counting
        try:
            centroids, labels, iterations = spherical_kmeans(x, k, 50, seed)
        finally:
            kmeans.split_clusters = original
        assert iterations == expected[2]
        np.testing.assert_array_equal(labels, expected[1])
        np.testing.assert_allclose(centroids, expected[0], rtol=0, atol=EXACT)
    assert splits  # the inputs do force empty clusters


@pytest.mark.parametrize(("n", "d", "k", "pool"), [(400, 16, 8, 40), (1500, 64, 20, 60)])
def test_the_start_and_the_splits_are_faiss_own(n, d, k, pool):
    """One iteration on points with exact products, below faiss's BLAS threshold (where
    it takes the lowest index of equal products, as here): faiss's centroids, splits
    included, within float32 rounding of its sums."""
    assert n * d < faiss.cvar.distance_compute_blas_threshold
    for seed in (0, 2):
        x = repeated_patterns(n, d, pool, seed)
        km = faiss.Kmeans(
            d, k, niter=1, spherical=True, seed=seed, max_points_per_centroid=n // k + 1
        )
        km.train(x)
        assert km.iteration_stats[0]["nsplit"] > 0
        centroids, _, _ = spherical_kmeans(x, k, 1, seed)
        np.testing.assert_allclose(centroids, km.centroids, rtol=0, atol=1e-6)


def test_products_taken_by_torch_give_the_same_run():
    """Another device takes the products in torch (played here by torch on the CPU): the
    labels are decided alike, so the centroids are equal, bit for bit."""
    x = unit_points(2500, 64, 3)
    numpy_run = spherical_kmeans(x, 16, 40, 3)
    torch_run = spherical_kmeans(x, 16, 40, 3, torch.device("cpu"))
    np.testing.assert_array_equal(torch_run[0], numpy_run[0])
    np.testing.assert_array_equal(torch_run[1], numpy_run[1])
    assert torch_run[2] == numpy_run[2]


def test_as_many_points_as_clusters_are_the_centroids_as_faiss_copies_them():
    x = unit_points(8, 16, 3)
    centroids, labels, iterations = spherical_kmeans(x, 8, 10, 0)
    np.testing.assert_array_equal(centroids, x.astype(np.float64))
    np.testing.assert_array_equal(labels, np.arange(8))
    assert iterations == 0


@pytest.mark.parametrize("centres", vlad.CENTRES)
def test_the_vocabulary_centres_are_the_unit_centroids_or_their_members_means(centres):
    """``unit``: the centroids rounded to float32; ``mean``: the float64 mean of each
    centroid's members (points normalised first), an empty cluster's unit centroid."""
    x = unit_points(2500, 32, 5) * 3.0  # not unit: normalised first
    x[:40] = x[40]  # repeated points: an empty cluster to fall back on
    unit = x.astype(np.float64) / np.linalg.norm(x.astype(np.float64), axis=1, keepdims=True)
    unit = unit.astype(np.float32)
    centroids, labels, _ = spherical_kmeans(unit, 16, 50, 5)
    actual = fit_spherical_kmeans(x, 16, 50, 5, centres=centres)
    assert actual.dtype == np.float32 and actual.shape == (16, 32)
    if centres == "unit":
        np.testing.assert_array_equal(actual, centroids.astype(np.float32))
        return
    for c in range(16):
        members = unit[labels == c].astype(np.float64)
        expected = members.mean(axis=0) if len(members) else centroids[c]
        np.testing.assert_allclose(actual[c], expected, rtol=0, atol=1e-7)


def test_kmeans_refuses_non_finite_points():
    x = unit_points(100, 8, 0)
    x[3, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        fit_spherical_kmeans(x, 4, 10, 0)


# ------------------------------------------------------------------ the vocabulary stage


def test_the_vocabulary_stage_stores_the_same_centres_on_cpu_and_auto(tmp_path):
    """``device: cpu`` and ``auto`` store the same centres under the same record (on a
    GPU, ``auto`` takes the products there, where the plan gives the stage a GPU
    (``uses_gpu``, a model's features): the same decisions)."""
    make_dataset(tmp_path / "data" / "toy", n_places=4, width=64, height=48)
    config = toy_config(tmp_path / "data", resolution=[64, 48], methods=["anyloc_vlad"])
    config["vocabulary"].update(n_clusters=3, n_iter=5)
    plan = build_plan(validate_config(config, SCHEMA))
    (stage,) = plan.stages["vocabulary"].values()
    assert stage.run_params == {"device": config["device"], "uses_gpu": False}

    def run(stage, device, out):
        inputs = {name: run(plan.get(*ref), device, out) for name, ref in stage.inputs.items()}
        path = str(out / f"{stage.stage}.zarr")
        job = Job(stage.record, inputs, path, data_root=str(tmp_path / "data"))
        run_job(replace(job, run={"device": device, "uses_gpu": True}))
        return path

    cpu, auto = (run(stage, device, tmp_path / device) for device in ("cpu", "auto"))
    np.testing.assert_array_equal(read_centres(auto), read_centres(cpu))
    assert stores.open_store(auto).attrs["record"] == stores.open_store(cpu).attrs["record"]
    assert read_centres(cpu).shape[0] == 3


def test_the_vocabulary_stage_asks_a_gpu_to_fit_a_models_features_only(tmp_path):
    """A fitted vocabulary runs where its features' model does (`device`, and a cluster
    GPU for a model's features); one read from a file needs none. The device is no
    part of the key."""
    centres = tmp_path / "centres.npy"
    np.save(centres, np.eye(4, dtype=np.float32))
    raw = repo_config()
    raw["datasets"] = {"corridor": raw["datasets"]["corridor"]}
    raw["datasets"]["corridor"]["methods"] = ["anyloc_vlad", "anyloc_vlad_file"]
    raw["methods"]["anyloc_vlad_file"] = {
        "aggregator": "anyloc_vlad",
        "vocabulary": {"source": "file", "file": str(centres)},
    }
    keys = set()
    for features in ("daisy", "dinov2_vitg14"):
        raw["datasets"]["corridor"]["defaults"]["features"] = features
        uses_gpu = model_kind("features", raw["backbones"][features]).uses_gpu
        assert uses_gpu is (features != "daisy")
        for device in ("auto", "cpu"):
            raw["device"] = device
            plan = build_plan(validate_config(raw, SCHEMA))
            fitted = {
                stage.record["params"]["source"]: stage
                for stage in plan.stages["vocabulary"].values()
            }
            assert fitted["map"].run_params == {"device": device, "uses_gpu": uses_gpu}
            assert fitted["file"].run_params == {"device": device, "uses_gpu": False}
            keys.add((features, fitted["map"].key, fitted["file"].key))
    assert len(keys) == 2  # one per features: the device changes no key
