"""From a config to the stages of every experiment: validation (``config``), the plan
of content-addressed stages (``plan``), content hashes (``fingerprints``), what a change
reruns (``reruns``), the report's files (``reports``) and the store index
(``store_index``). Never imports torch.
"""
