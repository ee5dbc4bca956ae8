"""``tiger edit`` end to end, as a user runs it, and where its wall time goes: imports, the scene
and the retrieval (CLIP), the diffusion models (loaded beside them), the optimisation (its graph
captures included), and the outputs (pictures, video, metrics). Runs the command in this process
with time-stamped log lines and reads its ``edit.json``.

    python -m benchmarks.edit_command SCENE "make it look like a tiger" --target fox --out OUT --device cuda

Every argument after the module goes to ``tiger edit`` unchanged (its defaults are the product's).
Raw figures: ``benchmarks/gpu/results/edit_command_fox_h100.txt`` (H100, the fox of
``benchmarks/gpu/default_commands.sh``'s QUICK run, full-size random models in their real formats).
"""
from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path

T0 = time.perf_counter()


class _Marks(logging.Handler):
    """Seconds since the start at which the log lines that end each phase were written."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.marks: dict[str, float] = {}

    def emit(self, record: logging.LogRecord) -> None:
        msg = record.getMessage()
        for key, start in (("retrieval", "retrieval:"), ("loop_start", "edit '")):
            if msg.startswith(start) and key not in self.marks:
                self.marks[key] = time.perf_counter() - T0
        if msg.startswith("captured a CUDA graph"):  # the last one ends the first steps' warm-up
            self.marks["captured"] = time.perf_counter() - T0


def phases(marks: dict[str, float], imported: float, report: dict, total: float) -> dict[str, float]:
    """Wall seconds per phase from the marks and the command's ``edit.json``."""
    loop_start = marks.get("loop_start", float("nan"))
    loop = float(report["time_s"])
    return {"imports": imported, "scene + CLIP + retrieval": marks.get("retrieval", float("nan")) - imported,
            "models (loaded beside) and setup": loop_start - marks.get("retrieval", float("nan")),
            "optimisation (edit.json time_s)": loop, "outputs and metrics": total - loop_start - loop,
            "total": total}


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if "--out" not in args:
        raise SystemExit("benchmarks.edit_command: pass --out (the edit's folder; edit.json is read from it)")
    out = Path(args[args.index("--out") + 1])
    handler = _Marks()
    logging.basicConfig(level=logging.INFO, format="%(relativeCreated)7.0f ms %(threadName)s %(name)s: %(message)s")
    logging.getLogger().addHandler(handler)
    from tiger.cli.main import main as tiger_main

    imported = time.perf_counter() - T0
    rc = tiger_main(["edit", *args])
    total = time.perf_counter() - T0
    if rc != 0:
        print(f"tiger edit exited {rc} after {total:.1f} s")
        return rc
    report = json.loads((out / "edit.json").read_text())
    print("\n`tiger edit` wall time by phase (s):")
    for name, s in phases(handler.marks, imported, report, total).items():
        print(f"  {name:34s} {s:7.2f}")
    if "captured" in handler.marks and "loop_start" in handler.marks:
        # H100 (edit_command_fox_h100.txt): 1.9 s on a machine that had run the models before, 7.1 s on a fresh one
        print(f"  of the optimisation, loop start to the last CUDA-graph capture: "
              f"{handler.marks['captured'] - handler.marks['loop_start']:.2f} s")
    print("stage times of the optimisation (s):", json.dumps({k: round(v, 2) for k, v in report["stage_times_s"].items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
