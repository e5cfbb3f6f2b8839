"""Segment retrieval: faiss flat against the exact torch path (bf16 and float32 candidates),
optionally sharded, and SegVLAD image voting, on random unit vectors.

    python benchmarks/bench_retrieval.py        # 20,000 x 5,000 x 1024, about 1 min on 2 cores
    python benchmarks/bench_retrieval.py --smoke   # 340 x 170 x 32, every method, CPU
    # 17places shapes (34,510 reference x 34,510 query segments, d 1024)
    python benchmarks/bench_retrieval.py --ref-segments 34510 --query-segments 34510 --dim 1024
    # 1M reference x 20k query segments: a 4 GiB database (+ 4 GiB per worker process),
    # faiss flat does 4e13 flops (minutes on 16 cores; a GPU takes the torch path)
    python benchmarks/bench_retrieval.py --ref-segments 1000000 --query-segments 20000 \\
        --dim 1024 --shard 250000

The inputs are written once as ``.npy`` to a temporary folder. Each method runs in a
fresh process (``--smoke``: all of them in one, so ``peak`` is theirs together) that
loads them and makes a small warm-up call (library start-up, thread pools), then times
``--repeat`` searches (default 3): the table shows the fastest, the notes the median,
since on a shared machine the spread comes from other load. Memory: ``peak`` is the
process's ``ru_maxrss`` (inputs included); ``search`` is how much the first search
raised it over the resident size after loading and warm-up, i.e. the method's own
working memory and outputs. tracemalloc would miss both torch's and faiss's native
allocations.

Columns: ``time s`` is wall-clock time, ``cpu s`` the process's CPU time over all its
threads (both the fastest repeat); ``/ faiss`` is each over faiss flat's. On a machine
shared with other jobs both mislead: threads waiting at barriers burn CPU time, and the
torch path (many short multi-threaded steps) suffers more than faiss (one long GEMM), so
compare methods on an idle machine. ``agree@k`` is the mean fraction of each query's top-k
set shared with faiss flat (:func:`vprflow.search.topk.topk_agreement`; below 1 only through
near-ties within float32 rounding). Voting is
:func:`vprflow.search.voting.vote_ranking` on faiss flat's lists with 85 segments per image;
its note gives the fraction of query images whose top-50 ranking is identical when voted
from the exact bf16 lists instead.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from revisions import module_at  # noqa: E402

SRC = Path(__file__).resolve().parents[1] / "src"
SEGMENTS_PER_IMAGE = 85
VOTE_TOP = 50
CHUNK = 8192
# exact_knn before its chunked norms and fewer, larger re-scoring steps.
OLD_EXACT = "d036158"
# What OLD_EXACT's exact.py imports that has gone since.
OLD_EXACT_IMPORTS = ("vprflow.core.registry",)


def write_unit_vectors(path: Path, n: int, dim: int, seed: int) -> None:
    """Random unit vectors ``[n, dim]`` float32 to ``path``, in chunks (bounded memory)."""
    rng = np.random.default_rng(seed)
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(n, dim))
    for start in range(0, n, CHUNK):
        x = rng.standard_normal((min(CHUNK, n - start), dim), dtype=np.float32)
        out[start : start + len(x)] = x / np.linalg.norm(x, axis=1, keepdims=True)
    out.flush()
    del out


def max_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def load_old_exact(ref: str):
    """``exact_knn`` as it was at git revision ``ref`` (the baseline the chunked exact
    search is compared with), loaded from ``git show`` into a module of its own, with the
    registry of ``ref`` it imported; None without git or ref."""
    try:
        module = module_at(ref, "vprflow.search.exact", "vprflow_exact_old", OLD_EXACT_IMPORTS)
    except (OSError, subprocess.CalledProcessError):
        return None
    return module.exact_knn


def bf16_floor(database: np.ndarray, queries: np.ndarray, args: argparse.Namespace):
    """The bf16 products alone, blocked as exact_knn blocks them: the floor of the exact
    search. Returns ``search(db, q)`` over the first ``len(db)``, ``len(q)`` rows; the bf16
    copies are made here, outside the timing, and the products are dropped."""
    import torch

    db = torch.from_numpy(database).to(args.device_resolved, torch.bfloat16)
    q = torch.from_numpy(queries).to(args.device_resolved, torch.bfloat16)

    def search(rows_db: np.ndarray, rows_q: np.ndarray) -> tuple[None, None]:
        for first in range(0, len(rows_db), args.block_database):
            ref = db[first : min(first + args.block_database, len(rows_db))]
            for start in range(0, len(rows_q), args.block_queries):
                torch.mm(q[start : min(start + args.block_queries, len(rows_q))], ref.T)
        if db.device.type == "cuda":
            torch.cuda.synchronize()
        return None, None

    return search


def worker(method: str, folder: Path, args: argparse.Namespace) -> None:
    """Run one method in this process and save its lists and measurements."""
    sys.path.insert(0, str(SRC))
    import faiss
    import torch

    from vprflow.search.exact import exact_knn
    from vprflow.search.flat import flat_knn
    from vprflow.search.topk import merge_knn

    database = np.load(folder / "database.npy")
    queries = np.load(folder / "queries.npy")
    options = {
        "device": args.device,
        "block_queries": args.block_queries,
        "block_database": args.block_database,
        "candidate_dtype": "float32" if method == "exact_float32" else "bfloat16",
    }
    knn = exact_knn
    if method == "exact_old":
        knn = load_old_exact(args.old_exact)

    def search(db: np.ndarray, q: np.ndarray, stats: dict) -> tuple[np.ndarray, np.ndarray]:
        if method == "faiss_flat":
            return flat_knn(db, q, args.k)
        if method == "bf16_floor":
            return floor(db, q)
        if method != "exact_sharded":
            return knn(db, q, args.k, stats=stats, **options)
        parts = []
        for first in range(0, len(db), args.shard):
            d, i = exact_knn(db[first : first + args.shard], q, args.k, stats=stats, **options)
            parts.append((d, i + first))
        return merge_knn(parts, args.k)

    if method == "bf16_floor":
        from vprflow.core.devices import resolve_device

        args.device_resolved = resolve_device(args.device)
        floor = bf16_floor(database, queries, args)
    search(database[:2000], queries[:64], {})  # warm-up: thread pools, kernels, faiss init
    base = max_rss_mib()
    times, cpu = [], []
    for _ in range(args.repeat):
        stats: dict = {}
        start, start_cpu = time.perf_counter(), time.process_time()
        distances, indices = search(database, queries, stats)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        if len(times) == 1:
            peak = max_rss_mib()  # repeats reuse the memory; the first shows what it takes
    if distances is not None:
        np.save(folder / f"{method}_distances.npy", distances)
        np.save(folder / f"{method}_indices.npy", indices)
    report = {"seconds": min(times), "median": float(np.median(times)), "search_mib": peak - base}
    report["cpu_seconds"] = min(cpu)
    report["stats"] = stats
    # The libraries as the methods ran them, for the table's heading: the parent imports
    # neither.
    report["torch"] = f"torch {torch.__version__} ({torch.get_num_threads()} threads"
    report["faiss"] = f"faiss {faiss.__version__} ({faiss.omp_get_max_threads()} threads)"
    (folder / f"{method}.json").write_text(json.dumps(report))


def run_methods(methods: list[str], folder: Path, args: argparse.Namespace) -> dict[str, dict]:
    """``{method: report}`` from one fresh process that runs ``methods`` one after the
    other; its peak memory is the largest of theirs (one method a process: its own)."""
    command = [sys.executable, __file__, "--worker", ",".join(methods), "--data", str(folder)]
    command += ["--k", str(args.k), "--block-queries", str(args.block_queries)]
    command += ["--shard", str(args.shard or 0), "--device", args.device]
    command += ["--repeat", str(args.repeat), "--block-database", str(args.block_database)]
    command += ["--old-exact", args.old_exact]
    process = subprocess.Popen(command)
    _, status, usage = os.wait4(process.pid, 0)
    if status != 0:
        raise SystemExit(f"{', '.join(methods)} failed (status {status})")
    reports = {}
    for method in methods:
        report = json.loads((folder / f"{method}.json").read_text())
        report["peak_mib"] = usage.ru_maxrss / 1024
        if method != "bf16_floor":
            report["indices"] = np.load(folder / f"{method}_indices.npy")
            report["distances"] = np.load(folder / f"{method}_distances.npy")
        reports[method] = report
    return reports


def voted(report: dict, n_query: int, n_ref: int, args: argparse.Namespace):
    from vprflow.search.voting import vote_ranking

    query_image = np.arange(args.query_segments) // SEGMENTS_PER_IMAGE
    ref_image = np.arange(args.ref_segments) // SEGMENTS_PER_IMAGE
    start = time.perf_counter()
    ranking = vote_ranking(
        report["distances"], report["indices"], query_image, ref_image, n_query, n_ref, VOTE_TOP
    )
    return ranking, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ref-segments", type=int, default=20_000)
    parser.add_argument("--query-segments", type=int, default=5_000)
    parser.add_argument("--dim", type=int, default=1024)
    parser.add_argument("--k", type=int, default=50)
    parser.add_argument("--shard", type=int, default=0, help="also run per reference shard")
    parser.add_argument("--block-queries", type=int, default=4096)
    parser.add_argument("--block-database", type=int, default=65536)
    parser.add_argument(
        "--old-exact",
        default=OLD_EXACT,
        help="git revision whose exact_knn is timed as 'exact_knn before' ('' to skip)",
    )
    parser.add_argument("--device", default="auto", help="torch device of the exact path")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per method (min shown)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--data", help=argparse.SUPPRESS)
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="340 x 170 segments (4 x 2 images), d 32, k 10, shards of 170, one repeat, CPU",
    )
    args = parser.parse_args()
    if args.smoke:
        # A process's imports (~1.4 s) cost more than these sizes: every method runs in
        # one process.
        args.ref_segments, args.query_segments, args.dim, args.k = 340, 170, 32, 10
        args.shard, args.repeat, args.device = 170, 1, "cpu"
    if args.worker:
        for method in args.worker.split(","):
            worker(method, Path(args.data), args)
        return

    sys.path.insert(0, str(SRC))
    from vprflow.search.topk import topk_agreement

    with tempfile.TemporaryDirectory(prefix="bench_retrieval_") as tmp:
        folder = Path(tmp)
        write_unit_vectors(folder / "database.npy", args.ref_segments, args.dim, args.seed)
        write_unit_vectors(folder / "queries.npy", args.query_segments, args.dim, args.seed + 1)
        methods = ["faiss_flat", "bf16_floor", "exact_bf16", "exact_float32"]
        if args.old_exact and load_old_exact(args.old_exact) is not None:
            methods.insert(2, "exact_old")
        if args.shard:
            methods.append("exact_sharded")
        groups = [methods] if args.smoke else [[method] for method in methods]
        reports = {m: r for group in groups for m, r in run_methods(group, folder, args).items()}

    n_query = -(-args.query_segments // SEGMENTS_PER_IMAGE)
    n_ref = -(-args.ref_segments // SEGMENTS_PER_IMAGE)
    reference = reports["faiss_flat"]
    ranking, vote_seconds = voted(reference, n_query, n_ref, args)
    ranking_exact, _ = voted(reports["exact_bf16"], n_query, n_ref, args)

    print(
        f"\n{args.ref_segments:,} reference x {args.query_segments:,} query segments, "
        f"d {args.dim}, k {args.k}; {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cpus, {reference['torch']}, exact path on {args.device}), "
        f"{reference['faiss']}\n"
    )
    header = f"{'method':<34}{'time s':>9}{'/ faiss':>9}{'/ floor':>9}{'cpu s':>9}{'/ faiss':>9}"
    header += f"{'agree@k':>10}{'search MiB':>12}{'peak MiB':>10}  notes"
    print(header)
    print("-" * len(header))
    names = {
        "faiss_flat": "faiss IndexFlatL2",
        "bf16_floor": "bf16 products alone (floor)",
        "exact_old": f"exact_knn bf16, before ({args.old_exact})",
        "exact_bf16": "exact_knn, bf16 candidates",
        "exact_float32": "exact_knn, float32 candidates",
        "exact_sharded": f"exact_knn bf16, shards of {args.shard:,}",
    }
    floor = reports["bf16_floor"]
    for method, report in reports.items():
        seconds = report["seconds"]
        notes = f"median {report['median']:.2f} s"
        agreement = "-"
        if "indices" in report:
            agreement = f"{topk_agreement(report['indices'], reference['indices']):.5f}"
        stats = report["stats"]
        if stats:
            per_row = stats["rescored"] / args.query_segments
            notes += f"; {per_row:.0f} re-scored/query, {stats['widened']} rows widened"
        if method.startswith("exact") and method != "exact_old":
            same_lists = np.mean(np.all(report["indices"] == reference["indices"], axis=1))
            same_sets = np.mean(
                np.all(np.sort(report["indices"], 1) == np.sort(reference["indices"], 1), 1)
            )
            gap = np.abs(report["distances"] - reference["distances"]).max()
            notes += f"; lists equal to faiss {same_lists:.2%} (as sets {same_sets:.2%})"
            notes += f", max |d - faiss d| {gap:.1e}"
        if method == "exact_bf16" and "exact_old" in reports:
            old = reports["exact_old"]
            same = np.array_equal(report["distances"], old["distances"]) and np.array_equal(
                report["indices"], old["indices"]
            )
            notes += "; identical to before" if same else "; DIFFERS from before"
        cpu = report["cpu_seconds"]
        print(
            f"{names[method]:<34}{seconds:>9.2f}{seconds / reference['seconds']:>9.2f}"
            f"{seconds / floor['seconds']:>9.2f}{cpu:>9.2f}{cpu / reference['cpu_seconds']:>9.2f}"
            f"{agreement:>10}{report['search_mib']:>12.0f}{report['peak_mib']:>10.0f}  {notes}"
        )
    same = float(np.mean(np.all(ranking == ranking_exact, axis=1)))
    print(
        f"{'vote_ranking (faiss lists)':<34}{vote_seconds:>9.2f}{'':>68}  {n_query:,} x "
        f"{n_ref:,} images, top {VOTE_TOP}; {same:.2%} of rankings equal with exact bf16 lists"
    )


if __name__ == "__main__":
    main()
