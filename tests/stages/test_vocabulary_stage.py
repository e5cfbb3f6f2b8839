"""The vocabulary stage (vprflow.stages.vocabulary) and the PCA fitted on its VLADs
(vprflow.stages.pca): their shapes."""

from __future__ import annotations

from toy_pipeline import stage_path

from vprflow.stages.readers import read_centres, read_pca


def test_vocabulary_and_pca_shapes(pipeline):
    centres = read_centres(stage_path(pipeline, "vocabulary"))
    assert centres.shape == (3, 104)
    pca = read_pca(stage_path(pipeline, "pca"))
    assert pca.components.shape == (8, 3 * 104)
