"""The Klipper module in a Klipper newer than it knows: a copy of the oracle's Klipper
84104bbbd tree in which a hook the module takes (KLIPPER_HOOKS in
plugins/klipper/kestimator/hooks.py) is renamed, everywhere Klipper itself uses it. A corpus
file prints there in batch mode (tests/klipper_module/run_print.py): Klipper finishes the
print, display_status is Klipper's own (never answered through the module), and the
module says once in klippy.log and in its status which hook is missing."""
from __future__ import annotations

import os
import re
import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "klipper_module"))
import run_print  # noqa: E402

from tests.conftest import require_klipper  # noqa: E402

FILE = Path(run_print.SHARED) / "corpus" / "gcode" / "prusaslicer" / \
    "ps25_nut_accelA_small.gcode"
# The hook as the module names it, and the rename made in Klipper's own sources.
RENAMES = {
    "gcode.run_script": (r"\brun_script\(", "run_script_text("),
    "toolhead.lookahead|move_queue.get_last": (r"\bget_last\(", "last_queued_move("),
}


def renamed_tree(klipper: str, dst: Path, pattern: str, replacement: str) -> str:
    """A copy of `klipper`'s klippy/ (its built chelper with it; out/ linked) under `dst`,
    with `pattern` replaced in every Python file: as an upstream rename would be."""
    shutil.copytree(os.path.join(klipper, "klippy"), dst / "klippy", symlinks=True)
    os.symlink(os.path.join(klipper, "out"), dst / "out")
    changed = 0
    for path in (dst / "klippy").rglob("*.py"):
        if path.is_symlink():
            continue
        text = path.read_text()
        new, n = re.subn(pattern, replacement, text)
        if n:
            stat = path.stat()
            path.write_text(new)
            # Keep the mtime: chelper rebuilds when its sources look newer than its library.
            os.utime(path, (stat.st_atime, stat.st_mtime))
            changed += n
    assert changed >= 2, "the rename found nothing to rename"
    return str(dst)


@pytest.mark.parametrize("hook", sorted(RENAMES))
def test_a_renamed_klipper_hook_is_named_once_and_the_print_goes_on(
        tmp_path: Path, hook: str) -> None:
    klipper, kpython = require_klipper()
    tree = renamed_tree(klipper, tmp_path / "klipper", *RENAMES[hook])
    work = tmp_path / "print"
    result = run_print.run_print(str(FILE), str(work), samples=4,
                                 klipper_tree=(tree, kpython))
    # Klipper printed the whole file: every sample and the end were reached, untroubled.
    assert result["errors"] == []
    assert [s["id"] for s in result["samples"]] == [1, 2, 3, 4, 5]
    assert result["samples"][-1]["print_time"] > result["samples"][0]["print_time"]
    # ... in the time it takes with the module working in the unchanged tree.
    plain = run_print.run_print(str(FILE), str(tmp_path / "plain"), samples=4)
    assert plain["kestimator_error"] is None and plain["display_status_wrapped"] is True
    assert result["end_print_time"] == pytest.approx(plain["end_print_time"], abs=1e-9)
    assert all(s["remaining_s"] is None for s in result["samples"])
    log = (work / "klippy.log").read_text(errors="replace")
    assert "Unhandled exception" not in log and "Transition to shutdown" not in log
    # The module says which hook, once; display_status is Klipper's own.
    status = result["kestimator_status"]
    assert status["missing_hooks"] == [hook]
    assert status["state"] == "error"
    assert "Klipper's %s is missing or changed" % hook in status["error"]
    assert log.count("missing or changed") == 1
    assert result["display_status_wrapped"] is False
    assert 0. < result["display_status"]["progress"] <= 1.
