"""Print the numbers plugins/klipper/README.md gives for real-time prints: the cases of
tests/test_klipper_module_realtime.py (real Klipper at wall-clock speed with the module), as a
Markdown table: status cycles checked, the worst error of `remaining_s` against the time
Klipper then took, the worst of Mainsail's own estimate and ETA (its store code,
tests/frontends/), and the module's longest reactor callback. With --releases: the print of
each release (tests/test_klipper_module_realtime.py's RELEASES) instead, with
each print's wall time.

    python3 tests/klipper_module/measure_realtime.py [--releases]   (about 9 or 5 minutes)
"""
from __future__ import annotations

import argparse
import concurrent.futures
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "frontends"))
import frontends  # noqa: E402

from tests import test_klipper_module_realtime as rt  # noqa: E402
from tests.conftest import require_release  # noqa: E402


def row(name: str, result: dict[str, Any]) -> str:
    checked = rt._checked(result["samples"], result["typed"])
    worst = max(checked, key=lambda c: abs(c[0]["error_s"]))[0]
    ids = {id(s) for s, _, _ in checked}
    views = [v for s, v in zip(result["samples"], frontends.realtime_view(result))
             if id(s) in ids]
    mainsail = max(abs(v["mainsail_estimate_error_s"] or 0.) for v in views)
    eta = max(abs(v["mainsail_eta_left_error_s"] or 0.) for v in views)
    callback = max(float(s["status"].get("kestimator", {}).get("max_callback_ms") or 0.)
                   for s in result["samples"])
    typed = ", ".join(t["cmd"].split()[0] for t in result["typed"]) or "-"
    return "| %s | %s | %d | %.3f s at %.0f s left | %.2f s | %.2f s | %.2f ms |" % (
        name, typed, len(checked), abs(worst["error_s"]), worst["truth_s"], mainsail, eta,
        callback)


def _timed(release: str, work: Path) -> dict[str, Any]:
    tree, cfg = require_release(release)
    start = time.monotonic()
    result = rt._case_release(work, tree, cfg)
    result["wall_s"] = time.monotonic() - start
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--releases", action="store_true")
    args = ap.parse_args()
    print("| %s | typed | cycles checked | worst error | Mainsail estimate | Mainsail ETA "
          "| longest callback |%s" % ("release" if args.releases else "case",
                                      " wall |" if args.releases else ""))
    print("|---|---|---|---|---|---|---|%s" % ("---|" if args.releases else ""))
    with tempfile.TemporaryDirectory() as tmp, \
            concurrent.futures.ThreadPoolExecutor(max_workers=3) as pool:
        if args.releases:
            futures = {release: pool.submit(_timed, release, Path(tmp) / release)
                       for release in rt.RELEASES}
        else:
            futures = {name: pool.submit(case, Path(tmp) / name)
                       for name, case in rt.CASES.items()}
        for name, future in futures.items():
            result = future.result()
            wall = " %.0f s |" % result["wall_s"] if args.releases else ""
            print(row(name, result) + wall, flush=True)


if __name__ == "__main__":
    main()
