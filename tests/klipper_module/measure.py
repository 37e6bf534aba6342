"""Print the numbers plugins/klipper/README.md gives: the module in real Klipper on the
cases tests/test_klipper_module_real.py checks, as a Markdown table (worst error against
Klipper's own remaining time, waits, longest reactor callback, memory).

    python3 tests/klipper_module/measure.py [--big]    (--big adds the 40 MB corpus file)
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "exclude_refs"))
import run_print  # noqa: E402
import test_klipper_module_real as real  # noqa: E402

BIG = "prusaslicer/ps25_bunny120_fast_fwretract_large.gcode"


def row(name: str, result: dict[str, Any], after_change: bool) -> str:
    samples = result["samples"]
    if after_change:
        user = result["users"][0]
        change_t = next(s["print_time"] for s in samples if s["position"] >= user["position"])
        samples = [s for s in samples if s["print_time"] >= change_t]
    worst = max(samples, key=lambda s: abs(s["error_s"]))
    user = result["users"][0] if result["users"] else None
    return "| %s | %d | %.3f s at %.0f s left | %s | %.2f s | %.2f ms | %.0f KiB | %.0f MiB |" % (
        name, len(samples), abs(worst["error_s"]), worst["truth_s"],
        "%.2f s" % user["answer_wait_s"] if user else "-", result["start_wait_s"],
        result["max_callback_ms"], result["table_bytes"] / 1024.,
        result["memory_kib"]["worker"].get("VmHWM", 0) / 1024.)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--big", action="store_true")
    args = ap.parse_args()
    print("| case | samples | worst error | answer to the change | start | longest "
          "callback | table | worker peak |")
    print("|---|---|---|---|---|---|---|---|")
    corpus = real.CORPUS
    cases: list[tuple[str, Path, dict[str, Any], bool]] = []
    for slicer, rel in sorted(real.FILES.items()):
        cases.append(("%s plain" % slicer, corpus / rel, {}, False))
    for slicer in ("cura", "orcaslicer", "prusaslicer"):
        cases.append(("%s, inject's table" % slicer, corpus / real.FILES[slicer],
                      {"inject": True}, False))
    for slicer, rel in sorted(real.FILES.items()):
        for factor in (50, 150):
            cases.append(("%s, M220 S%d at 40 %%" % (slicer, factor), corpus / rel,
                          {"users": [(0.4, "M220 S%d" % factor)]}, True))
    if args.big:
        big = corpus / BIG
        cases += [("40 MB bunny plain", big, {"samples": 20}, False),
                  ("40 MB bunny, inject's table", big, {"samples": 20, "inject": True}, False),
                  ("40 MB bunny, M220 S150 at 50 %", big,
                   {"samples": 20, "users": [(0.5, "M220 S150")]}, True)]
    with tempfile.TemporaryDirectory() as tmp:
        for name, path, kw, changed in cases:
            work = os.path.join(tmp, str(len(os.listdir(tmp))))
            print(row(name, run_print.run_print(str(path), work, **kw), changed), flush=True)
        for slicer in sorted(real.LABELLED):
            labelled, names = real._labelled(Path(tmp), slicer)
            work = os.path.join(tmp, str(len(os.listdir(tmp))))
            result = run_print.run_print(str(labelled), work, users=[
                (0.45, "EXCLUDE_OBJECT NAME=%s" % names[-1])])
            print(row("%s, EXCLUDE_OBJECT at 45 %%" % slicer, result, True), flush=True)


if __name__ == "__main__":
    main()
