"""Reading a place dataset: its images (``images``: any bit depth, EXIF orientation, the
published resizes) and their lists (``datasets``), the ground truth (``ground_truth``,
from positions in ``positions`` or the papers' own files in ``published_truth``), the
authors' preprocessed files (``published``), the papers' datasets as presets
(``presets``, ``presets.yaml``) and public datasets on demand (``download``).
"""
