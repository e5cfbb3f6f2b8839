"""Segment Anything's automatic mask generation for every SAM kind: the generator
(``generator``), its mask operations (``masks``), the shared prompt decoder
(``decoder``) and one adapter per kind (``adapters``).
"""
