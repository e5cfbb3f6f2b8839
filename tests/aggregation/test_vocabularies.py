"""Published vocabularies by name: the schema lists them, the key holds the name and the
pinned hash, the fetch keeps only the pinned file, the stage reads it and refuses
another, and through Snakemake a wrong file fails the run leaving nothing behind."""

from __future__ import annotations

import copy
import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from synthetic import make_dataset
from workflow_helpers import snakemake, toy_config, write_config

from vprflow.aggregation.vocabularies import (
    PATH,
    PUBLISHED,
    URL_ENV,
    fetch_vocabulary,
    vocabulary_url,
)
from vprflow.core import stores
from vprflow.core.errors import ConfigError
from vprflow.core.paths import PUBLISHED_VOCABULARY
from vprflow.data.download import DownloadError
from vprflow.planning.config import load_schema, validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.jobs import Job
from vprflow.stages.readers import read_centres
from vprflow.stages.vocabulary import fit_vocabulary

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def test_the_schema_admits_exactly_the_published_names():
    vocabulary = load_schema(SCHEMA)["definitions"]["vocabulary"]["properties"]
    assert vocabulary["name"]["enum"] == list(PUBLISHED)
    assert "published" in vocabulary["source"]["enum"]
    assert {"urban", "indoor", "aerial", "urbanNVFinetuned"} <= set(PUBLISHED)


def vocabulary_stage(config: dict, dataset: str = "corridor", method: str = "anyloc_vlad"):
    plan = build_plan(validate_config(config, SCHEMA))
    run = next(r for r in plan.runs[dataset] if r.method == method)
    stage, key = "recall", run.recall_key
    while stage != "vocabulary":
        inputs = plan.get(stage, key).inputs
        stage, key = inputs["vocabulary"] if "vocabulary" in inputs else inputs["descriptors"]
    return plan.get("vocabulary", key)


def test_a_published_vocabulary_is_keyed_by_its_name_and_pinned_hash_alone(tmp_path):
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["data_root"] = str(tmp_path)
    config["vocabulary"] = {"source": "published", "name": "urban"}
    # roadscene runs anyloc_vlad_thermal, whose `fit_on` a published vocabulary ignores.
    del config["datasets"]["roadscene"]
    urban = vocabulary_stage(config)
    assert urban.record["params"] == {
        "source": "published",
        "name": "urban",
        "sha256": PUBLISHED["urban"].sha256,
    }
    assert urban.input_paths()["centres"] == PUBLISHED_VOCABULARY.format(name="urban")
    other = copy.deepcopy(config)
    other["vocabulary"]["n_clusters"] = 7  # a published vocabulary does not read it: refused
    with pytest.raises(ConfigError, match="n_clusters"):
        vocabulary_stage(other)
    del other["vocabulary"]["n_clusters"]
    other["vocabulary"]["name"] = "indoor"
    assert vocabulary_stage(other).key != urban.key


def test_the_url_follows_a_mirror_when_one_is_set(monkeypatch):
    monkeypatch.delenv(URL_ENV, raising=False)
    assert vocabulary_url("urban").startswith("https://raw.githubusercontent.com/AnyLoc/")
    monkeypatch.setenv(URL_ENV, "file:///mirror/")
    assert vocabulary_url("urban") == "file:///mirror/" + PATH.format(name="urban")


def tiny_centres(path: Path) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(torch.arange(12, dtype=torch.float32).reshape(4, 3) / 10, path)
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_fetch_keeps_the_file_only_when_its_hash_is_the_pinned_one(tmp_path):
    sha256 = tiny_centres(tmp_path / "mirror" / "c.pt")
    url = (tmp_path / "mirror" / "c.pt").as_uri()
    out = tmp_path / "got" / "c_centers.pt"
    with pytest.raises(DownloadError, match=f"expected sha256 {'0' * 64}, got {sha256}"):
        fetch_vocabulary(url, "0" * 64, out)
    assert not out.exists() and not list(out.parent.iterdir())
    fetch_vocabulary(url, sha256, out)
    assert hashlib.sha256(out.read_bytes()).hexdigest() == sha256


def features_store(path: Path, dim: int) -> str:
    with stores.atomic_store(path, {"stage": "features", "dim": dim}):
        pass
    return str(path)


def test_the_stage_reads_the_pinned_file_and_refuses_another(tmp_path):
    centres = tmp_path / "c_centers.pt"
    sha256 = tiny_centres(centres)
    features = features_store(tmp_path / "features.zarr", 3)
    record = {"params": {"source": "published", "name": "urban", "sha256": sha256}}
    inputs = {"features": features, "centres": str(centres)}
    fit_vocabulary(Job(record, inputs, str(tmp_path / "v.zarr")))
    expected = np.arange(12, dtype=np.float64).reshape(4, 3) / 10
    np.testing.assert_allclose(read_centres(str(tmp_path / "v.zarr")), expected, rtol=1e-7)
    record["params"]["sha256"] = "f" * 64  # a file put there by hand, not the published one
    with pytest.raises(ValueError, match="not the published"):
        fit_vocabulary(Job(record, inputs, str(tmp_path / "w.zarr")))
    record["params"]["sha256"] = sha256
    wider = features_store(tmp_path / "features4.zarr", 4)
    with pytest.raises(ValueError, match="3 dimensions but the features have 4"):
        fit_vocabulary(Job(record, {**inputs, "features": wider}, str(tmp_path / "x.zarr")))


@pytest.mark.workflow
def test_a_mirror_serving_another_file_fails_the_run_and_leaves_nothing(tmp_path, monkeypatch):
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    config = toy_config(tmp_path / "data", methods=["anyloc_vlad"])
    config["vocabulary"] = {"source": "published", "name": "indoor"}
    mirror = tmp_path / "mirror"
    tiny_centres(mirror / PATH.format(name="indoor"))
    monkeypatch.setenv(URL_ENV, mirror.as_uri())
    result = snakemake(
        tmp_path, write_config(tmp_path, config), "results/recall_toy.csv", check=False
    )
    assert result.returncode != 0
    log = (tmp_path / "logs" / "published_vocabulary" / "indoor.log").read_text()
    assert PUBLISHED["indoor"].sha256 in log and "checksum mismatch" in log
    assert not (tmp_path / PUBLISHED_VOCABULARY.format(name="indoor")).exists()
    assert not list((tmp_path / "results" / "cache" / "vocabulary").glob("*.zarr"))


def test_the_vlad_aggregators_vocabulary_is_fitted_on_channel_normalised_tokens(
    tmp_path, monkeypatch
):
    """SNSM's `--vlad` baseline (aggregator ``vlad``) fits its centres on the tokens it
    aggregates: each channel divided by its L2 norm over the image's tokens (+ 1e-10);
    AnyLoc-VLAD's vocabulary key and sample stay the stored patches."""
    import vprflow.stages.vocabulary as vocabulary_module

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["data_root"] = str(tmp_path)
    del config["datasets"]["roadscene"]
    config["methods"]["snsm_vlad"] = {"aggregator": "vlad"}
    config["datasets"]["corridor"]["methods"] = ["anyloc_vlad", "snsm_vlad"]
    snsm = vocabulary_stage(config, method="snsm_vlad").record["params"]
    anyloc = vocabulary_stage(config).record["params"]
    assert snsm == {**anyloc, "normalization": "channel"}
    assert "normalization" not in anyloc

    rng = np.random.default_rng(3)
    grids = rng.standard_normal((2, 2, 3, 4)) * rng.uniform(0.5, 9.0, (2, 1, 1, 4))
    path = str(tmp_path / "features.zarr")
    with stores.atomic_store(path, {"stage": "features", "grid": [2, 3], "dim": 4}) as group:
        stores.write_array(group, "features", grids.astype(np.float32))

    class TwoReferences:
        def __init__(self, _path):
            pass

        def indices(self, _side):
            return [0, 1]

    seen = []
    monkeypatch.setattr(vocabulary_module, "Dataset", TwoReferences)
    monkeypatch.setattr(
        vocabulary_module, "fit_spherical_kmeans", lambda x, k, *a, **o: seen.append(x) or x[:k]
    )
    for params in (snsm, anyloc):
        record = {"params": {**params, "n_clusters": 2, "max_descriptors": 12}}
        inputs = {"images": "unused", "features": path}
        fit_vocabulary(Job(record, inputs, str(tmp_path / f"v{len(seen)}.zarr")))
    flat = grids.reshape(2, 6, 4).astype(np.float64)
    channel = flat / (np.sqrt((flat**2).sum(axis=1, keepdims=True)) + 1e-10)
    np.testing.assert_allclose(seen[0], channel.reshape(12, 4), rtol=1e-6)
    np.testing.assert_allclose(seen[1], flat.reshape(12, 4), rtol=1e-6)
