#!/usr/bin/env python3
"""Compares helmholtz-bench reports of two builds (e.g. before and after a refactor).

Usage:
    python3 bench/tools/compare_runs.py PRESET OLD_DIR [OLD_DIR...] -- NEW_DIR [NEW_DIR...]

Each DIR holds DIR/benchmarks-PRESET.json (benchmarks.json for --preset full) written by one run
of `helmholtz-bench --preset PRESET --out DIR`. Run the two binaries interleaved (old, new, old,
new, ...) so that the machine's drift lands on both. Prints the largest PSNR difference over all
cases (raw and after the affine fit; the numerics are deterministic, so an unchanged build gives
0), the cases that differ by more than 0.01 dB, and the best-of-runs time per case, new / old.
Exits 1 if any PSNR differs by more than 0.01 dB.
"""
import json
import statistics
import sys


def load(directory, preset):
    name = "benchmarks.json" if preset == "full" else f"benchmarks-{preset}.json"
    with open(f"{directory}/{name}") as f:
        results = json.load(f)["results"]
    return {json.dumps(r["case"], sort_keys=True): r for r in results}


def main():
    args = sys.argv[1:]
    if len(args) < 4 or "--" not in args:
        print(__doc__)
        return 2
    preset, rest = args[0], args[1:]
    cut = rest.index("--")
    old = [load(d, preset) for d in rest[:cut]]
    new = [load(d, preset) for d in rest[cut + 1:]]
    worst, over, ratios = 0.0, [], []
    for key, first in old[0].items():
        other = new[0][key]
        for field in ("psnr_db", "psnr_fitted_db"):
            a, b = first.get(field), other.get(field)
            if isinstance(a, (int, float)) and isinstance(b, (int, float)):
                worst = max(worst, abs(a - b))
                if abs(a - b) > 0.01:
                    over.append((key, field, a, b))
            elif a != b:
                over.append((key, field, a, b))
        t_old = min(run[key]["seconds"] for run in old)
        t_new = min(run[key]["seconds"] for run in new)
        if t_old > 0.01:
            ratios.append((t_new / t_old, key))
    print(f"{len(old[0])} cases; largest |PSNR difference| {worst:.3g} dB; {len(over)} over 0.01 dB")
    for case in over:
        print("  differs:", *case)
    if ratios:
        r = [x for x, _ in ratios]
        print(f"time new/old, best of {len(old)} vs {len(new)} runs, {len(r)} cases over 10 ms: "
              f"median {statistics.median(r):.3f}, min {min(r):.3f}, max {max(r):.3f}")
    return 1 if over else 0


if __name__ == "__main__":
    sys.exit(main())
