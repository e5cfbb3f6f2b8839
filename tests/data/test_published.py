"""Reading the authors' HDF5 features / masks and torch-saved cluster centres."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from vprflow.data.published import (
    PublishedDataError,
    load_c_centers,
    read_features_h5,
    read_masks_h5,
)


class NotATensor:
    """A picklable object that ``weights_only`` loading must refuse."""

    def __init__(self):
        self.value = 1


@pytest.fixture
def published_h5(tmp_path):
    rng = np.random.default_rng(0)
    features = {
        "0001.jpg": rng.standard_normal((1, 6, 3, 4)).astype(np.float32),
        "0002.jpg": rng.standard_normal((1, 6, 3, 4)).astype(np.float32),
    }
    # 12 masks so that numeric order ("10" after "9") differs from string order.
    masks = rng.random((12, 24, 32)) > 0.5
    path = tmp_path / "features.h5"
    with h5py.File(path, "w") as handle:
        for name, array in features.items():
            handle.create_dataset(f"{name}/ift_dino", data=array)
        for j, mask in enumerate(masks):
            handle.create_dataset(f"0001.jpg/masks/{j}/segmentation", data=mask)
            handle.create_dataset(f"0001.jpg/masks/{j}/area", data=int(mask.sum()))
    return path, features, masks


def test_features_round_trip(published_h5):
    path, features, _ = published_h5
    read = read_features_h5(path, "0002.jpg")
    assert read.shape == (3, 4, 6) and read.dtype == np.float32
    # [1, D, h, w] -> [h, w, D]: element (i, j, d) is the source's (0, d, i, j).
    assert read[2, 1, 5] == features["0002.jpg"][0, 5, 2, 1]
    np.testing.assert_array_equal(read, features["0002.jpg"][0].transpose(1, 2, 0))


def test_masks_round_trip_in_numeric_order(published_h5):
    path, _, masks = published_h5
    read = read_masks_h5(path, "0001.jpg")
    assert read.dtype == bool and read.shape == (12, 24, 32)
    np.testing.assert_array_equal(read, masks)


def test_missing_entries_name_file_and_key(published_h5, tmp_path):
    path, _, _ = published_h5
    with pytest.raises(PublishedDataError, match=r"features\.h5.*'9999\.jpg'"):
        read_features_h5(path, "9999.jpg")
    with pytest.raises(PublishedDataError, match=r"features\.h5.*0002\.jpg/masks"):
        read_masks_h5(path, "0002.jpg")
    with pytest.raises(FileNotFoundError, match="absent.h5"):
        read_features_h5(tmp_path / "absent.h5", "0001.jpg")
    with h5py.File(path, "a") as handle:
        del handle["0001.jpg/masks/3/segmentation"]
        handle.create_dataset("0003.jpg/ift_dino", data=np.zeros((6, 3, 4), np.float32))
    with pytest.raises(PublishedDataError, match="0001.jpg/masks/3/segmentation"):
        read_masks_h5(path, "0001.jpg")
    with pytest.raises(PublishedDataError, match=r"expected \[1, D, h, w\]"):
        read_features_h5(path, "0003.jpg")


def test_c_centers_tensor_and_dict(tmp_path):
    centres = torch.randn(32, 24, dtype=torch.float64)
    torch.save(centres, tmp_path / "c_centers.pt")
    loaded = load_c_centers(tmp_path / "c_centers.pt")
    assert loaded.dtype == np.float32 and loaded.shape == (32, 24)
    np.testing.assert_allclose(loaded, centres.numpy(), rtol=1e-6)

    torch.save({"c_centers": centres, "note": "x"}, tmp_path / "dict.pt")
    np.testing.assert_allclose(load_c_centers(tmp_path / "dict.pt"), centres.numpy(), rtol=1e-6)


def test_c_centers_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.pt"):
        load_c_centers(tmp_path / "absent.pt")
    torch.save({"a": torch.zeros(2, 3), "b": torch.zeros(2, 3)}, tmp_path / "two.pt")
    with pytest.raises(PublishedDataError, match=r"two\.pt.*\['a', 'b'\]"):
        load_c_centers(tmp_path / "two.pt")
    torch.save(torch.zeros(4), tmp_path / "flat.pt")
    with pytest.raises(PublishedDataError, match=r"flat\.pt.*\[K, D\]"):
        load_c_centers(tmp_path / "flat.pt")
    torch.save(NotATensor(), tmp_path / "pickle.pt")
    with pytest.raises(PublishedDataError, match=r"pickle\.pt.*weights_only"):
        load_c_centers(tmp_path / "pickle.pt")


def test_pickled_npy_vocabulary_is_refused_naming_the_file(tmp_path):
    from vprflow.stages.vocabulary import load_centres_file

    table = np.empty(2, dtype=object)
    table[0], table[1] = [1.0, 2.0], [3.0, 4.0]
    np.save(tmp_path / "centres.npy", table, allow_pickle=True)
    with pytest.raises(ValueError, match=r"vocabulary.file .*centres\.npy.*np\.save"):
        load_centres_file(str(tmp_path / "centres.npy"))
    np.save(tmp_path / "flat.npy", np.arange(6.0))
    with pytest.raises(ValueError, match=r"flat\.npy: expected numeric centres \[K, D\]"):
        load_centres_file(str(tmp_path / "flat.npy"))
    np.save(tmp_path / "ok.npy", np.ones((3, 4)))
    assert load_centres_file(str(tmp_path / "ok.npy")).dtype == np.float32
