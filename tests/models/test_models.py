"""Model-source resolution, weight fingerprints and device / dtype choice."""

from __future__ import annotations

import shutil

import pytest
import torch
from tiny_models import save_tiny_dino

from vprflow.core.devices import batch_for_memory, resolve_device, resolve_dtype
from vprflow.models.hub import ModelNotFoundError, resolve_model_source, weights_fingerprint
from vprflow.models.vit import load_vit

MISSING_ID = "vprflow-tests/no-such-model"


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    # transformers' own (seeded) initialisation: only the weight bytes matter here
    return save_tiny_dino(
        tmp_path_factory.mktemp("tiny"),
        hidden_size=16,
        num_layers=1,
        image_size=16,
        seed=0,
        scale=None,
    )


@pytest.fixture
def offline(monkeypatch):
    # Set after huggingface_hub was imported: the resolver must still notice it.
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")


def _assert_names_both_remedies(message: str, model: str) -> None:
    assert repr(model) in message
    assert "--local-dir DIR" in message and "huggingface-cli download" in message
    assert "config key `model`" in message
    assert "config.json" in message


def test_local_directory_resolves_to_itself(tiny_dir):
    assert resolve_model_source(str(tiny_dir), None) == str(tiny_dir.resolve())


def test_missing_local_directory_names_model_and_remedies(tmp_path):
    missing = str(tmp_path / "nowhere" / "dinov2")
    with pytest.raises(ModelNotFoundError) as info:
        resolve_model_source(missing, None)
    _assert_names_both_remedies(str(info.value), missing)
    assert "does not exist" in str(info.value)


def test_directory_without_weights_is_rejected(tiny_dir, tmp_path):
    shutil.copy(tiny_dir / "config.json", tmp_path / "config.json")
    with pytest.raises(ModelNotFoundError, match=r"no \*\.safetensors or \*\.bin"):
        resolve_model_source(str(tmp_path), None)
    (tmp_path / "config.json").unlink()
    shutil.copy(tiny_dir / "model.safetensors", tmp_path / "model.safetensors")
    with pytest.raises(ModelNotFoundError, match="no config.json"):
        resolve_model_source(str(tmp_path), None)


def test_unknown_hub_id_offline_names_model_and_remedies(tmp_path, offline):
    with pytest.raises(ModelNotFoundError) as info:
        resolve_model_source(MISSING_ID, str(tmp_path))
    message = str(info.value)
    _assert_names_both_remedies(message, MISSING_ID)
    assert f"huggingface-cli download {MISSING_ID} --local-dir DIR" in message
    assert "not in the cache, and HF_HUB_OFFLINE is set" in message
    assert str(tmp_path) in message  # says which cache it looked in


def test_load_vit_reports_missing_model(tmp_path, offline):
    params = {"backbone": "dino", "model": MISSING_ID, "cache_dir": str(tmp_path)}
    with pytest.raises(ModelNotFoundError, match=MISSING_ID):
        load_vit(params, "cpu")


def test_hub_id_found_in_cache_dir_offline(tiny_dir, tmp_path, offline):
    # The Hugging Face cache layout: models--owner--name/{refs/main, snapshots/<commit>/}.
    commit = "0123456789abcdef0123456789abcdef01234567"
    repo = tmp_path / "models--vprflow-tests--tiny"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)
    shutil.copytree(tiny_dir, repo / "snapshots" / commit)
    source = resolve_model_source("vprflow-tests/tiny", str(tmp_path))
    assert source.endswith(commit)
    params = {"backbone": "dino", "model": "vprflow-tests/tiny", "cache_dir": str(tmp_path)}
    backbone = load_vit(params, "cpu")
    assert backbone.features(torch.rand(1, 16, 24, 3).numpy()).shape == (1, 2, 3, 16)


def test_weights_fingerprint_tracks_weight_bytes(tiny_dir, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(tiny_dir, copy)
    original = weights_fingerprint(str(tiny_dir))
    assert original.startswith("sha256:") and len(original) == len("sha256:") + 64
    assert weights_fingerprint(str(copy)) == original  # content, not location
    weights = copy / "model.safetensors"
    data = bytearray(weights.read_bytes())
    data[-1] ^= 0xFF
    weights.write_bytes(bytes(data))
    assert weights_fingerprint(str(copy)) != original
    shutil.copy(tiny_dir / "model.safetensors", weights)
    assert weights_fingerprint(str(copy)) == original
    (copy / "extra.bin").write_bytes(b"\0")
    assert weights_fingerprint(str(copy)) != original


def test_weights_fingerprint_of_hub_id_and_missing_dir(tmp_path):
    assert weights_fingerprint("facebook/dinov2-giant") == "hf:facebook/dinov2-giant"
    with pytest.raises(ModelNotFoundError):
        weights_fingerprint(str(tmp_path / "absent"))


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type in {"cpu", "cuda", "mps"}
    with pytest.raises(ValueError, match="unknown device"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA is not available"):
            resolve_device("cuda")
        with pytest.raises(RuntimeError, match="CUDA is not available"):
            resolve_device("cuda:1")


def test_an_auto_batch_fills_a_share_of_the_free_memory_within_its_bounds():
    gib = 2**30
    assert batch_for_memory(10 * gib, gib) == 8  # 80% of 10 GiB
    assert batch_for_memory(10 * gib, 3 * gib) == 2
    assert batch_for_memory(gib, 2 * gib) == 1  # too little for one: still one
    assert batch_for_memory(1000 * gib, gib) == 64
    assert batch_for_memory(1000 * gib, gib, cap=16) == 16


def test_resolve_dtype():
    cpu = torch.device("cpu")
    assert resolve_dtype("float32", cpu) == torch.float32
    assert resolve_dtype("bfloat16", "cpu") == torch.bfloat16
    with pytest.raises(ValueError, match="float16"):
        resolve_dtype("float16", cpu)
    with pytest.raises(ValueError, match="unknown dtype"):
        resolve_dtype("int8", cpu)
    assert resolve_dtype("float16", torch.device("cuda")) == torch.float16


@pytest.mark.parametrize("damage", ["random", "truncated"])
def test_corrupt_safetensors_names_the_directory_and_the_remedy(tiny_dir, tmp_path, damage):
    from vprflow.models.hub import ModelLoadError

    broken = tmp_path / "broken"
    shutil.copytree(tiny_dir, broken)
    weights = broken / "model.safetensors"
    data = weights.read_bytes()
    weights.write_bytes(
        torch.randint(0, 256, (len(data),), dtype=torch.uint8).numpy().tobytes()
        if damage == "random"
        else data[: len(data) // 2]
    )
    with pytest.raises(ModelLoadError) as error:
        load_vit({"backbone": "dino", "model": str(broken)}, "cpu")
    text = str(error.value)
    assert str(broken) in text and "huggingface-cli download" in text


def test_a_pickled_bin_checkpoint_is_refused_with_the_remedy(tiny_dir, tmp_path):
    from vprflow.models.hub import ModelLoadError

    class Payload:
        def __reduce__(self):
            return (print, ("executed",))

    pickled = tmp_path / "pickled"
    pickled.mkdir()
    shutil.copy(tiny_dir / "config.json", pickled / "config.json")
    torch.save({"weights": Payload()}, pickled / "pytorch_model.bin")
    with pytest.raises(ModelLoadError, match=r"pickled.*refused"):
        load_vit({"backbone": "dino", "model": str(pickled)}, "cpu")
