"""What every stage shares: image ranges, store attributes and logged sources."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger("vprflow")


def resolved_sources(params: dict) -> dict[str, str]:
    """The model directory or file a stage reads, as absolute paths (hub ids as they
    are), for its log and attributes: a ``..`` or absolute path outside ``data_root``
    is allowed, but never invisible."""
    from vprflow.models.hub import is_local_model

    sources = {}
    for name in ("model", "file"):
        value = params.get(name)
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


def stage_attrs(stage: str, record: dict, images: range) -> dict:
    return {"stage": stage, "record": record, "start": images.start, "stop": images.stop}
