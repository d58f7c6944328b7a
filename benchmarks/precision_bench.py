"""Training-step and query-time micro-benchmark of the regressor, fp32 vs bf16, on this CPU and
on this CPU restricted to AVX2 (ONEDNN_MAX_CPU_ISA=AVX2, ATEN_CPU_CAPABILITY=avx2), and on an AMX
CPU with AMX off (ONEDNN_MAX_CPU_ISA=AVX512_CORE_BF16: an AVX512-BF16 CPU's kernels), each in a
fresh process because these variables are read when torch loads.

    python benchmarks/precision_bench.py [--threads 1] [--arch wide]

Prints a markdown table: median ms per training step (batch 1024, region head, AdamW) and per
query batch (1536 descriptors, padded as the localizer pads), and what `auto` picks for each.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

AVX2 = {"ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"}
# oneDNN without AMX: on an AMX CPU, an AVX512-BF16 CPU's kernels (elsewhere no change)
NO_AMX = {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_BF16"}


def measure(arch: str, threads: int, repeats: int = 15) -> dict:
    import torch

    from slamreloc.runtime.precision import autocast, bf16_support, resolve_precision
    from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = SceneCoordinateRegressor(RegressorConfig.preset(arch, 128))
    k = max(len(model.centres), 1)
    opt = torch.optim.AdamW(model.parameters(), 1e-3)
    x, y = torch.randn(1024, 128), torch.randn(1024, 3)
    target = torch.randint(0, k, (1024,))
    query = torch.randn(1536, 128)
    logits_head = model.config.head == "clusters"

    def train_step(precision: str) -> None:
        with autocast("cpu", precision):
            hidden = model.hidden(x)
        pred, logits = model.head_outputs(hidden, target if logits_head else None)
        loss = (pred - y).norm(dim=1).mean()
        if logits is not None:
            loss = loss + torch.nn.functional.cross_entropy(logits, target)
        opt.zero_grad()
        loss.backward()
        opt.step()

    def query_step(precision: str) -> None:
        with torch.inference_mode(), autocast("cpu", precision):
            model.predict(query)

    sizes = torch.randint(500, 1600, (repeats,), generator=torch.Generator().manual_seed(0))

    def varying(precision: str, pad: bool) -> float:
        """Median ms over queries of varying keypoint counts, padded as the localizer pads."""
        times = []
        for n in sizes.tolist():
            q = torch.randn(n + ((-n) % 256 if pad else 0), 128)
            t0 = time.perf_counter()
            with torch.inference_mode(), autocast("cpu", precision):
                model.predict(q)
            times.append(time.perf_counter() - t0)
        return 1000 * sorted(times)[len(times) // 2]

    out = {"auto": resolve_precision("auto", "cpu"), "reason": bf16_support("cpu")[1],
           "auto_query": resolve_precision("auto", "cpu", use="query")}
    for name, fn in (("train", train_step), ("query", query_step)):
        for precision in ("fp32", "bf16"):
            for _ in range(2):
                fn(precision)
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                fn(precision)
                times.append(time.perf_counter() - t0)
            out[f"{name}_{precision}_ms"] = 1000 * sorted(times)[len(times) // 2]
    auto = out["auto_query"]
    varying(auto, True)  # warm-up
    out["varying_padded_ms"], out["varying_unpadded_ms"] = varying(auto, True), varying(auto, False)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--arch", default="wide")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.arch, args.threads)))
        return
    print(f"arch {args.arch}, {args.threads} thread(s); ms per training step (batch 1024) / "
          "per query (1536 descriptors), medians\n")
    print("| CPU as seen by torch | auto picks: train / query | train fp32 | train bf16 | "
          "query fp32 | query bf16 | varying sizes, query auto: padded / unpadded |")
    print("|---|---|---|---|---|---|---|")
    for label, env in (("native", {}), ("no AMX", NO_AMX), ("restricted to AVX2", AVX2)):
        res = subprocess.run([sys.executable, __file__, "--child", "--threads",
                              str(args.threads), "--arch", args.arch],
                             env={**os.environ, **env}, capture_output=True, text=True, check=True)
        r = json.loads(res.stdout)
        print(f"| {label} ({r['reason']}) | {r['auto']} / {r['auto_query']} | "
              f"{r['train_fp32_ms']:.0f} | "
              f"{r['train_bf16_ms']:.0f} | {r['query_fp32_ms']:.1f} | {r['query_bf16_ms']:.1f} | "
              f"{r['varying_padded_ms']:.1f} / {r['varying_unpadded_ms']:.1f} |")


if __name__ == "__main__":
    main()
