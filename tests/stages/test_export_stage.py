"""The pairs files (vprflow.stages.export): each query's ranking at the depth asked for."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from toy_pipeline import N_PLACES, stage_path

from vprflow.core import stores
from vprflow.stages.export import ranking_at_depth, write_pairs
from vprflow.stages.readers import Dataset
from vprflow.stages.retrieval import retrieve


def retrieval_paths(pipeline, run) -> dict[str, str]:
    """The descriptors and (per-segment methods) search stores of a row's recall."""
    plan, runner, _, _ = pipeline
    inputs = plan.get("recall", run.recall_key).inputs
    return {
        f"{name}_path": runner.path(*inputs[name])
        for name in ("descriptors", "search")
        if name in inputs
    }


def test_pairs_files_list_each_querys_ranking_as_hloc_and_kapture_read_them(pipeline, tmp_path):
    plan, _, recalls, _ = pipeline
    dataset = Dataset(stage_path(pipeline, "dataset"))
    for run, path in zip(plan.runs["toy"], recalls, strict=True):
        pairs, kapture = tmp_path / f"{run.method}.txt", tmp_path / f"{run.method}.kapture"
        # 20 deep, past the toy's 6 references: every ranked reference.
        write_pairs(
            stage_path(pipeline, "dataset"),
            path,
            str(pairs),
            str(kapture),
            20,
            **retrieval_paths(pipeline, run),
        )
        result = stores.open_store(path)
        ranking, scores = np.asarray(result["ranking"]), np.asarray(result["scores"])
        expected = [
            (dataset.names[dataset.n_reference + q], dataset.names[r], scores[q, k])
            for q in range(dataset.n_query)
            for k, r in enumerate(ranking[q])
            if r >= 0 and (ranking[q, :k] >= 0).all()
        ]
        assert [tuple(line.split(" ")) for line in pairs.read_text().splitlines()] == [
            (query, reference) for query, reference, _ in expected
        ]
        lines = kapture.read_text().splitlines()
        assert lines[0] == "# kapture format: 1.0" and lines[2].startswith("# score: ")
        rows = [line.split(", ") for line in lines if not line.startswith("#")]
        assert [(q, r) for q, r, _ in rows] == [(q, r) for q, r, _ in expected]
        np.testing.assert_allclose(
            [float(v) for *_, v in rows], [v for *_, v in expected], rtol=1e-5
        )


def cut_recall_store(path: str, out: Path, width: int) -> str:
    """A copy of the recall store at ``path`` whose ranking and scores end after
    ``width`` columns, as a recall of fewer references than the pairs ask for."""
    result = stores.open_store(path)
    with stores.atomic_store(out, dict(result.attrs)) as group:
        for name in ("ranking", "scores"):
            stores.write_array(group, name, np.asarray(result[name][...])[:, :width])
    return str(out)


def test_the_pairs_depth_cuts_the_recalls_ranking_or_continues_it_with_the_retrieval(
    pipeline, tmp_path
):
    """Shallower than the recall's ranking: its first columns. Deeper (a recall store cut
    to 2 of the toy's 6 references): the recall's columns, then the method's own
    retrieval without the references already ranked; a re-ranked row's continuation
    scores as its lowest score."""
    plan, _, recalls, _ = pipeline
    dataset = Dataset(stage_path(pipeline, "dataset"))
    rows = {r.method: (r, path) for r, path in zip(plan.runs["toy"], recalls, strict=True)}
    for method in ("anyloc_vlad", "anyloc_vlad+mnn", "segvlad", "segvlad+ransac"):
        run, path = rows[method]
        paths = retrieval_paths(pipeline, run)
        result = stores.open_store(path)
        ranking, scores = np.asarray(result["ranking"]), np.asarray(result["scores"])
        shallow = ranking_at_depth(dataset, path, 3, **paths)
        np.testing.assert_array_equal(shallow[0], ranking[:, :3])
        np.testing.assert_array_equal(shallow[1], scores[:, :3])
        cut = cut_recall_store(path, tmp_path / f"{method}.zarr", 2)
        deep, deep_scores, kind = ranking_at_depth(dataset, cut, 6, **paths)
        assert deep.shape == (N_PLACES, 6) and kind == result.attrs["score"]
        np.testing.assert_array_equal(deep[:, :2], ranking[:, :2])
        retrieved = retrieve(
            dataset, paths["descriptors_path"], 6, paths.get("search_path"),
            result.attrs["record"]["params"].get("vote_ranking"),
        )  # fmt: skip
        for q in range(N_PLACES):
            rest = [r for r in retrieved[0][q] if r >= 0 and r not in ranking[q, :2]]
            assert list(deep[q, 2:]) == rest + [-1] * (4 - len(rest)), (method, q)
            if "+" in method:
                assert set(deep_scores[q, 2 : 2 + len(rest)]) <= {scores[q, :2].min()}
            elif (ranking[q] >= 0).all():  # the retrieval's own order and scores
                np.testing.assert_array_equal(deep[q], ranking[q])
                np.testing.assert_allclose(deep_scores[q], scores[q], rtol=1e-6)
