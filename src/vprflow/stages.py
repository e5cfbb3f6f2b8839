"""The workflow's stages as plain functions: inputs are store paths, output is a store.

Each function is what one Snakemake rule runs (``workflow/scripts/<stage>.py`` only
unpacks ``snakemake`` and calls it). ``params`` is the stage's hashed record from
:mod:`vprflow.plan` (``params["params"]`` holds the stage's own settings); it is
written into the output store's attributes so every store documents itself.

Per-image stages take ``start``/``stop`` (a shard of the concatenated image list:
references first, then queries) and write only those images; :func:`gather`
concatenates shards.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vprflow import datasets, stores
from vprflow.images import read_image, resize_image

log = logging.getLogger("vprflow")


# ------------------------------------------------------------------ dataset


def build_dataset(name: str, params: dict, data_root: str, out: str) -> None:
    """List and decode every image once (so a corrupt file fails here, by name) and
    store paths (relative to ``data_root``, so the data folder may move), sizes and
    ground truth. The absolute folder read is logged and kept in the attributes."""
    spec = params["params"]
    files = datasets.list_dataset(data_root, name, spec)
    folder = datasets.dataset_folder(data_root, spec)
    truth = datasets.ground_truth(files, spec["ground_truth"], folder)
    paths = files.reference + files.query
    sizes = np.zeros((len(paths), 2), dtype=np.int64)
    for i, path in enumerate(tqdm(paths, desc=f"checking {name} images")):
        sizes[i] = read_image(path).shape[:2]
    counts = np.array([len(t) for t in truth], dtype=np.int64)
    with stores.atomic_store(out, {"stage": "dataset", "params": params}) as group:
        group.attrs.update(
            name=name,
            data_root_at_build=str(Path(data_root).resolve()),
            n_reference=len(files.reference),
            n_query=len(files.query),
            ground_truth_rule=datasets.ground_truth_rule(spec["ground_truth"]),
            n_queries_with_positives=int((counts > 0).sum()),
        )
        stores.write_array(
            group, "paths", np.array([p.relative_to(data_root).as_posix() for p in paths])
        )
        stores.write_array(group, "names", np.array([f"{p.parent.name}/{p.name}" for p in paths]))
        stores.write_array(group, "image_sizes", sizes)
        stores.write_array(
            group, "truth", np.concatenate(truth) if truth else np.zeros(0, np.int64)
        )
        stores.write_array(group, "truth_offsets", np.r_[0, np.cumsum(counts)].astype(np.int64))
    log.info(
        "dataset %s: %d reference, %d query images read from %s",
        name,
        len(files.reference),
        len(files.query),
        folder.resolve(),
    )


class Dataset:
    """Read-side view of a dataset store. ``paths`` are the image files under
    ``data_root`` (relative to it when none is given)."""

    def __init__(self, path: str, data_root: str | None = None):
        self.group = stores.open_store(path)
        self.n_reference = int(self.group.attrs["n_reference"])
        self.n_query = int(self.group.attrs["n_query"])
        self.n_images = self.n_reference + self.n_query
        relative = stores.read_strings(self.group, "paths")
        root = Path(data_root) if data_root is not None else None
        self.paths = [str(root / p) if root else p for p in relative]
        self.names = stores.read_strings(self.group, "names")

    def truth(self) -> list[np.ndarray]:
        refs = np.asarray(self.group["truth"][...])
        offsets = np.asarray(self.group["truth_offsets"][...])
        return [refs[offsets[q] : offsets[q + 1]] for q in range(self.n_query)]

    def indices(self, which: str) -> np.ndarray:
        return {
            "reference": np.arange(self.n_reference),
            "query": np.arange(self.n_reference, self.n_images),
            "both": np.arange(self.n_images),
        }[which]


def resolved_sources(spec: dict) -> dict[str, str]:
    """The model directory or file a stage reads, as absolute paths (hub ids as they
    are), for its log and attributes: a ``..`` or absolute path outside ``data_root``
    is allowed, but never invisible."""
    from vprflow.models import is_local_model

    sources = {}
    for name in ("model", "file"):
        value = spec.get(name)
        if value:
            local = name == "file" or is_local_model(str(value))
            sources[name] = str(Path(value).expanduser().resolve()) if local else str(value)
    for name, value in sources.items():
        log.info("reads %s %s", name, value)
    return sources


def shard_range(n_images: int, start: int | None, stop: int | None) -> range:
    start = 0 if start is None else start
    stop = n_images if stop is None else min(stop, n_images)
    return range(start, stop)


def _stage_attrs(stage: str, params: dict, images: range) -> dict:
    return {"stage": stage, "params": params, "start": images.start, "stop": images.stop}


# ------------------------------------------------------------------ features


def compute_features(
    dataset_path: str,
    params: dict,
    out: str,
    data_root: str,
    device: str = "auto",
    batch_size: int = 1,
    start: int | None = None,
    stop: int | None = None,
) -> None:
    """Dense patch descriptors ``features [n, h, w, D]`` of images ``start..stop``."""
    spec = params["params"]
    dataset = Dataset(dataset_path, data_root)
    log.info("reading images under %s", Path(data_root).resolve())
    images = shard_range(dataset.n_images, start, stop)
    width, height = spec["resolution"]
    store_dtype = np.dtype(spec.get("store_dtype", "float16"))
    extract, patch_size = _feature_extractor(spec, device, width, height)
    attrs = {**_stage_attrs("features", params, images), "sources": resolved_sources(spec)}
    with stores.atomic_store(out, attrs) as group:
        array = None
        batches = [images[i : i + batch_size] for i in range(0, len(images), batch_size)]
        for batch in tqdm(batches, desc="features", unit="batch"):
            grids = extract([dataset.paths[i] for i in batch])
            if array is None:
                h, w, dim = grids.shape[1:]
                array = group.create_array(
                    "features",
                    shape=(len(images), h, w, dim),
                    chunks=(1, h, w, dim),
                    dtype=store_dtype,
                    compressors=stores.COMPRESSOR,
                )
                group.attrs.update(
                    grid=[h, w], dim=dim, patch_size=patch_size, image_size=[height, width]
                )
            elif grids.shape[1:] != array.shape[1:]:
                raise ValueError(
                    f"{dataset.paths[batch.start]}: feature grid {grids.shape[1:]} differs from "
                    f"the first image's {array.shape[1:]}"
                )
            start_row = batch.start - images.start
            stored = grids.astype(store_dtype)
            stores.check_finite(group, f"features of {dataset.paths[batch.start]}", stored)
            array[start_row : start_row + len(batch)] = stored


def _feature_extractor(spec: dict, device: str, width: int, height: int):
    """``(paths -> float32 [B, h, w, D], patch size)`` for the configured backbone.

    ``backbone: import`` reads the authors' published HDF5 features instead of
    running a model (``<image file name>/ift_dino``).
    """
    if spec["backbone"] == "import":
        from vprflow.arrays import l2_normalize
        from vprflow.published import read_features_h5

        def read(paths):
            grids = np.stack([read_features_h5(spec["file"], Path(p).name) for p in paths])
            return l2_normalize(grids) if spec.get("normalize", True) else grids

        return read, spec.get("patch_size", 14)
    from vprflow.backbones import load_backbone

    backbone = load_backbone(spec, device)

    def run(paths):
        pixels = np.stack(
            [resize_image(read_image(p), width, height, spec["resize"]) for p in paths]
        )
        return backbone.features(pixels)

    return run, backbone.patch_size


def read_features(group, index: int) -> np.ndarray:
    """float32 ``[h, w, D]`` of one image of a features store."""
    return np.asarray(group["features"][index], dtype=np.float32)


# ------------------------------------------------------------------ segments


def compute_segments(
    dataset_path: str,
    params: dict,
    out: str,
    data_root: str,
    device: str = "auto",
    start: int | None = None,
    stop: int | None = None,
) -> None:
    """Bit-packed masks per image at the segmentation resolution (ragged ``masks``)."""
    spec = params["params"]
    dataset = Dataset(dataset_path, data_root)
    log.info("reading images under %s", Path(data_root).resolve())
    images = shard_range(dataset.n_images, start, stop)
    segment = _mask_source(spec, device)
    attrs = {**_stage_attrs("segments", params, images), "sources": resolved_sources(spec)}
    with stores.atomic_store(out, attrs) as group:
        writer, shape = None, None
        for i in tqdm(images, desc="segments", unit="image"):
            masks = segment(dataset.paths[i])
            if shape is None:
                shape = masks.shape[1:]
                group.attrs.update(mask_height=shape[0], mask_width=shape[1])
                writer = stores.RaggedWriter(
                    group, "masks", ((shape[0] * shape[1] + 7) // 8,), np.uint8, chunk_rows=256
                )
            elif masks.shape[1:] != shape:
                raise ValueError(
                    f"{dataset.paths[i]}: masks of size {masks.shape[1:]} differ from the "
                    f"first image's {shape}"
                )
            if len(masks) == 0:
                log.warning("%s: the segmenter returned no masks", dataset.paths[i])
            writer.append(stores.pack_masks(masks))
        writer.close()


def _mask_source(spec: dict, device: str):
    """``path -> bool [S, Hm, Wm]`` for the configured segmenter.

    ``segmenter: import`` reads the authors' published HDF5 masks
    (``<image file name>/masks/<j>/segmentation``) at their own resolution.
    """
    if spec["segmenter"] == "import":
        from vprflow.published import read_masks_h5

        return lambda path: read_masks_h5(spec["file"], Path(path).name)
    from vprflow.segmenters import load_segmenter

    segmenter = load_segmenter(spec, device)
    width, height = spec["resolution"]
    return lambda path: segmenter.masks(
        resize_image(read_image(path), width, height, spec["resize"])
    )


def read_masks(group, index: int) -> np.ndarray:
    packed = stores.read_ragged(group, "masks", index)
    return stores.unpack_masks(
        packed, int(group.attrs["mask_height"]), int(group.attrs["mask_width"])
    )


# ------------------------------------------------------------------ vocabulary


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
    from vprflow.published import load_c_centers

    return load_c_centers(path)


def fit_vocabulary(dataset_path: str, features_path: str, params: dict, out: str) -> None:
    """VLAD centres ``[K, D]``: spherical k-means on sampled patch descriptors, or a file."""
    from vprflow.vlad import fit_spherical_kmeans

    spec = params["params"]
    if spec["source"] == "file":
        centres = load_centres_file(spec["file"])
        dim = int(stores.open_store(features_path).attrs["dim"])
        if centres.shape[1] != dim:
            raise ValueError(
                f"vocabulary.file {spec['file']}: centres have {centres.shape[1]} dimensions "
                f"but the features have {dim}; the file belongs to another backbone or layer"
            )
    else:
        dataset = Dataset(dataset_path)
        features = stores.open_store(features_path)
        images = dataset.indices(spec["fit_on"])
        h, w = features.attrs["grid"]
        per_image = h * w
        total = len(images) * per_image
        rng = np.random.default_rng(spec["seed"])
        chosen = np.sort(rng.choice(total, size=min(total, spec["max_descriptors"]), replace=False))
        owner = chosen // per_image
        sample = []
        for i in tqdm(np.unique(owner), desc="vocabulary sample", unit="image"):
            grid = read_features(features, images[i]).reshape(per_image, -1)
            sample.append(grid[chosen[owner == i] % per_image])
        sample = np.concatenate(sample)
        if len(sample) < spec["n_clusters"]:
            raise ValueError(
                f"config key vocabulary.n_clusters = {spec['n_clusters']} is more than the "
                f"{len(sample)} patch descriptors of the {spec['fit_on']} images "
                f"({len(images)} images x {per_image} patches, max_descriptors "
                f"{spec['max_descriptors']}): lower n_clusters"
            )
        centres = fit_spherical_kmeans(
            sample,
            spec["n_clusters"],
            spec["n_iter"],
            spec["seed"],
            centres=spec["centres"],
        )
    attrs = {"stage": "vocabulary", "params": params, "sources": resolved_sources(spec)}
    with stores.atomic_store(out, attrs) as group:
        stores.write_array(group, "centres", centres.astype(np.float32))


def read_centres(path: str) -> np.ndarray:
    return np.asarray(stores.open_store(path)["centres"][...], dtype=np.float32)


# ------------------------------------------------------------------ SegVLAD helpers


def _vlad_input(grid: np.ndarray, spec: dict) -> np.ndarray:
    """Patches as VLAD sees them: L2-normalised per patch unless the method says not
    (AnyLoc's VLAD ``norm_descs=True``; stored float16 features are only nearly unit)."""
    from vprflow.arrays import l2_normalize

    return l2_normalize(grid) if spec["normalize_descriptors"] else grid


def _segvlad_image(features, segments, centres, index, order, spec) -> np.ndarray:
    from vprflow.segvlad import image_segvlad

    grid = _vlad_input(read_features(features, index), spec)
    height, width = features.attrs["image_size"]
    return image_segvlad(
        grid,
        read_masks(segments, index),
        centres,
        (height, width),
        int(features.attrs["patch_size"]),
        order,
        crop_aligned=spec["mask_to_patch"] == "crop_aligned",
        small_graph=spec["small_graph"],
    )


# ------------------------------------------------------------------ PCA


def fit_pca_stage(
    dataset_path: str,
    features_path: str,
    segments_path: str,
    vocabulary_path: str,
    params: dict,
    out: str,
) -> None:
    """PCA fitted on a random sample of reference SegVLAD segment descriptors."""
    from vprflow.pca import fit_pca

    spec = params["params"]
    dataset = Dataset(dataset_path)
    features = stores.open_store(features_path)
    segments = stores.open_store(segments_path)
    centres = read_centres(vocabulary_path)
    offsets = np.asarray(segments["masks_offsets"][...])
    total = int(offsets[dataset.n_reference])
    rng = np.random.default_rng(spec["seed"])
    chosen = np.sort(rng.choice(total, size=min(total, spec["max_samples"]), replace=False))
    # Filled in place: for DINOv2-G this is 50,000 x 49,152 floats (10 GB), one copy only.
    sample = None
    filled = 0
    for i in tqdm(range(dataset.n_reference), desc="pca sample", unit="image"):
        rows = chosen[(chosen >= offsets[i]) & (chosen < offsets[i + 1])] - offsets[i]
        if len(rows):
            vectors = _segvlad_image(features, segments, centres, i, spec["fit_order"], spec)
            if sample is None:
                sample = np.empty((len(chosen), vectors.shape[1]), dtype=np.float32)
            sample[filled : filled + len(rows)] = vectors[rows]
            filled += len(rows)
    if sample is None:
        raise ValueError(f"{segments_path}: the reference images have no segments to fit PCA on")
    fitted = fit_pca(sample, spec["dim"], spec["whiten"], spec["seed"], solver=spec["solver"])
    with stores.atomic_store(out, {"stage": "pca", "params": params}) as group:
        # `dim` is the effective dimension: capped at the sample's numerical rank.
        group.attrs.update(
            whiten=fitted.whiten, n_samples=len(chosen), dim=fitted.dim, requested_dim=spec["dim"]
        )
        stores.write_array(group, "mean", fitted.mean)
        stores.write_array(group, "components", fitted.components)
        stores.write_array(group, "explained_variance", fitted.explained_variance)


def read_pca(path: str):
    from vprflow.pca import Pca

    group = stores.open_store(path)
    return Pca(
        mean=np.asarray(group["mean"][...]),
        components=np.asarray(group["components"][...]),
        explained_variance=np.asarray(group["explained_variance"][...]),
        whiten=bool(group.attrs["whiten"]),
    )


# ------------------------------------------------------------------ descriptors


def compute_descriptors(
    inputs: dict[str, str],
    params: dict,
    out: str,
    start: int | None = None,
    stop: int | None = None,
) -> None:
    """Per-image descriptors of one method.

    SegVLAD writes a ragged ``descriptors`` array (one row per segment, offsets per
    image); every global aggregator writes ``descriptors [n, dim]``.
    """
    spec = params["params"]
    aggregator = spec["aggregator"]
    dataset = Dataset(inputs["dataset"])
    features = stores.open_store(inputs["features"])
    images = shard_range(dataset.n_images, start, stop)
    attrs = _stage_attrs("descriptors", params, images)
    if aggregator == "segvlad":
        segments = stores.open_store(inputs["segments"])
        centres = read_centres(inputs["vocabulary"])
        pca = read_pca(inputs["pca"]) if "pca" in inputs else None
        dim = pca.dim if pca else centres.size
        with stores.atomic_store(out, {**attrs, "kind": "segments", "dim": dim}) as group:
            writer = stores.RaggedWriter(
                group, "descriptors", (dim,), np.float32, chunk_rows=max(1, (1 << 22) // (4 * dim))
            )
            for i in tqdm(images, desc="segvlad", unit="image"):
                vectors = _segvlad_image(features, segments, centres, i, spec["order"], spec)
                writer.append(pca.transform(vectors) if pca else vectors)
            writer.close()
        return
    global_descriptor = global_aggregator(spec, inputs)
    with stores.atomic_store(out, {**attrs, "kind": "global"}) as group:
        array = None
        for i in tqdm(images, desc=aggregator, unit="image"):
            vector = global_descriptor(read_features(features, i))
            if array is None:
                array = group.create_array(
                    "descriptors",
                    shape=(len(images), len(vector)),
                    chunks=(max(1, (1 << 22) // (4 * len(vector))), len(vector)),
                    dtype=np.float32,
                    compressors=stores.COMPRESSOR,
                )
                group.attrs["dim"] = len(vector)
            stores.check_finite(group, f"descriptors of {dataset.paths[i]}", vector)
            array[i - images.start] = vector


def global_aggregator(spec: dict, inputs: dict[str, str]):
    """``[h, w, D] -> [dim]`` for the configured global aggregator."""
    aggregator = spec["aggregator"]
    if aggregator == "anyloc_vlad":
        from vprflow.vlad import vlad

        centres = read_centres(inputs["vocabulary"])
        return lambda grid: vlad(_vlad_input(grid, spec).reshape(-1, grid.shape[-1]), centres)
    if aggregator == "snsm":
        from vprflow.snsm import snsm_descriptor

        options = {
            k: spec[k]
            for k in ("upscale", "window", "neighbourhood", "similarity", "normalization")
        }
        return lambda grid: snsm_descriptor(grid, **options)
    from vprflow import pooling
    from vprflow.snsm import normalize_tokens

    pool = {
        "gem": lambda tokens: pooling.gem(tokens, p=spec["p"]),
        "average": pooling.average_pool,
        "max": pooling.max_pool,
    }.get(aggregator)
    if pool is None:
        raise ValueError(f"unknown aggregator {aggregator!r}")
    # The SNSM authors pool tokens normalised like SNSM's own input (per channel).
    return lambda grid: pool(normalize_tokens(grid, spec["normalization"]))


# ------------------------------------------------------------------ shards


def gather(shard_paths: list[str], params: dict, out: str) -> None:
    """Concatenate per-image shard stores (in image order) into one store.

    Arrays with an ``<name>_offsets`` partner are ragged: rows are concatenated and
    offsets shifted; other arrays are concatenated along the image axis.
    """
    shards = [stores.open_store(p) for p in shard_paths]
    first = shards[0]
    names = [name for name, _ in stores.array_items(first)]
    attrs = {k: v for k, v in first.attrs.items() if k not in ("start", "stop")}
    attrs["params"] = params
    attrs["shards"] = len(shards)
    with stores.atomic_store(out, attrs) as group:
        for name in names:
            if name.endswith("_offsets"):
                continue
            source = first[name]
            chunks = source.chunks
            target = group.create_array(
                name,
                shape=(0, *source.shape[1:]),
                chunks=chunks,
                dtype=source.dtype,
                compressors=stores.COMPRESSOR,
            )
            for shard in tqdm(shards, desc=f"gather {name}", unit="shard"):
                if shard[name].shape[0]:
                    target.append(np.asarray(shard[name][...]), axis=0)
            if f"{name}_offsets" in names:
                offsets = [np.zeros(1, dtype=np.int64)]
                base = 0
                for shard in shards:
                    local = np.asarray(shard[f"{name}_offsets"][...])
                    offsets.append(local[1:] + base)
                    base += int(local[-1])
                stores.write_array(group, f"{name}_offsets", np.concatenate(offsets))


# ------------------------------------------------------------------ evaluation


def evaluate(dataset_path: str, descriptors_path: str, params: dict, out: str) -> None:
    """Retrieve references for every query, score them and compute Recall@N."""
    from vprflow.recall import correct_at, recall_at
    from vprflow.retrieval import (
        global_ranking,
        image_of_segment,
        search,
        vote_ranking,
    )

    spec = params["params"]
    dataset = Dataset(dataset_path)
    group = stores.open_store(descriptors_path)
    n_ref, n_query = dataset.n_reference, dataset.n_query
    top_k = min(spec["top_k"], n_ref)
    if group.attrs["kind"] == "segments":
        offsets = np.asarray(group["descriptors_offsets"][...])
        split = int(offsets[n_ref])
        vectors = group["descriptors"]
        reference, query = np.asarray(vectors[:split]), np.asarray(vectors[split:])
        distances, indices = search(reference, query, spec["top_segments"])
        owner = image_of_segment(offsets)
        ranking = vote_ranking(
            distances,
            indices,
            owner[split:] - n_ref,
            owner[:split],
            n_query,
            n_ref,
            top_k,
            spec["vote_ranking"],
        )
    else:
        vectors = np.asarray(group["descriptors"][...])
        ranking = global_ranking(vectors[:n_ref], vectors[n_ref:], top_k)
    truth = dataset.truth()
    # N beyond the number of references is kept: it equals Recall@n_ref.
    recalls = recall_at(ranking, truth, spec["recall_at"])
    evaluated = np.array([len(t) > 0 for t in truth], dtype=bool)
    ranked = (ranking >= 0).sum(axis=1)
    with stores.atomic_store(out, {"stage": "recall", "params": params}) as result:
        result.attrs.update(
            recall={str(n): v for n, v in recalls.items()},
            n_queries=int(evaluated.sum()),
            descriptor_dim=int(group.attrs["dim"]),
            # Queries ranking fewer references than the largest N (or than all of them):
            # SegVLAD ranks only voted images, and a missing rank counts as a miss.
            n_short_rankings=int((evaluated & (ranked < min(max(spec["recall_at"]), n_ref))).sum()),
            ground_truth_rule=dataset.group.attrs["ground_truth_rule"],
        )
        stores.write_array(result, "ranking", ranking.astype(np.int64))
        stores.write_array(result, "first_correct", correct_at(ranking, truth))
    log.info("recall: %s", recalls)


def write_report(
    dataset_name: str,
    dataset_path: str,
    runs: list[dict],
    recall_paths: list[str],
    csv_out: str,
    predictions_out: str,
) -> None:
    """The results table (one row per method) and per-query top predictions.

    ``runs[i]`` is ``{"method": name, "params": {flattened parameters}}`` for
    ``recall_paths[i]``. Output is deterministic: fixed column order, no timestamps.
    """
    import csv

    dataset = Dataset(dataset_path)
    results = [stores.open_store(p) for p in recall_paths]
    recall_columns = sorted({int(n) for r in results for n in r.attrs["recall"]})
    param_columns = sorted({name for run in runs for name in run["params"]})
    header = ["dataset", "method", *param_columns, "descriptor_dim", "ground_truth"]
    header += ["n_queries", "n_short_rankings"]
    header += [f"recall@{n}" for n in recall_columns]
    Path(csv_out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(csv_out).with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(header)
        for run, result in zip(runs, results, strict=True):
            recall = result.attrs["recall"]
            writer.writerow(
                [dataset_name, run["method"]]
                + [_cell(run["params"].get(name, "")) for name in param_columns]
                + [result.attrs["descriptor_dim"], result.attrs["ground_truth_rule"]]
                + [result.attrs["n_queries"], result.attrs["n_short_rankings"]]
                + [f"{recall[str(n)]:.6f}" if str(n) in recall else "" for n in recall_columns]
            )
    tmp.replace(csv_out)
    tmp = Path(predictions_out).with_suffix(".csv.tmp")
    truth = dataset.truth()
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(
            ["method", "query", "query_image", "positives", "first_correct_rank", "top"]
        )
        for run, result in zip(runs, results, strict=True):
            ranking = np.asarray(result["ranking"][...])
            first = np.asarray(result["first_correct"][...])
            for q in range(dataset.n_query):
                writer.writerow(
                    [
                        run["method"],
                        q,
                        dataset.names[dataset.n_reference + q],
                        " ".join(map(str, truth[q])),
                        int(first[q]) + 1 if first[q] >= 0 else "",
                        " ".join(map(str, ranking[q][ranking[q] >= 0])),
                    ]
                )
    tmp.replace(predictions_out)


def _cell(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
