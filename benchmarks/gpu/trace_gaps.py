"""Where the GPU waits for the host: the idle gaps of a profiled run's GPU timeline, attributed to
the Python frames the host thread was in during each gap.

Reads a Chrome trace written with Python stacks (``python -m benchmarks.edit ... --profile-steps N
--profile-trace trace.json``, optionally gzipped). The steps are the host ranges whose name
contains ``--step-name`` (``step_once``: the edit loop); the first one is left out (it pays for
the loop's setup). Each gap between GPU activities (kernels, copies, memsets) longer than
``--min-us`` inside the other steps goes to the first of ``--keys`` found among the frames active
on the main thread at its midpoint ("other" when none is). Prints idle milliseconds per step by
key, then the largest gaps with their innermost frames.

    python -m benchmarks.gpu.trace_gaps trace.json.gz
    python -m benchmarks.gpu.trace_gaps trace.json.gz --keys camera_conditions,bin_gaussians --largest 20
"""
from __future__ import annotations

import argparse
import collections
import gzip
import json
from pathlib import Path

from benchmarks.common import gpu_timeline

GPU_CATS = ("kernel", "gpu_memcpy", "gpu_memset")
HOST_CATS = ("python_function", "cpu_op")
DEFAULT_KEYS = ("camera_conditions", "condition_latents", "_pool_set", "check_render_values", "bin_gaussians",
                "checked_sizes", "_signature", "sample", "render_views", "csd.py", "ip2p.py", "mvdream.py",
                "backward", "update", "densify", "step_once")


def load_events(path: Path) -> list[dict]:
    """The complete ('X') events of a Chrome trace file (.json or .json.gz)."""
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    return [e for e in events if e.get("ph") == "X" and "dur" in e]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trace", type=Path)
    ap.add_argument("--step-name", default="step_once", help="host range that marks one step")
    ap.add_argument("--min-us", type=float, default=5.0, help="shortest gap counted (µs)")
    ap.add_argument("--keys", default=",".join(DEFAULT_KEYS),
                    help="comma-separated frame substrings, first match wins")
    ap.add_argument("--largest", type=int, default=10, help="list this many of the largest gaps")
    args = ap.parse_args()

    events = load_events(args.trace)
    gpu = [e for e in events if e.get("cat") in GPU_CATS]
    host = [e for e in events if e.get("cat") in HOST_CATS]
    steps = sorted((e for e in host if args.step_name in e["name"]), key=lambda e: e["ts"])
    if len(steps) < 2:
        raise SystemExit(f"trace_gaps: fewer than 2 '{args.step_name}' ranges in {args.trace} "
                         "(was it written with --profile-trace, i.e. with Python stacks?)")
    main_tid = steps[0]["tid"]
    frames = sorted((e for e in host if e["tid"] == main_tid), key=lambda e: e["ts"])
    lo, hi = steps[1]["ts"], steps[-1]["ts"] + steps[-1]["dur"]
    keys = [k for k in args.keys.split(",") if k]
    per_key: collections.Counter = collections.Counter()
    listed = []
    for a, b, _, _ in gpu_timeline(((e["ts"], e["ts"] + e["dur"], e["name"]) for e in gpu), args.min_us)[1]:
        if not lo <= a <= hi:
            continue
        mid = (a + b) / 2
        active = [e for e in frames if e["ts"] <= mid <= e["ts"] + e["dur"]]
        names = [e["name"] for e in active]
        key = next((k for k in keys if any(k in n for n in names)), "other")
        per_key[key] += b - a
        listed.append((b - a, [n.split(" of ")[0][:80] for n in names[-5:]]))
    n = len(steps) - 1
    print(f"{n} steps, {(hi - lo) / n / 1e3:.2f} ms of wall time per step; GPU idle per step by host frame:")
    for key, us in per_key.most_common():
        print(f"  {us / n / 1e3:8.3f} ms  {key}")
    print(f"  {sum(per_key.values()) / n / 1e3:8.3f} ms  total")
    print(f"the {args.largest} largest gaps (ms, innermost frames last):")
    for us, names in sorted(listed, key=lambda g: -g[0])[:args.largest]:
        print(f"  {us / 1e3:7.3f}  {' > '.join(names)}")


if __name__ == "__main__":
    main()
