"""What labelling ahead adds to `kestimator-compat post-process` (issue 49 item 1).

Under Moonraker's metadata run with object processing on, post-process also starts
Moonraker's own labelling on a copy of the upload (idle CPU time only) and moves its table
to where the labels will put its lines (kestimator/moonraker_labels.py). The target: at
most 1.5 times a plain post-process of the same file. This runs both, alternately, each in a
fresh process (`compat.main` with the labelling that Moonraker's metadata run would give,
built from a Moonraker install's Python and metadata.py), and prints the wall and CPU
seconds (ours and our children's) of each and whether the table was made for the labelled
file.

    python3 benchmarks/moonraker_prelabel.py --moonraker-python PY FILE [--runs N]

PY: a Python with PyPI `moonraker` (0.11) installed. FILE: a G-code file with PrusaSlicer
object labels (`; printing object`).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORPUS_CFG = os.path.join(os.path.dirname(ROOT), "shared", "corpus", "printer.cfg")


def _metadata_script(python: str) -> str:
    found = subprocess.run(
        [python, "-c", "import moonraker.components.file_manager.metadata as m; "
                       "print(m.__file__)"], capture_output=True, text=True, check=True)
    return found.stdout.strip()


def one(mode: str, python: str, source: str, work: str) -> dict[str, object]:
    """One post-process of a fresh copy of `source` in this process."""
    sys.path.insert(0, ROOT)
    from kestimator import compat
    from kestimator.config.klipper_estimator import dump_config
    from kestimator.config.resolve import LimitRequest, resolve_limits
    from kestimator.moonraker_labels import Labeller

    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    config = os.path.join(work, "estimator.json")
    with open(config, "w") as f:
        json.dump(dump_config(machine.limits, machine.sources), f)
    path = os.path.join(work, os.path.basename(source))
    shutil.copyfile(source, path)
    labeller = Labeller(python, _metadata_script(python), 600.0, 600.0, 0.0)
    def labelling(pid: int | None = None) -> Labeller | None:
        return labeller if mode == "ahead" else None

    compat.moonraker_labeller = labelling
    compat.run_started = time.monotonic  # the copy above is not the post-process's
    said = open(os.path.join(work, "said"), "w")
    saved = sys.stdout, sys.stderr
    sys.stdout = sys.stderr = said
    wall = time.monotonic()
    status = compat.main(["--config_file", config, "post-process", path])
    wall = time.monotonic() - wall
    sys.stdout, sys.stderr = saved
    said.close()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(os.path.join(work, "said")) as f:
        text = f.read()
    return {"mode": mode, "status": status, "wall_s": wall,
            "cpu_s": usage.ru_utime + usage.ru_stime,
            "children_cpu_s": children.ru_utime + children.ru_stime,
            "labelled": "table made for the file as Moonraker labels its objects" in text}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--moonraker-python", required=True)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--one", choices=("plain", "ahead"), help=argparse.SUPPRESS)
    ap.add_argument("--work", help=argparse.SUPPRESS)
    ap.add_argument("file")
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.moonraker_python, args.file, args.work)))
        return
    best: dict[str, float] = {}
    for _ in range(args.runs):
        for mode in ("plain", "ahead"):
            work = tempfile.mkdtemp(prefix="kestimator-bench-")
            try:
                done = subprocess.run(
                    [sys.executable, os.path.abspath(__file__), "--one", mode,
                     "--moonraker-python", args.moonraker_python, "--work", work, args.file],
                    capture_output=True, text=True, check=True)
            finally:
                shutil.rmtree(work, ignore_errors=True)
            row = json.loads(done.stdout.strip().splitlines()[-1])
            best[mode] = min(best.get(mode, float("inf")), float(row["wall_s"]))
            print("%-5s wall %.2f s, cpu %.2f s (+ children %.2f s)%s" % (
                mode, row["wall_s"], row["cpu_s"], row["children_cpu_s"],
                ", table for the labelled file" if row["labelled"] else ""), flush=True)
    print("least wall: plain %.2f s, ahead %.2f s: %.2fx"
          % (best["plain"], best["ahead"], best["ahead"] / best["plain"]))


if __name__ == "__main__":
    main()
