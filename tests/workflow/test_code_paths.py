"""One table on every machine: the shipped corridor and roadscene runs under x86-64 code
paths this CPU can force (tests/code_paths.py), each in a process of its own, against
the environment's path (the shipped runs the other tests read: conftest.py).

- the whole tables (every recall, mAP and precision-recall value and count of every row)
  and vprflow's own steps' stores, the weight-free DAISY features, SLIC segments and the
  map vocabulary's k-means (docs/methods.md §3), are equal under the machine's own
  kernels, which differ from the environment's in every variable at once
  (OPENBLAS_CORETYPE and OPENBLAS_L2_SIZE unset: the failing README of an AVX-512 CPU;
  two threads, ATen's AVX-512 where the CPU has it, MKL's AVX kernels);
- the own steps are the same bits under scalar-most kernels on one thread (OpenBLAS
  Prescott, ATen's default capability, MKL's conditional reproducibility, numpy's loops
  without AVX-512) and under other OpenBLAS core types: corridor's three, and
  roadscene's SLIC segments (its thermal ones moved on SandyBridge and Prescott; its
  DAISY features and k-means are corridor's code on other images, which the machine's
  own kernels check, at 40 CPU seconds fewer).

``benchmarks/check_code_paths.py`` runs the whole tables under every single path of
code_paths() and names the stores that move where the authors' code moves (VLAD sums,
PCA, faiss's segment search, the re-rankers' float32 matches); no table value moves
(benchmarks/README.md).
"""

from __future__ import annotations

import pytest
from code_paths import child_result, code_paths, start_child, workflow_digests

pytestmark = pytest.mark.data

SINGLE = code_paths()


def merged(*names: str) -> dict:
    """The changes of the named single paths that this CPU has, together."""
    return {k: v for name in names if name in SINGLE for k, v in SINGLE[name].items()}


SCALAR = merged("one_thread_scalar", "numpy_avx2")
WHOLE_TABLES = {
    "machine_kernels": merged("openblas_unset", "two_threads", "aten_avx512", "mkl_avx")
}
OWN_STEPS = {
    "corridor": {
        **{
            name: SINGLE[name]
            for name in ("openblas_haswell", "openblas_sandybridge")
            if name in SINGLE
        },
        "scalar_one_thread": SCALAR,
    },
    "roadscene": {
        "openblas_sandybridge": SINGLE["openblas_sandybridge"],
        "scalar_one_thread": SCALAR,
    },
}
DATASETS = ("corridor", "roadscene")
OWN = ("features", "segments", "vocabulary")
# The own steps each dataset runs under OWN_STEPS' paths (under WHOLE_TABLES: all).
CHECKED = {"corridor": OWN, "roadscene": ("segments",)}


@pytest.fixture(scope="module")
def runs(request, data_root, tmp_path_factory) -> dict[tuple[str, str], dict]:
    """``{(dataset, path): run_dataset's result}``: every stage under WHOLE_TABLES, the
    own steps under OWN_STEPS, one process a path (the datasets of a path together),
    two at a time; the environment's path is the shipped Snakemake runs the other tests
    read (conftest.py), asked for once the children are done, so that another worker
    may have built them meanwhile."""
    out = tmp_path_factory.mktemp("code_paths")
    jobs = [(p, changes, dict.fromkeys(DATASETS)) for p, changes in WHOLE_TABLES.items()]
    own_paths = {p: changes for d in DATASETS for p, changes in OWN_STEPS[d].items()}
    jobs += [
        (p, changes, {d: list(CHECKED[d]) for d in DATASETS if p in OWN_STEPS[d]})
        for p, changes in own_paths.items()
    ]
    results, running = {}, []

    def collect(path, datasets, process):
        found = child_result(process, f"{', '.join(datasets)} under {path}")
        results.update({(dataset, path): found[dataset] for dataset in datasets})

    for path, changes, datasets in jobs:
        process = start_child(data_root, out / path, datasets, changes)
        running.append((path, datasets, process))
        if len(running) == 2:  # two processes at a time: this machine's cores
            collect(*running.pop(0))
    for job in running:
        collect(*job)
    results["corridor", "default"] = workflow_digests(request.getfixturevalue("corridor_run")[0])
    results["roadscene", "default"] = workflow_digests(request.getfixturevalue("roadscene_run"))
    return results


def own_stores(result: dict, stages: tuple[str, ...] = OWN) -> dict[str, str]:
    return {k: v for k, v in result["stores"].items() if k.split()[0] in stages}


@pytest.mark.parametrize(
    ("dataset", "path"),
    [(d, p) for d in DATASETS for p in [*WHOLE_TABLES, *OWN_STEPS[d]]],
)
def test_vprflows_own_steps_are_the_same_bits_under(path, dataset, runs):
    """DAISY features, SLIC segments and the map vocabulary's k-means; roadscene's SLIC
    segments alone under OWN_STEPS' paths (CHECKED)."""
    ours = own_stores(runs[dataset, path])
    checked = OWN if path in WHOLE_TABLES else CHECKED[dataset]
    default = own_stores(runs[dataset, "default"], checked)
    assert {name.split()[0] for name in ours} == set(checked) and set(ours) == set(default)
    differ = sorted(name for name, digest in ours.items() if default[name] != digest)
    assert not differ, f"{dataset} under {path}: {differ} differ from the environment's"


@pytest.mark.parametrize("dataset", DATASETS)
@pytest.mark.parametrize("path", list(WHOLE_TABLES))
def test_every_table_value_is_the_same_under(path, dataset, runs):
    tables, default = runs[dataset, path]["tables"], runs[dataset, "default"]["tables"]
    assert len(default) >= 9 and set(tables) == set(default)  # every row of the table
    differ = sorted(key for key in default if tables[key] != default[key])
    assert not differ, f"{dataset} under {path}: rows {differ} differ from the environment's"
