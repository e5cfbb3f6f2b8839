"""The dataset stage (vprflow.stages.dataset): the image list and truth it stores, and the
images it refuses."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import make_dataset
from toy_pipeline import N_PLACES, SCHEMA, small_plan, stage_path
from workflow_helpers import toy_config

from vprflow.core.errors import DatasetError
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.dataset import build_images
from vprflow.stages.jobs import Job
from vprflow.stages.readers import Dataset


def test_dataset_lists_images_and_truth(pipeline):
    dataset = Dataset(stage_path(pipeline, "dataset"))
    assert (dataset.n_reference, dataset.n_query) == (N_PLACES, N_PLACES)
    assert [list(t) for t in dataset.truth()][:2] == [[0, 1], [0, 1, 2]]
    assert dataset.paths[0] == "toy/ref/0000.png"


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
