"""The ``pca`` rule: PCA fitted on a sample of the references' segment descriptors."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from vprflow.aggregation import pca
from vprflow.aggregation.aggregators import aggregator
from vprflow.core import stores
from vprflow.stages.base import Job
from vprflow.stages.image_descriptors import image_descriptor
from vprflow.stages.readers import Dataset, segment_offsets


def fit_pca(job: Job) -> None:
    """PCA fitted on a random sample of the reference images' segment descriptors,
    computed by the method's aggregator with the options ``fit_on`` (SegVLAD: at
    ``pca.fit_order``, docs/methods.md §5)."""

    inputs, record, params = job.inputs, job.record, job.params
    dataset = Dataset(inputs["images"])
    describe = image_descriptor(aggregator(params["aggregator"]), params["fit_on"], inputs)
    segments_path = inputs["segments"]
    offsets = segment_offsets(stores.open_store(segments_path))
    total = int(offsets[dataset.n_reference])
    rng = np.random.default_rng(params["seed"])
    chosen = np.sort(rng.choice(total, size=min(total, params["max_samples"]), replace=False))
    # Filled in place: for DINOv2-G this is 50,000 x 49,152 floats (10 GB), one copy only.
    sample = None
    filled = 0
    # One BLAS thread, as the descriptors stage computes them: the same vectors, bit
    # for bit, whatever the rule's thread count.
    with threadpool_limits(limits=1):
        for i in tqdm(range(dataset.n_reference), desc="pca sample", unit="image"):
            rows = chosen[(chosen >= offsets[i]) & (chosen < offsets[i + 1])] - offsets[i]
            if len(rows):
                vectors = describe(i)
                if sample is None:
                    sample = np.empty((len(chosen), vectors.shape[1]), dtype=np.float32)
                sample[filled : filled + len(rows)] = vectors[rows]
                filled += len(rows)
    if sample is None:
        raise ValueError(f"{segments_path}: the reference images have no segments to fit PCA on")
    fitted = pca.fit_pca(
        sample, params["dim"], params["whiten"], params["seed"], solver=params["solver"]
    )
    with stores.atomic_store(job.out, {"stage": "pca", "record": record}) as group:
        # `dim` is the effective dimension: capped at the sample's numerical rank.
        stores.set_attrs(
            group,
            whiten=fitted.whiten,
            n_samples=len(chosen),
            dim=fitted.dim,
            requested_dim=params["dim"],
        )
        stores.write_array(group, "mean", fitted.mean)
        stores.write_array(group, "components", fitted.components)
        stores.write_array(group, "explained_variance", fitted.explained_variance)
