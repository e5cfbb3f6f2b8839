"""The floating-point precisions a config may name, torch-free.

:data:`vprflow.core.devices.DTYPES` maps the compute precisions to torch dtypes; the
config schema lists both tuples from here (``x-enum``), so validating a config does not
import torch.
"""

# A model's compute precision (`dtype` of a ViT backbone or a SAM segmenter).
COMPUTE_DTYPES = ("float32", "bfloat16", "float16")
# A store's precision (`store_dtype` of a backbone's features, of SegVLAD's descriptors):
# numpy dtypes, bfloat16 has none.
STORE_DTYPES = ("float32", "float16")
