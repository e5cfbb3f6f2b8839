"""What every stage shares: the :class:`Job` each stage's function takes, image ranges,
store attributes and logged sources."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from vprflow.models.hub import is_local_model

log = logging.getLogger("vprflow")


@dataclass(frozen=True)
class Job:
    """What one job of a stage needs: every stage's function takes one (``run(job)``, as
    :data:`vprflow.planning.plan.STAGES` names them) and reads what it uses.

    ``record`` is the stage's hashed record (:class:`vprflow.planning.plan.Stage`); ``inputs``
    its upstream stores (and files) by name; ``start``/``stop`` the image range of a sharded
    stage's job (references first, then queries; for ``search``, reference images; None:
    all); ``data_root``, ``run`` (device, batch size), ``threads`` and ``fingerprints`` do
    not shape the output.
    """

    record: dict
    inputs: dict[str, str]
    out: str
    start: int | None = None
    stop: int | None = None
    data_root: str = ""
    run: dict = field(default_factory=dict)  # the plan's run_params: device, batch_size
    threads: int = 1
    fingerprints: str | None = None  # the images and dataset stages' memo of content hashes

    @property
    def stage(self) -> str:
        return self.record["stage"]

    @property
    def params(self) -> dict:
        """The stage's own parameters (``record["params"]``)."""
        return self.record["params"]

    @property
    def device(self) -> str:
        return self.run.get("device", "auto")

    @property
    def batch_size(self) -> int:
        return self.run.get("batch_size", 1)

    def images(self, n_images: int) -> range:
        """The images of this job among ``n_images``: ``start..stop``, or all of them."""
        return shard_range(n_images, self.start, self.stop)


def resolved_sources(params: dict) -> dict[str, str]:
    """The model directory or file a stage reads, as absolute paths (hub ids as they
    are), for its log and attributes: a ``..`` or absolute path outside ``data_root``
    is allowed, but never invisible."""

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
