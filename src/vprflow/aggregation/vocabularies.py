"""The VLAD vocabularies the SegVLAD authors publish, by name (docs/methods.md §3).

AnyLoc/Revisit-Anything ships cluster centres in its repository, under
``cache/vocabulary/dinov2_vitg14/l31_value_c32/<name>/c_centers.pt``: 32 centres of
DINOv2 ViT-G/14 layer 31 value features (1536-d) per dataset (its "map" vocabularies)
and per domain (``urban``, ``indoor``, ``aerial``), and 768-d ones for the fine-tuned
DINOv2-B/14 (``<name>NVFinetuned``). ``vocabulary: {source: published, name: urban}``
fetches one at the pinned commit, checks its SHA-256 and loads it with
``torch.load(weights_only=True)``. Names are the authors' own.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from vprflow.core.files import atomic_path
from vprflow.data.download import fetch, verify_sha256

COMMIT = "89cade5529a590c4ed2999b396dcd3cab86e275b"
# An offline mirror of the repository's raw files may stand in (tests, clusters).
URL_ENV = "VPRFLOW_VOCABULARY_URL"
BASE_URL = f"https://raw.githubusercontent.com/AnyLoc/Revisit-Anything/{COMMIT}"
PATH = "cache/vocabulary/dinov2_vitg14/l31_value_c32/{name}/c_centers.pt"


@dataclass(frozen=True)
class PublishedVocabulary:
    sha256: str
    dim: int  # 1536: DINOv2 ViT-G/14 layer 31 value; 768: the fine-tuned DINOv2-B/14


# Read from the repository at COMMIT (git blobs; none is a Git LFS pointer).
_VITG14 = {  # 1536-d: DINOv2 ViT-G/14 layer 31 value
    "urban": "a684e571f05c85c804e7301547d8620c28ae759e824adb9ac88294b080feaba0",
    "indoor": "05731213c402a27ddb5cd7a03fd942de4b884a3f4fc63a1bf49d1fbe9a2aff35",
    "aerial": "432b55a35d3662117ea78196e9740b7ab692ebed399961a1019856451bc2ac79",
    "17places": "c73105310d9e293d7d8b7c30800f8f0c4c610d77bc51cecb758e2a7f3d36cffa",
    "AmsterTime": "66d3175a3f92c350db765ec1c502bce689320586d1631de483772dcb904a7646",
    "InsideOut": "9762b2642cdc392fb83fefc2c6da16ea18363d3928408f1c2d4bd86f641fd529",
    "ROxford5k": "0e509861c4ba1af3a80da7ceef23361a5a57f636e5d4b54ccf37debc59600c1e",
    "RParis6k": "a885555309596773af0eaf6881947666c906f703cbf3fd731975dd898a96d81f",
    "SFXL": "841a2a095d5f0c4425427a14971641be4752b514493a898b7a37d016fbb3e3dd",
    "VPAir": "bec5863c7d999d0c1e73d0f8d49d1e0ebda231ac07998421ba2e784220a3b012",
    "baidu": "b506faa493eafcae28fce0ed93b8b0c9a7688cd066fb58ff5b0892a5098147ae",
    "habitat": "2500bd789e2531290cfb354721c70207e154e451d702ee4c52cdd17be3905ce7",
    "hawkins": "2a19c2ce69c01bb924f2d9eee0e7692288fb0c6e6f23c579163bbeefe2d87217",
    "laurel_caverns": "5f4d855c881f2e8fc0c5f43ddec2383bd7bb5724078115dc5f1f3b99a55cd0f4",
    "mslsCPH": "f6fb077963646855ed7a5ab269427056070dba31beb179abf6de9d597b9a29e3",
    "mslsSF": "c3f07b2af53b0c4cbe36f0e53d49a8288ba4384e930dc5f2f57169e48ffdae0d",
    "pitts": "aa85481cce1c792d4826086010e3e15e2d035defa7954995b328d296137b88f6",
    "torWIC": "bad5c70b2a17f003ddc2873123bfacacee85c82dd9e46e629457f070a9c013ec",
}
_FINETUNED = {  # 768-d: the fine-tuned DINOv2-B/14, named <name>NVFinetuned
    "17places": "da7e0ff84dda901d850867cec33977ba22ab3aee23dc7af4b2ebfbddca0fb914",
    "AmsterTime": "03aa1e8924793dc3c8405bf13e58f99cd88f999fed4d19e4e5dcd56c1bd5e88b",
    "InsideOut": "fb5d405e2929324aeaaa4cf06b71947b54c63f4a8591c3c3c1d36f209789c5f5",
    "ROxford5k": "4c3a1fa19151abf48d2a6ead4a41e1914366c66a78a7eea52d2b0350c89b2567",
    "RParis6k": "215b9e42fa5ccb45b931779f1b9932558976952ea193f0e382e83036d88256bd",
    "SFXL": "60f69a11f0827bc9b5c624df6e39d661ddbe40ade05b995a8bf2e62abf5e6f62",
    "VPAir": "5f2ba15e2abd48c80899e9bee6a6b4ef14854f9a22c4d6fe642e5a735ae35d63",
    "aerial": "e9ed50fc40f292328411fa8c392020b6a6abae9aa95e58e284fca38af3e1d3d8",
    "baidu": "f78e269194cc3af48e5dcae998ee8db53159af48ad1dbc3c8d66db918883e9be",
    "indoor": "1e024bdb804e74b08974a48f53d32e4cf7217c5fc8f8659d99421956e6f5f56e",
    "mslsCPH": "fd7ca443c1bde73feaffc62195b95cda11216bf7d3e6bc3032462915e068ca95",
    "mslsSF": "1f16d69f967580f392ba09c23e2fee7ccc892702db060c1a277a79a8d6b24621",
    "pitts": "6d079b2549b979a320125a9c828e1f1923f99df0719ede3942df4105b1f8da07",
    "urban": "c540aa5a14e9115137c0a8b0cf529ab11b852eaa5b2af7ca73334e44cdbb6b57",
}
PUBLISHED: dict[str, PublishedVocabulary] = {
    **{name: PublishedVocabulary(sha, 1536) for name, sha in _VITG14.items()},
    **{f"{name}NVFinetuned": PublishedVocabulary(sha, 768) for name, sha in _FINETUNED.items()},
}


def vocabulary_url(name: str) -> str:
    """Where the published vocabulary ``name`` is fetched from (``$VPRFLOW_VOCABULARY_URL``
    in place of the pinned repository when set: a mirror of its raw files)."""
    base = os.environ.get(URL_ENV, BASE_URL).rstrip("/")
    return f"{base}/{PATH.format(name=name)}"


def fetch_vocabulary(url: str, sha256: str, out: str | Path) -> None:
    """Fetch ``url`` to ``out`` if its SHA-256 is ``sha256``; otherwise fail naming both
    hashes and leave nothing at ``out`` (the file is renamed into place when checked)."""

    # A temporary of this writer's own: two runs fetching one vocabulary (--nolock) used
    # to share `<out>.tmp`, and the second's rename found it gone.
    with atomic_path(out) as partial:
        verify_sha256(url, sha256, fetch(url, partial))
