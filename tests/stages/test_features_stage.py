"""The features stage (vprflow.stages.features): sharded features equal to the backbone's,
the same bits in any batch size, and its batches sized from memory."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from synthetic import make_dataset
from toy_pipeline import N_PLACES, SCHEMA, small_plan, stage_path
from workflow_helpers import toy_config

from vprflow.core import stores
from vprflow.core.errors import DatasetError
from vprflow.data.images import read_image, resize_image
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.dataset import build_images
from vprflow.stages.features import compute_features
from vprflow.stages.jobs import Job, built_shard_ranges
from vprflow.stages.readers import Dataset, read_features


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
