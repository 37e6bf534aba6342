"""Fingerprint every result a change must not move: for each corpus file, the estimate's
every field (floats bit for bit), `estimate --json`, `check --json` and `inject`'s bytes.

Used while refactoring ("behaviour unchanged"): take a snapshot at the commit before the
change, another after, and compare them.

    python tools/snapshot_outputs.py write before.json       # at the old commit
    python tools/snapshot_outputs.py compare before.json     # at the new one: exit 1 if any differ

Reads the corpus in place (../shared/corpus, or $KESTIMATOR_CORPUS). Run it with the
interpreter whose build is to be compared (the checkout's .venv/bin/python for the pure
package).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

PROJECT = Path(__file__).resolve().parent.parent
CORPUS = Path(os.environ.get("KESTIMATOR_CORPUS", PROJECT.parent / "shared" / "corpus"))


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _run(args: list[str], home: str) -> tuple[int, bytes]:
    env = dict(os.environ, HOME=home, XDG_CONFIG_HOME=os.path.join(home, ".config"),
               PYTHONPATH=str(PROJECT))
    proc = subprocess.run([sys.executable, "-m", "kestimator", *args], env=env,
                          capture_output=True, cwd=PROJECT)
    return proc.returncode, proc.stdout + b"\0" + proc.stderr


def _one(gcode: Path) -> tuple[str, dict[str, str]]:
    cfg = str(CORPUS / "printer.cfg")
    result: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="kestimator-snap-") as home:
        env = dict(os.environ, PYTHONPATH=str(PROJECT))
        digest = subprocess.run([sys.executable, str(PROJECT / "tests" / "estimate_digest.py"),
                                 cfg, str(gcode)], env=env, capture_output=True, cwd=PROJECT)
        lines = digest.stdout.splitlines()[1:]  # the first names the build
        result["digest"] = _sha(b"\n".join(lines) + digest.stderr)
        for name, args in (("estimate", ["estimate", "--json"]), ("check", ["check", "--json"])):
            rc, out = _run([*args, "--printer-cfg", cfg, str(gcode)], home)
            result[name] = "%d:%s" % (rc, _sha(out))
        out_path = os.path.join(home, "out.gcode")
        rc, out = _run(["inject", "-q", "--printer-cfg", cfg, "-o", out_path, str(gcode)], home)
        written = Path(out_path).read_bytes() if os.path.exists(out_path) else b""
        result["inject"] = "%d:%s:%s" % (rc, _sha(out), _sha(written))
    return str(gcode.relative_to(CORPUS)), result


def snapshot() -> dict[str, dict[str, str]]:
    files = sorted((CORPUS / "gcode").rglob("*.gcode"))
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        return dict(pool.map(_one, files))


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] not in ("write", "compare"):
        print(__doc__, file=sys.stderr)
        return 2
    now = snapshot()
    if argv[0] == "write":
        Path(argv[1]).write_text(json.dumps(now, indent=1, sort_keys=True) + "\n")
        print("%d files fingerprinted" % len(now))
        return 0
    before = json.loads(Path(argv[1]).read_text())
    differ = [(name, kind) for name in sorted(set(before) | set(now))
              for kind in sorted(set(before.get(name, {})) | set(now.get(name, {})))
              if before.get(name, {}).get(kind) != now.get(name, {}).get(kind)]
    for name, kind in differ:
        print("differs: %s %s" % (name, kind))
    print("%d files, %d results differ" % (len(now), len(differ)))
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
