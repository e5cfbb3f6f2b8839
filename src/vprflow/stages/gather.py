"""The ``gather`` rule: one store from the per-image shards of a stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr
from tqdm import tqdm

from vprflow.core import reuse, stores
from vprflow.core.paths import shard_layout


def gather(shard_paths: list[str], record: dict, out: str) -> None:
    """Concatenate per-image shard stores (in image order) into one store.

    Arrays with an ``<name>_offsets`` partner are ragged: rows are concatenated and
    offsets shifted; other arrays are concatenated along the image axis. A single shard
    is renamed into place (its store is a temporary output nobody else reads).
    """
    shards = [stores.open_store(p) for p in shard_paths]
    first = shards[0]
    names = [name for name, _ in stores.array_items(first)]
    attrs = {k: v for k, v in first.attrs.items() if k not in ("start", "stop")}
    attrs["record"] = record
    attrs["shards"] = shard_layout(shard_paths)
    packed = _packed(names, record)
    if len(shards) == 1:
        # One shard is the whole store: rename it instead of copying every array. Its
        # attributes are rewritten first, so `out` appears complete or not at all. Only the
        # group's: each array keeps the chunk count atomic_store recorded for open_store.
        for name in packed:
            reuse.link_equal_chunks(Path(shard_paths[0]) / name, record, Path(out).parent)
        zarr.open_group(shard_paths[0], mode="r+").attrs.put(attrs)
        stores.replace_store(shard_paths[0], out)
        return
    with stores.atomic_store(out, attrs) as group:
        for name in names:
            if name.endswith("_offsets"):
                continue
            if _whole_chunks(shards, name):
                _link_rows(shards, name, group)
            else:
                source = first[name]
                target = group.create_array(
                    name,
                    shape=(0, *source.shape[1:]),
                    chunks=source.chunks,
                    dtype=source.dtype,
                    # The shards' own (features: CHECKSUM_ONLY), which carry the checksum.
                    compressors=source.raw.compressors,
                    chunk_key_encoding=source.raw.metadata.chunk_key_encoding,
                )
                for shard in tqdm(shards, desc=f"gather {name}", unit="shard"):
                    if shard[name].shape[0]:
                        target.append(np.asarray(shard[name][...]), axis=0)
                if name in packed:
                    array = stores.array_directory(target)
                    reuse.link_equal_chunks(array, record, Path(out).parent)
            if f"{name}_offsets" in names:
                offsets = [np.zeros(1, dtype=np.int64)]
                base = 0
                for shard in shards:
                    local = np.asarray(shard[f"{name}_offsets"][...])
                    offsets.append(local[1:] + base)
                    base += int(local[-1])
                stores.write_array(group, f"{name}_offsets", np.concatenate(offsets))


def _whole_chunks(shards: list[stores.CheckedGroup], name: str) -> bool:
    """Whether every shard's ``name`` but the last's ends on a chunk boundary, in chunk
    files alike (chunked along the first axis only, with a checksum last): then each
    chunk of the gathered array is one shard's chunk as it is (features, one image a
    chunk; per_image masks, :mod:`vprflow.core.masks`)."""
    first = shards[0][name]
    folder = stores.array_directory(first.raw)
    return (
        first.chunks[1:] == first.shape[1:]
        and first.raw.compressors in (stores.CHECKSUM_ONLY, stores.COMPRESSORS)
        and all(shard[name].shape[0] % first.chunks[0] == 0 for shard in shards[:-1])
        and all(
            reuse.same_chunks(folder, stores.array_directory(shard[name].raw))
            for shard in shards[1:]
        )
    )


def _packed(names: list[str], record: dict) -> list[str]:
    """The ragged arrays of a stage whose results are reused per image (a segments
    store's masks): many images' rows a chunk, so their chunks are shared whole with
    stores holding the same rows (:func:`vprflow.core.reuse.link_equal_chunks`)."""
    if record["stage"] not in reuse.STAGES:
        return []
    return [name for name in names if f"{name}_offsets" in names]


def _link_rows(shards: list[stores.CheckedGroup], name: str, group: zarr.Group) -> None:
    """``name`` gathered by hard-linking each shard's chunk files at their new places
    (:func:`_whole_chunks`): the same files as appending the rows writes, without
    reading them, and rows reused from another store (:mod:`vprflow.core.reuse`) stay
    one file on disk."""
    first = shards[0][name]
    step = first.chunks[0]
    target = group.create_array(
        name,
        shape=(sum(shard[name].shape[0] for shard in shards), *first.shape[1:]),
        chunks=first.chunks,
        dtype=first.dtype,
        compressors=first.raw.compressors,
        chunk_key_encoding=first.raw.metadata.chunk_key_encoding,
    )
    plain = first.raw.compressors == stores.CHECKSUM_ONLY
    chunk_bytes = first.dtype.itemsize * int(np.prod(first.chunks)) if plain else None
    base = 0
    for shard in shards:
        array = shard[name]
        for index in range(-(-array.shape[0] // step)):
            source = reuse.chunk_file(array.raw, index)
            if source.exists() and not reuse.link_chunk(
                source, reuse.chunk_file(target, base + index), chunk_bytes
            ):
                raise stores.StoreCorruptError(
                    shard.path, f"array '{name}' chunk {index} is damaged"
                )
        base += array.shape[0] // step
