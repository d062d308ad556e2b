#!/usr/bin/env python3
"""Cost exponents from a beampack-bench JSON file: for each benchmark family measured at several
sizes N, the least-squares slope of log(time) against log(N) (1 = linear).

    ./build/beampack-bench --benchmark_out=bench.json --benchmark_out_format=json
    scripts/bench_report.py bench.json            # prints a Markdown table
"""
import json
import math
import sys
from collections import defaultdict


def family_and_size(name):
    """The size N is the first numeric argument. A second one is a ray count (trace/): 10000
    stays in the family's name; any other is the paper's resolution, which grows with N."""
    parts = [p for p in name.split("/") if not p.startswith(("real_time", "min_time", "repeats",
                                                            "iterations"))]
    sizes = [i for i, p in enumerate(parts) if p.isdigit()]
    if not sizes:
        return None, None
    i = sizes[0]
    rest = [("rays=1e4" if p == "10000" else "rays=paper") if p.isdigit() else p
            for p in parts[i + 1:]]
    return "/".join(parts[:i] + rest), int(parts[i])


def slope(points):
    xs = [math.log(n) for n, _ in points]
    ys = [math.log(t) for _, t in points]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx if sxx > 0 else float("nan")


def main(path):
    data = json.load(open(path))
    series = defaultdict(dict)
    for b in data["benchmarks"]:
        if b.get("run_type") == "aggregate" and b.get("aggregate_name") != "median":
            continue
        family, n = family_and_size(b["run_name"] if "run_name" in b else b["name"])
        if family is None:
            continue
        series[family][n] = (b["real_time"], b.get("time_unit", "ns"))
    print("| benchmark family | N range | time at largest N | exponent |")
    print("|---|---|---|---|")
    for family in sorted(series):
        points = sorted(series[family].items())
        if len(points) < 2:
            continue
        last_time, unit = points[-1][1]
        times = [(n, t) for n, (t, _) in points]
        print(f"| {family} | {points[0][0]:.0e} .. {points[-1][0]:.0e} | "
              f"{last_time:.4g} {unit} | {slope(times):.2f} |")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "bench.json")
