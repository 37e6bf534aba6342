"""Set Mainsail's and Fluidd's settings so that they show the Klipper module's remaining time,
through Moonraker's database API (never by editing a file); undo puts back what was there.

    python3 plugins/klipper/frontend_settings.py [--moonraker URL] [--undo]

The module answers for display_status with progress D / (D + R) (print duration, remaining
time). Mainsail then shows Klipper's time with three of its settings (Settings -> General):
"Print progress calculation" = Slicer (M73), "Estimate time calculation" = File, "ETA
calculation" = File (its "file" estimate is D / progress - D with the selected progress).
Fluidd's progress follows with "Print Progress calculation" = Slicer (M73); no setting makes
its remaining time or ETA use the progress (they use the file position, or the slicer's
estimate). Each front end reads its settings from its own namespace of Moonraker's database
when a browser opens it (a tab already open needs a reload).

What each key held before is kept in Moonraker's database too (namespace `kestimator`, key
`frontend_settings_before`), so that --undo restores it (a key that did not exist is deleted)
and then removes that record. Standard library only: install.sh runs it with the system's
python3. Exit status: 0 done, 1 Moonraker refused or could not be reached (one line says why).
"""
from __future__ import annotations

import argparse
import json
import sys
import urllib.error
import urllib.parse
import urllib.request
from typing import Any

# (namespace, key, value): the names Mainsail and Fluidd store their settings under, read
# from their sources (tests/frontends/README.md; tests/test_frontends.py runs their code).
SETTINGS: list[tuple[str, str, Any]] = [
    ("mainsail", "general.calcPrintProgress", "slicer"),
    ("mainsail", "general.calcEstimateTime", ["file"]),
    ("mainsail", "general.calcEtaTime", ["file"]),
    ("fluidd", "uiSettings.general.printProgressCalculation", ["slicer"]),
]
RECORD = ("kestimator", "frontend_settings_before")
TIMEOUT_S = 10.
MISSING = {"missing": True}


class MoonrakerError(Exception):
    """Moonraker could not be reached or refused a request (the message says which)."""


class Database:
    """Moonraker's database API (server/database/item) at `base`."""

    def __init__(self, base: str) -> None:
        self.base = base.rstrip("/")
        self.opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))

    def _call(self, method: str, namespace: str, key: str, value: Any = None) -> Any:
        url = self.base + "/server/database/item"
        body = None
        headers = {}
        if method == "POST":
            body = json.dumps({"namespace": namespace, "key": key, "value": value}).encode()
            headers["Content-Type"] = "application/json"
        else:
            url += "?" + urllib.parse.urlencode({"namespace": namespace, "key": key})
        request = urllib.request.Request(url, data=body, method=method, headers=headers)
        try:
            with self.opener.open(request, timeout=TIMEOUT_S) as response:
                return json.loads(response.read()).get("result", {}).get("value")
        except urllib.error.HTTPError as e:
            if e.code == 404 and method in ("GET", "DELETE"):
                return MISSING
            raise MoonrakerError("Moonraker refused %s %s.%s (HTTP %d)"
                                 % (method, namespace, key, e.code)) from None
        except (urllib.error.URLError, OSError, ValueError) as e:
            reason = getattr(e, "reason", e)
            raise MoonrakerError("cannot reach Moonraker at %s (%s)"
                                 % (self.base, str(reason)[:200])) from None

    def get(self, namespace: str, key: str) -> Any:
        return self._call("GET", namespace, key)

    def set(self, namespace: str, key: str, value: Any) -> None:
        self._call("POST", namespace, key, value)

    def delete(self, namespace: str, key: str) -> None:
        self._call("DELETE", namespace, key)


def apply(db: Database) -> list[str]:
    """Set every setting, keeping what was there before (once: a second run keeps the first
    record). Returns one line per setting changed."""
    before = db.get(*RECORD)
    if before is MISSING or not isinstance(before, dict):
        before = {}
        for namespace, key, _ in SETTINGS:
            before["%s/%s" % (namespace, key)] = db.get(namespace, key)
        db.set(RECORD[0], RECORD[1], before)
    said = []
    for namespace, key, value in SETTINGS:
        if db.get(namespace, key) != value:
            db.set(namespace, key, value)
            said.append("%s: %s = %s" % (namespace, key, json.dumps(value)))
    return said


def undo(db: Database) -> list[str]:
    """Put back what each setting held before apply() (deleting one that did not exist),
    unless the user changed it since; then forget the record."""
    before = db.get(*RECORD)
    if before is MISSING or not isinstance(before, dict):
        return []
    said = []
    for namespace, key, value in SETTINGS:
        name = "%s/%s" % (namespace, key)
        if name not in before or db.get(namespace, key) != value:
            continue        # changed by the user since: theirs now
        old = before[name]
        if old == MISSING:
            db.delete(namespace, key)
            said.append("%s: %s back to the default" % (namespace, key))
        else:
            db.set(namespace, key, old)
            said.append("%s: %s back to %s" % (namespace, key, json.dumps(old)))
    db.delete(*RECORD)
    return said


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--moonraker", default="http://127.0.0.1:7125",
                    help="Moonraker's address (default http://127.0.0.1:7125)")
    ap.add_argument("--undo", action="store_true", help="put back what was there before")
    args = ap.parse_args(argv)
    db = Database(args.moonraker)
    try:
        said = undo(db) if args.undo else apply(db)
    except MoonrakerError as e:
        print("frontend_settings: %s" % (e,), file=sys.stderr)
        return 1
    for line in said:
        print(line)
    if not said:
        print("Mainsail's and Fluidd's settings: nothing to change.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
