"""`python3 -m kestimator.worker` over real pipes: JSON lines in, one answer line out per
request, from the file's table or by estimating; a bad request is answered and the worker
lives on; end of input ends it with status 0."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file
from kestimator.rewrite import inject_file

from .conftest import CORPUS_CFG, PROJECT

NUT = "gcode/prusaslicer/ps25_nut_accelA_small.gcode"


def _ask(proc: subprocess.Popen[bytes], request: object) -> dict[str, Any]:
    assert proc.stdin is not None and proc.stdout is not None
    line = request if isinstance(request, bytes) else json.dumps(request).encode()
    proc.stdin.write(line + b"\n")
    proc.stdin.flush()
    answer = proc.stdout.readline()
    assert answer.endswith(b"\n")
    return json.loads(answer)  # type: ignore[no-any-return]


def test_worker_answers_from_the_table_and_by_estimating_and_survives_bad_requests(
        corpus_root: Path, tmp_path: Path) -> None:
    src = corpus_root / NUT
    injected = tmp_path / "nut.gcode"
    shutil.copyfile(src, injected)
    os.chmod(injected, 0o644)
    limits = limits_from_printer_cfg(CORPUS_CFG)[0]
    inject_file(injected, limits)
    total = estimate_file(src, limits).total_s
    env = dict(os.environ, PYTHONPATH=str(PROJECT), HOME=str(tmp_path),
               XDG_CONFIG_HOME=str(tmp_path / "config"), XDG_CACHE_HOME=str(tmp_path / "cache"))
    proc = subprocess.Popen([sys.executable, "-m", "kestimator.worker"], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        table = _ask(proc, {"id": 1, "file": str(injected), "config": str(CORPUS_CFG),
                            "events": [], "use_table": True})
        assert table["ok"] and table["id"] == 1 and table["source"] == "table"
        assert abs(table["total_s"] - total) < 0.001
        assert table["offsets"][0] == 0 and table["offsets"] == sorted(table["offsets"])
        assert len(table["offsets"]) == len(table["times"]) > 100

        bad = _ask(proc, b"{not json")
        assert bad["ok"] is False and "JSON" in bad["error"]
        missing = _ask(proc, {"id": 3, "file": str(tmp_path / "missing.gcode")})
        assert missing == {"id": 3, "ok": False, "error": missing["error"]}
        assert "missing.gcode" in missing["error"]

        estimated = _ask(proc, {"id": 4, "file": str(src), "config": str(CORPUS_CFG),
                                "events": [], "use_table": True})
        assert estimated["ok"] and estimated["source"] == "estimate", estimated
        assert abs(estimated["total_s"] - total) < 1e-6
        assert estimated["offsets"][-1] == src.stat().st_size
        # The same times as the table of the injected file, at the same lines (the offsets
        # differ by what inject inserted).
        assert abs(estimated["times"][len(estimated["times"]) // 2]
                   - table["times"][len(table["times"]) // 2]) < 5.0

        with_events = _ask(proc, {"id": 5, "file": str(src), "config": str(CORPUS_CFG),
                                  "events": [[5000, "M220 S150"]]})
        assert with_events["id"] == 5
        assert with_events["ok"]
        assert with_events["source"] == "estimate"
        assert with_events["total_s"] < total
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        assert proc.wait(timeout=60) == 0
        assert proc.stderr is not None
        assert proc.stderr.read() == b""
