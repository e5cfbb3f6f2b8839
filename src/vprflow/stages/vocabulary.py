"""The ``vocabulary`` rule: VLAD centres fitted on a dataset's patches, or read from a file."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from vprflow.aggregation.snsm import normalize_tokens
from vprflow.aggregation.vlad import fit_spherical_kmeans
from vprflow.core import stores
from vprflow.data.published import load_c_centers
from vprflow.planning.fingerprints import file_digest
from vprflow.stages.base import Job, resolved_sources
from vprflow.stages.readers import Dataset, read_features


def load_centres_file(path: str) -> np.ndarray:
    """Centres ``[K, D]`` from a torch-saved ``c_centers.pt`` or a ``.npy`` file
    (plain numbers only: a pickled object array is refused, naming the file)."""
    if path.endswith(".npy"):
        try:
            centres = np.load(path, allow_pickle=False)
        except ValueError as error:
            raise ValueError(
                f"vocabulary.file {path}: cannot load it without unpickling ({error}); save "
                "the centres as a plain float array: np.save(path, centres.astype('float32'))"
            ) from error
        if centres.ndim != 2 or centres.dtype.kind not in "fiu":
            raise ValueError(
                f"vocabulary.file {path}: expected numeric centres [K, D], found "
                f"{centres.dtype} {centres.shape}"
            )
        return centres.astype(np.float32)

    return load_c_centers(path)


def fit_vocabulary(job: Job) -> None:
    """VLAD centres ``[K, D]``: spherical k-means on sampled patch descriptors, a file, or
    a published vocabulary (the ``centres`` input, fetched by its rule)."""

    record, params = job.record, job.params
    features_path = job.inputs["features"]
    if params["source"] in ("file", "published"):
        if params["source"] == "published":
            path, what = job.inputs["centres"], f"published vocabulary {params['name']!r}"
            # The file may have been put there by hand: it must be the pinned one.
            actual = file_digest(path)
            if actual != params["sha256"]:
                raise ValueError(
                    f"{what}: {path} has sha256 {actual}, not the published {params['sha256']}; "
                    "delete it and run again to fetch it"
                )
            centres = load_centres_file(path)
        else:
            centres, what = load_centres_file(params["file"]), f"vocabulary.file {params['file']}"
        dim = int(stores.open_store(features_path).attrs["dim"])
        if centres.shape[1] != dim:
            raise ValueError(
                f"{what}: centres have {centres.shape[1]} dimensions but the features have "
                f"{dim}; the vocabulary belongs to another backbone or layer"
            )
    else:
        dataset = Dataset(job.inputs["images"])
        features = stores.open_store(features_path)
        images = dataset.indices(params["fit_on"])
        h, w = features.attrs["grid"]
        per_image = h * w
        total = len(images) * per_image
        rng = np.random.default_rng(params["seed"])
        chosen = np.sort(
            rng.choice(total, size=min(total, params["max_descriptors"]), replace=False)
        )
        owner = chosen // per_image
        # An aggregator that normalises each image's tokens first (the plan's
        # `normalization`) has its vocabulary fitted on the tokens so normalised.
        normalization = params.get("normalization")
        sample = []
        for i in tqdm(np.unique(owner), desc="vocabulary sample", unit="image"):
            grid = read_features(features, images[i]).reshape(per_image, -1)
            if normalization is not None:
                grid = normalize_tokens(grid, normalization)
            sample.append(grid[chosen[owner == i] % per_image])
        sample = np.concatenate(sample)
        if len(sample) < params["n_clusters"]:
            raise ValueError(
                f"config key vocabulary.n_clusters = {params['n_clusters']} is more than the "
                f"{len(sample)} patch descriptors of the {params['fit_on']} images "
                f"({len(images)} images x {per_image} patches, max_descriptors "
                f"{params['max_descriptors']}): lower n_clusters"
            )
        centres = fit_spherical_kmeans(
            sample,
            params["n_clusters"],
            params["n_iter"],
            params["seed"],
            centres=params["centres"],
            # The device only where the plan gives the stage one (a model's features, as
            # a cluster's GPU request): elsewhere the products run in numpy, the same
            # centres, and the job never imports torch (~1.2 s) to resolve `auto`.
            device=job.device if job.run.get("uses_gpu") else "cpu",
        )
    attrs = {"stage": "vocabulary", "record": record, "sources": resolved_sources(params)}
    with stores.atomic_store(job.out, attrs) as group:
        stores.write_array(group, "centres", centres.astype(np.float32))
