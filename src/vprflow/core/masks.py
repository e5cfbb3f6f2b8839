"""How a segments store keeps its masks: a segmenter entry's ``masks_layout``.

``packed`` (when absent, the stores every key before the option hashes): the masks of
all images one after another, 256 a chunk file (:data:`vprflow.stages.segments.CHUNK_ROWS`).
``per_image``: each image's masks start a chunk file of their own
(:data:`vprflow.stages.segments.IMAGE_CHUNK_ROWS` masks a file), its last one padded
with empty rows, and ``masks_counts`` says how many are its. The masks read are the
same either way; only per_image lets another store hold an image by hard-linking its
files (:mod:`vprflow.core.reuse`), as a features store holds one image a file.
"""

PACKED, PER_IMAGE = "packed", "per_image"
MASKS_LAYOUTS = (PACKED, PER_IMAGE)
