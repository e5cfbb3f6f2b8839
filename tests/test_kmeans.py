"""The vocabulary's k-means in torch (vprflow.aggregation.kmeans) against faiss's own
``faiss.Kmeans(spherical=True)``, on the CPU in float64 and float32.

Tolerance: 1e-6 absolute on the entries of the unit centroids (about 8 float32 ulps of
1). faiss sums a cluster's points one after another in float32 and multiplies by the
float32 reciprocal of its count; torch sums them in a matrix product (another order in
float32, nearly exact in float64), so the centroids differ in the last bits (measured
here: at most 3e-7). A point moving to another cluster anywhere in the run would move
its centroids by about one over the cluster's size (1e-3 and more at these sizes), so
the tolerance tells a float difference from a different run. The iterations run must be
equal, and the final assignments identical except at near ties: points whose best and
second-best products under faiss's centroids differ by less than 1e-5 (what a 1e-6
change of the centroids can reverse at these dimensions); none differ on these inputs.
A near tie in the middle of a run can take the two runs apart to neighbouring solutions
(faiss itself parts so from its own run when its SIMD level changes); these inputs,
fixed, have none, and ``benchmarks/bench_vocabulary.py`` reports it where it happens.

Paths: faiss multiplies one product at a time below ``n * d = 128,000``
(``distance_compute_blas_threshold``), through BLAS with a SIMD argmax above it; each
test covers both.
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
from vprflow.aggregation.kmeans import spherical_kmeans, tie_order
from vprflow.aggregation.vlad import fit_spherical_kmeans, spherical_centroids
from vprflow.core import stores
from vprflow.models.kinds import model_kind
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.jobs import Job, run_job
from vprflow.stages.readers import read_centres

ATOL = 1e-6
NEAR_TIE = 1e-5
# (points, dimensions, clusters): below and above faiss's BLAS threshold.
SHAPES = [(2000, 16, 8), (2500, 64, 32)]
DTYPES = [torch.float64, torch.float32]


def unit_points(n, d, seed):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, d))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def repeated_patterns(n, d, pool, seed):
    """``n`` points drawn from ``pool`` distinct unit patterns of four +-1/2 entries:
    repeated points (so repeated initial centroids, then empty clusters) and products
    that are exact in float32 (so ties are exact, and broken by the tie rule)."""
    rng = np.random.default_rng(seed)
    patterns = np.zeros((pool, d), dtype=np.float32)
    for row in patterns:
        row[rng.choice(d, 4, replace=False)] = rng.choice([-0.5, 0.5], 4)
    return patterns[rng.integers(0, pool, n)]


def faiss_kmeans(x, k, n_iter, seed):
    km = faiss.Kmeans(
        x.shape[1],
        k,
        niter=n_iter,
        spherical=True,
        seed=seed,
        max_points_per_centroid=max(256, len(x) // k + 1),
    )
    km.train(x)
    return km.centroids, km.iteration_stats


def assert_same_kmeans(x, k, n_iter, seed, dtype):
    """torch's run equals faiss's: iterations, centroids within ATOL, assignments but for
    near ties. Returns faiss's iteration statistics."""
    expected, stats = faiss_kmeans(x, k, n_iter, seed)
    centroids, iterations = spherical_kmeans(torch.from_numpy(x).to(dtype), k, n_iter, seed)
    assert centroids.dtype == dtype
    assert iterations == len(stats)
    centroids = centroids.to(torch.float64).numpy()
    np.testing.assert_allclose(centroids, expected, rtol=0, atol=ATOL)
    products = x.astype(np.float64) @ expected.T.astype(np.float64)
    ranked = np.sort(products, axis=1)
    near = ranked[:, -1] - ranked[:, -2] < NEAR_TIE
    differ = np.argmax(products, axis=1) != np.argmax(x @ centroids.T.astype(np.float32), axis=1)
    assert not (differ & ~near).any(), f"{(differ & ~near).sum()} assignments differ, no near tie"
    assert differ.sum() == 0  # on these inputs: not one, near ties included
    return stats


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize(("n", "d", "k"), SHAPES)
@pytest.mark.parametrize("seed", [0, 1])
def test_torch_kmeans_gives_faiss_centroids_on_random_points(n, d, k, seed, dtype):
    assert_same_kmeans(unit_points(n, d, seed), k, 100, seed, dtype)


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize(("n", "d", "k", "pool"), [(400, 16, 8, 40), (2000, 64, 20, 60)])
def test_torch_kmeans_splits_empty_clusters_and_breaks_ties_as_faiss(n, d, k, pool, dtype):
    """Repeated points: two initial centroids on one point tie exactly for every point,
    the one faiss's tie rule passes over ends empty and is split off a donor drawn by
    faiss's generator, and perturbed by faiss's EPS."""
    for seed in (0, 2):
        stats = assert_same_kmeans(repeated_patterns(n, d, pool, seed), k, 50, seed, dtype)
        assert sum(s["nsplit"] for s in stats) > 0  # the inputs do force empty clusters


@pytest.mark.parametrize(("n", "d"), [(200, 64), (100, 2048)])
def test_the_tie_order_is_the_one_faiss_search_applies(n, d):
    """Integer points and centroids: exact products with many equal maxima. faiss's top-1
    search picks, in every row, the first of the tied centroids in ``tie_order``."""
    rng = np.random.default_rng(0)
    k = 37  # beyond a multiple of the SIMD width: a scalar tail after the lanes
    x = rng.integers(0, 2, (n, d)).astype(np.float32)
    centroids = rng.integers(0, 2, (k, d)).astype(np.float32)
    centroids[5:30:3] = centroids[4]  # whole groups of equal centroids
    index = faiss.IndexFlatIP(d)
    index.add(centroids)
    _, labels = index.search(x, 1)
    order = np.array(tie_order(k, d, n))
    products = x @ centroids.T
    assert (products == products.max(axis=1, keepdims=True)).sum(axis=1).max() > 1
    np.testing.assert_array_equal(labels[:, 0], order[np.argmax(products[:, order], axis=1)])
    assert sorted(order) == list(range(k))


def test_as_many_points_as_clusters_are_the_centroids_as_faiss_copies_them():
    x = unit_points(8, 16, 3)
    centroids, iterations = spherical_kmeans(torch.from_numpy(x), 8, 10, 0)
    np.testing.assert_array_equal(centroids.numpy(), faiss_kmeans(x, 8, 10, 0)[0])
    assert iterations == 0


@pytest.mark.parametrize("centres", vlad.CENTRES)
def test_off_the_cpu_the_vocabulary_k_means_is_torchs_and_gives_faiss_centres(monkeypatch, centres):
    """A non-CPU device (played here by the CPU) takes the torch path: the same centres
    as faiss's, within ATOL ("mean": float64 means of the same members)."""
    x = unit_points(2500, 64, 5) * 3.0  # not unit: normalised first on both paths
    expected = fit_spherical_kmeans(x, 16, 50, 5, centres=centres, device="cpu")
    calls = []
    monkeypatch.setattr(vlad, "on_cpu", lambda device: False)
    original = kmeans.fit_on_device
    monkeypatch.setattr(
        kmeans, "fit_on_device", lambda *args: calls.append(args) or original(*args)
    )
    actual = fit_spherical_kmeans(x, 16, 50, 5, centres=centres, device="cpu")
    assert len(calls) == 1
    assert actual.dtype == np.float32 and actual.shape == expected.shape
    np.testing.assert_allclose(actual, expected, rtol=0, atol=ATOL)


def test_on_the_cpu_the_vocabulary_k_means_is_faiss_itself(monkeypatch):
    def refuse(*args):
        raise AssertionError("the torch k-means ran on the CPU")

    monkeypatch.setattr(kmeans, "fit_on_device", refuse)
    x = unit_points(2000, 16, 1)
    unit = vlad.l2_normalize(spherical_centroids(vlad.l2_normalize(x), 8, 30, 1)[0])
    np.testing.assert_array_equal(fit_spherical_kmeans(x, 8, 30, 1, "unit", device="cpu"), unit)


def test_kmeans_refuses_non_finite_points_on_either_path(monkeypatch):
    x = unit_points(100, 8, 0)
    x[3, 2] = np.nan
    with pytest.raises(RuntimeError, match="NaN"):  # faiss's own check
        fit_spherical_kmeans(x, 4, 10, 0)
    monkeypatch.setattr(vlad, "on_cpu", lambda device: False)
    with pytest.raises(ValueError, match="NaN or infinite"):
        fit_spherical_kmeans(x, 4, 10, 0)


# ------------------------------------------------------------------ the vocabulary stage


def test_the_vocabulary_stage_fits_with_faiss_on_the_cpu_whatever_names_it(tmp_path, monkeypatch):
    """``device: cpu`` and ``auto`` on a machine without a GPU store the same centres,
    from faiss (the torch k-means is refused)."""
    if not vlad.on_cpu("auto"):
        pytest.skip("auto finds an accelerator here")
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
        run_job(replace(job, run={"device": device}))
        return path

    def refuse(*args):
        raise AssertionError("the torch k-means ran on the CPU")

    monkeypatch.setattr(kmeans, "fit_on_device", refuse)
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
