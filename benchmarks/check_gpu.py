"""Checks and timings on a CUDA GPU, for what CPU-only CI cannot run.

    python benchmarks/check_gpu.py                 # A, B and C at the city's size
    python benchmarks/check_gpu.py AB              # the checks alone
    python benchmarks/check_gpu.py D               # the matches stage's pairs, timed
    python benchmarks/check_gpu.py C 316000 215400 3328   # references, queries, dim

A: re-ranking on CUDA: the stages' scores (``candidate_pairs``, then ``pair_scorer``)
   against per-candidate products on the same device, for mnn (count, similarity, a
   threshold) and ransac, at bench_rerank.py's cases (K = 100); and how many candidates
   score the same on the CPU.
B: ``exact_knn`` on CUDA against float64 brute force (the tests' check), several blocks
   each way, bf16 and float32 candidates, random and clustered data; and against the CPU.
D: the ``matches`` stage's pairs (``candidate_pairs``: one product per group of
   candidates, the pairs read on the device) at bench_rerank.py's grids and the published
   SegVLAD's, timed against one product per candidate and against the products alone
   (``x fp32``), with the scoring of the stored pairs; how many candidates' pairs and
   similarities equal the per-candidate products' on CUDA and the CPU's.
C: ``exact_knn`` on CUDA at the segment search of a Pittsburgh-30k-size run
   (``bench_city.py``'s 31.6 SLIC segments an image: 316,000 reference x 215,400 query
   segments of SegVLAD's 3,328-d without PCA) beside its bf16 floor.

Exits 77 without CUDA. On a machine reached without git, copy the repository's
``src``, ``benchmarks`` and ``tests`` (``git archive HEAD src benchmarks tests``).
"""

import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))

from bench_rerank import CASES, inputs  # noqa: E402
from knn_helpers import check_against_float64, clustered, unit_vectors  # noqa: E402

from vprflow.evaluation import rerank as rr  # noqa: E402
from vprflow.evaluation.rerank import reranker  # noqa: E402
from vprflow.search.exact import exact_knn  # noqa: E402

if not torch.cuda.is_available():
    print("no CUDA device", file=sys.stderr)
    sys.exit(77)
part = sys.argv[1] if len(sys.argv) > 1 else "ABC"
if "C" in part and len(sys.argv) < 5:
    sys.argv[2:] = ["316000", "215400", "3328"]
dev = torch.device("cuda")
print(
    "#",
    torch.__version__,
    torch.cuda.get_device_name(),
    "tf32",
    torch.backends.cuda.matmul.allow_tf32,
    torch.get_float32_matmul_precision(),
    flush=True,
)


def per_candidate(q, c, method, settings, centres, patch):
    out = np.zeros(len(c))
    for k in range(len(c)):
        i, j, s = rr.mutual_nearest_neighbours(q, c[k])
        kept = rr._kept(s, settings.get("min_similarity"))
        if method == "mnn":
            out[k] = (
                len(i[kept])
                if settings["weighting"] == "count"
                else float(s[kept].astype(np.float64).sum())
            )
        else:
            o = {x: settings[x] for x in ("seed", "model", "max_iters", "confidence")}
            out[k] = rr.ransac_inliers(
                centres[i[kept]], centres[j[kept]], settings["threshold"] * patch, **o
            )
    return out


if "A" in part:
    print("\n## A: re-ranking on CUDA: the stages' == per-candidate on the same device", flush=True)
    print("| case | reranker | settings | stages' equal | cpu == cuda |")
    print("|---|---|---|---|---|")
    for name, (h, w, dim, patch) in CASES.items():
        qn, cn = inputs(h, w, dim, 100, seed=1)
        q = torch.from_numpy(qn).to(dev)
        c = torch.from_numpy(cn)
        centres = rr.patch_centres(h, w, patch)
        for method, extra in (
            ("mnn", {}),
            ("mnn", {"weighting": "similarity"}),
            ("mnn", {"min_similarity": 0.5}),
            ("ransac", {}),
        ):
            settings = reranker(method).settings(extra)
            score = rr.pair_scorer(method, extra, (h, w), patch)
            ref = per_candidate(q, c, method, settings, centres, patch)
            after = score(rr.candidate_pairs(q, c))
            cpu = score(rr.candidate_pairs(torch.from_numpy(qn), c))
            print(
                f"| {name} | {method} | {extra or 'default'} | {np.array_equal(ref, after)} | "
                f"{int((cpu == after).sum())}/100 |",
                flush=True,
            )

if "B" in part:
    print("\n## B: exact_knn on CUDA against float64", flush=True)
    rng = np.random.default_rng(5)
    for dtype in ("bfloat16", "float32"):
        for data in ("random", "clustered"):
            if data == "random":
                db, qs = unit_vectors(rng, 20000, 96), unit_vectors(rng, 200, 96)
            else:
                centres = unit_vectors(rng, 40, 96)
                db, qs = clustered(rng, 20000, 96, centres), clustered(rng, 200, 96, centres)
            d, i = exact_knn(
                db,
                qs,
                50,
                device="cuda",
                candidate_dtype=dtype,
                block_database=4096,
                block_queries=64,
            )
            clear = check_against_float64(d, i, db, qs, 50)
            dc, ic = exact_knn(
                db,
                qs,
                50,
                device="cpu",
                candidate_dtype=dtype,
                block_database=4096,
                block_queries=64,
            )
            print(
                f"- {dtype} {data}: float64 check passed ({clear.mean():.0%} rows with a clear "
                f"k-th gap); cuda == cpu indices {np.array_equal(i, ic)}, "
                f"distances max diff {np.abs(d - dc).max():.2e}",
                flush=True,
            )

if "D" in part:
    print("\n## D: the matches stage's pairs on CUDA (K = 100, ms a query, fastest of 5)")
    print(
        "| case | per candidate | candidate_pairs | x fp32 | + mnn scoring | + ransac scoring | "
        "pairs == per-candidate | == CPU's | similarity max diff to CPU |"
    )
    print("|---|---:|---:|---:|---:|---:|---|---|---:|")

    def best(call, n=5):
        call()
        torch.cuda.synchronize()
        times = []
        for _ in range(n):
            started = time.perf_counter()
            call()
            torch.cuda.synchronize()
            times.append(time.perf_counter() - started)
        return 1000 * min(times)

    def same(a, b):
        return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))

    # The published SegVLAD's grid (DINOv2 ViT-G/14 at 640 x 480: 34 x 45 patches of 1,536)
    # beside bench_rerank.py's.
    for name, (h, w, dim, patch) in {**CASES, "dinov2_g_640x480": (34, 45, 1536, 14)}.items():
        qn, cn = inputs(h, w, dim, 100, seed=0)
        # As the stage holds them: the query and the candidates on the device.
        q, c = torch.from_numpy(qn).to(dev), torch.from_numpy(cn).to(dev)
        centres = rr.patch_centres(h, w, patch)
        mnn, ransac = reranker("mnn").settings({}), reranker("ransac").settings({})
        pairs = rr.candidate_pairs(q, c)
        alone = [rr.mutual_nearest_neighbours(q, c[k]) for k in range(len(c))]
        on_cpu = rr.candidate_pairs(torch.from_numpy(qn), torch.from_numpy(cn))
        equal = sum(same(a, b) for a, b in zip(pairs, alone, strict=True))
        equal_cpu = sum(same(a, b) for a, b in zip(pairs, on_cpu, strict=True))
        diff = max(
            (
                float(np.abs(a[2] - b[2]).max())
                for a, b in zip(pairs, on_cpu, strict=True)
                if len(a[2]) and np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
            ),
            default=0.0,
        )
        flat = c.reshape(-1, dim)
        step = max(1, rr._product_elements(dev) // (h * w) ** 2) * h * w
        ms = (
            best(lambda: [rr.mutual_nearest_neighbours(q, c[k]) for k in range(len(c))], 2),  # noqa: B023
            best(lambda: rr.candidate_pairs(q, c)),  # noqa: B023
            best(lambda: [q @ flat[s : s + step].T for s in range(0, len(flat), step)]),  # noqa: B023
            best(lambda: rr.mnn_pair_scores(pairs, centres, patch, **mnn)),  # noqa: B023
            best(lambda: rr.ransac_pair_scores(pairs, centres, patch, **ransac), 2),  # noqa: B023
        )
        print(
            f"| {name} | {ms[0]:.1f} | {ms[1]:.1f} | {ms[1] / ms[2]:.2f} | {ms[3]:.1f} | "
            f"{ms[4]:.1f} | {equal}/100 | {equal_cpu}/100 | {diff:.1e} |",
            flush=True,
        )

if "C" in part:
    n_ref, n_q, dim, k = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), 50
    print(f"\n## C: exact_knn on CUDA, {n_ref:,} x {n_q:,} x {dim}, k {k}", flush=True)
    g = torch.Generator(device=dev).manual_seed(0)

    def unit(n):
        out = np.empty((n, dim), np.float32)
        for s in range(0, n, 32768):
            x = torch.randn(min(32768, n - s), dim, device=dev, generator=g)
            out[s : s + len(x)] = torch.nn.functional.normalize(x, dim=1).cpu().numpy()
        return out

    t = time.perf_counter()
    db, qs = unit(n_ref), unit(n_q)
    print(f"- data made in {time.perf_counter() - t:.1f} s", flush=True)
    exact_knn(db[:70000], qs[:5000], k, device="cuda")  # warm-up
    torch.cuda.synchronize()
    for dtype in ("bfloat16", "float32"):
        stats = {}
        t = time.perf_counter()
        d, i = exact_knn(db, qs, k, device="cuda", candidate_dtype=dtype, stats=stats)
        torch.cuda.synchronize()
        print(f"- exact_knn {dtype}: {time.perf_counter() - t:.2f} s, stats {stats}", flush=True)
    # bf16 floor: every block's product alone, inputs already on the GPU.
    dbg = torch.from_numpy(db).to(dev, torch.bfloat16)
    qg = torch.from_numpy(qs).to(dev, torch.bfloat16)
    for _ in range(2):
        torch.cuda.synchronize()
        t = time.perf_counter()
        for s in range(0, n_q, 4096):
            for r in range(0, n_ref, 65536):
                qg[s : s + 4096] @ dbg[r : r + 65536].T
        torch.cuda.synchronize()
        floor = time.perf_counter() - t
    print(
        f"- bf16 floor (products alone, on the GPU): {floor:.2f} s; "
        f"{2 * n_ref * n_q * dim / floor / 1e12:.0f} TFLOP/s",
        flush=True,
    )
    dbf = torch.from_numpy(db).to(dev)
    qf = torch.from_numpy(qs).to(dev)
    torch.cuda.synchronize()
    t = time.perf_counter()
    for s in range(0, n_q, 4096):
        qf[s : s + 4096] @ dbf[0:65536].T
    torch.cuda.synchronize()
    f32 = (time.perf_counter() - t) * ((n_ref + 65535) // 65536)
    print(f"- float32 floor (one database block, scaled): {f32:.2f} s", flush=True)
