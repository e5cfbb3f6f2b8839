"""One image's descriptor of any aggregator (vprflow.stages.image_descriptors)."""

from __future__ import annotations

import numpy as np
from toy_pipeline import N_PLACES, stage_path

from vprflow.core import stores


def test_a_new_aggregator_is_its_compute_function_and_nothing_in_the_stages(pipeline):
    """An entry's ``compute`` runs over each image's patch grid with the method's
    options, as every aggregator's does: GeM of the channel-normalised tokens this way
    gives the gem method's stored descriptors bit for bit."""
    from vprflow.aggregation.aggregators import Aggregator
    from vprflow.stages.image_descriptors import image_descriptor

    path = stage_path(pipeline, "features", "gem")
    stored = stores.open_store(stage_path(pipeline, "descriptors", "gem"))["descriptors"]
    new = Aggregator("gem_again", (), "global", _normalised_gem)
    options = {"aggregator": "gem_again", "p": 3.0, "normalization": "channel"}
    describe = image_descriptor(new, options, {"features": path})
    for index in (0, 2 * N_PLACES - 1):
        np.testing.assert_array_equal(describe(index), stored[index])


def _normalised_gem(grid: np.ndarray, options: dict) -> np.ndarray:
    from vprflow.aggregation.pooling import gem
    from vprflow.aggregation.snsm import normalize_tokens

    return gem(normalize_tokens(grid, options["normalization"]), p=options["p"])
