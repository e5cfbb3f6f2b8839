"""The x86-64 code paths this machine can force, and a child-process entry point that runs
a shipped dataset's stages under one of them and prints a digest of every store.

Each path is a set of environment changes (``None``: the variable unset) that picks
another kernel family or thread count for OpenBLAS (numpy's and faiss's BLAS), MKL and
ATen (torch's), or numpy's own SIMD loops. tests/aggregation/test_vlad_ties.py,
tests/workflow/test_code_paths.py and benchmarks/check_ties.py run under them.

Run as ``python tests/code_paths.py DATA_ROOT OUT DATASET[=STAGE+STAGE...],...``: runs
the STAGEs of each DATASET in the shipped config (``config/config.yaml``; without
``=``: every stage, the recall stores included) and what they read, in this process,
unsharded, into ``OUT/<dataset>``, and prints ``{dataset: run_dataset's result}`` as
JSON: each store's digest (sha256 of its arrays) and each recall store's table values.
Several datasets share one process: a child's start (its interpreter, numpy, zarr,
scikit-image, torch) costs 2-3 CPU seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _cpu_flags() -> set[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def code_paths() -> dict[str, dict[str, str | None]]:
    """Environment changes that force each kernel family this CPU can run; a path whose
    changes this environment already has (``OPENBLAS_CORETYPE=Haswell`` set here) is
    the default one, and left out."""
    threads = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    flags = _cpu_flags()
    paths: dict[str, dict[str, str | None]] = {
        "default": {},
        # The machine's own kernel, as a CPU without the environment's setting picks it.
        "openblas_unset": {"OPENBLAS_CORETYPE": None, "OPENBLAS_L2_SIZE": None},
        "openblas_haswell": {"OPENBLAS_CORETYPE": "Haswell"},
        "openblas_sandybridge": {"OPENBLAS_CORETYPE": "SandyBridge"},
        "openblas_prescott": {"OPENBLAS_CORETYPE": "Prescott"},
        "aten_default": {"ATEN_CPU_CAPABILITY": "default"},
        "mkl_cbwr_compatible": {"MKL_CBWR": "COMPATIBLE"},
        "mkl_avx": {"MKL_ENABLE_INSTRUCTIONS": "AVX"},
        "two_threads": dict.fromkeys(threads, "2"),
        "one_thread_scalar": {
            **dict.fromkeys(threads, "1"),
            "OPENBLAS_CORETYPE": "Prescott",
            "ATEN_CPU_CAPABILITY": "default",
            "MKL_CBWR": "COMPATIBLE",
        },
    }
    if "avx512f" in flags:
        paths["openblas_skylakex"] = {"OPENBLAS_CORETYPE": "SkylakeX"}
        paths["aten_avx512"] = {"ATEN_CPU_CAPABILITY": "avx512"}
        # numpy's own loops as on a CPU without AVX-512.
        paths["numpy_avx2"] = {"NPY_DISABLE_CPU_FEATURES": "AVX512F AVX512CD AVX512_SKX"}
    return {
        name: changes
        for name, changes in paths.items()
        if name == "default" or any(os.environ.get(k) != v for k, v in changes.items())
    }


def path_environment(changes: dict[str, str | None]) -> dict[str, str]:
    """This process's environment with ``changes`` applied (``None`` removes)."""
    env = dict(os.environ)
    for name, value in changes.items():
        if value is None:
            env.pop(name, None)
        else:
            env[name] = value
    return env


def start_child(
    data_root: Path, out: Path, datasets: dict[str, list[str] | None], changes: dict
) -> subprocess.Popen:
    """This file's entry point for ``datasets`` (each one's stages; None: all) in a
    process of its own under code path ``changes``; :func:`child_result` reads it."""
    spec = ",".join(
        d if stages is None else f"{d}={'+'.join(stages)}" for d, stages in datasets.items()
    )
    return subprocess.Popen(
        [sys.executable, __file__, str(data_root), str(out), spec],
        env=path_environment(changes),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def child_result(process: subprocess.Popen, what: str) -> dict:
    """What :func:`start_child`'s process printed (by dataset, :func:`run_dataset`'s result);
    ``RuntimeError`` naming ``what`` ran, with the end of its stderr, when it failed."""
    stdout, stderr = process.communicate(timeout=900)
    if process.returncode:
        raise RuntimeError(f"{what}: {stderr[-3000:]}")
    return json.loads(stdout.strip().splitlines()[-1])


def store_digest(path: str) -> str:
    """sha256 of every array of the store at ``path`` (names, shapes, dtypes, bytes), the
    per-query timings excluded."""
    from vprflow.core.stores import array_items, open_store

    digest = hashlib.sha256()
    for name, array in array_items(open_store(path)):
        data = np.ascontiguousarray(array[...])
        digest.update(f"{name} {data.dtype} {data.shape}".encode())
        digest.update(data.tobytes())
    return digest.hexdigest()


# What a recall store holds of its table (its attributes but the cost, which is timed).
TABLE_ATTRIBUTES = (
    "recall",
    "map",
    "precision_recall",
    "recall_exact",
    "n_queries",
    "n_queries_without_positive",
    "n_short_rankings",
    "denominator",
    "descriptor_dim",
)


def digests(stores: dict[tuple[str, str], str]) -> dict:
    """``{"stores": {"<stage> <key>": digest}, "tables": {"<recall key>": its table's
    values}}`` of ``stores`` (``(stage, key)`` -> path)."""
    from vprflow.core.stores import open_store

    result: dict = {"stores": {}, "tables": {}}
    for (stage, key), path in stores.items():
        result["stores"][f"{stage} {key}"] = store_digest(path)
        if stage == "recall":
            attrs = open_store(path).attrs
            result["tables"][key] = {name: attrs.get(name) for name in TABLE_ATTRIBUTES}
    return result


def run_dataset(data_root: Path, out: Path, dataset: str, stages: list[str] | None = None) -> dict:
    """Run ``dataset``'s ``stages`` (default: all) of the shipped config, and what they
    read, into ``out`` -> their stores' :func:`digests`."""
    import yaml
    from workflow_helpers import SCHEMA, run_stage

    from vprflow.planning.config import validate_config
    from vprflow.planning.plan import STAGES, build_plan

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["data_root"] = str(data_root)
    config["targets"] = [dataset]
    config["datasets"] = {dataset: config["datasets"][dataset]}
    plan = build_plan(validate_config(config, SCHEMA))
    done: dict = {}
    for stage in [s for s in STAGES if stages is None or s in stages]:
        for key, planned in sorted(plan.stages.get(stage, {}).items()):
            if planned.dataset == dataset:  # not a preset whose folder data_root holds
                run_stage(plan, stage, key, data_root, out, done)
    wanted = {ref: path for ref, path in done.items() if stages is None or ref[0] in stages}
    return digests(wanted)


def workflow_digests(workdir: Path) -> dict:
    """The :func:`digests` of every store a finished Snakemake run left in ``workdir``."""
    from vprflow.core.paths import CACHE
    from vprflow.planning.plan import STAGES

    stores = {
        (stage, path.name.removesuffix(".zarr")): str(path)
        for stage in STAGES
        for path in sorted((workdir / CACHE / stage).glob("*.zarr"))
    }
    return digests(stores)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    root, out = Path(sys.argv[1]), Path(sys.argv[2])
    asked = [item.partition("=") for item in sys.argv[3].split(",")]
    runs = {name: stages.split("+") if stages else None for name, _, stages in asked}
    print(json.dumps({name: run_dataset(root, out / name, name, runs[name]) for name in runs}))
