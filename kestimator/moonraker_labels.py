"""Moonraker's object labelling, run ahead: a processed file's progress table stays valid.

Owns what `kestimator-compat post-process` does when Moonraker will label the file's objects
after it. Moonraker's metadata run (moonraker/components/file_manager/metadata.py, 0.11:
`extract_metadata` -> `run_gcode_processors`) runs the registered processors first (the
estimator, i.e. us) and then, with ``[file_manager] enable_object_processing: True``, its own
`process_objects` (preprocess_cancellation): it inserts EXCLUDE_OBJECT_DEFINE lines near the
top and EXCLUDE_OBJECT_START/END lines around each object, reading the file in text mode (line
endings become LF). Every byte offset after the first insertion moves, so the table we wrote
would be refused ("the file was changed after its table was written") and the Klipper module
would estimate afresh at print start.

So, when our parent is that metadata run with object processing on (its ``-c`` config says
``check_objects``), we run Moonraker's own labelling ahead of it on a private copy of what we
are about to write (Moonraker's interpreter and its metadata.py, with the slicer it identified
from the uploaded file, as it will), `kestimator inject` the labelled copy (its table is then
made for the labelled file), and write our output with that table. Moonraker's labelling then
turns our output into exactly the labelled, injected copy: this is checked before anything is
kept, by labelling our output once more and comparing its digest. When anything differs or
fails, our output keeps the table of the unlabelled file (refused later, safely) and one line
says why. Files Moonraker will not label (no objects, already labelled, object processing off,
another parent) are left as they are.

The labelled copies live in a private temporary folder (as Moonraker's own labelling does),
one copy at a time; the labelling program runs with a time limit, its own temporary files in
that folder. Killed outright (Moonraker's time limit is a SIGKILL), we leave nothing running
and nothing for long: the labelling program reads a pipe only we hold and exits when it
closes, and the next run removes the folder (`kestimator.files.private_folder`).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from kestimator.files import private_folder
from kestimator.limits import Limits
from kestimator.macros import MacroTimes
from kestimator.progress_table import (
    ProgressTable,
    Selection,
    Settings,
    line_offsets,
    read_table_file,
)
from kestimator.rewrite import plan_file

METADATA_SCRIPT = ("file_manager", "metadata.py")
LABELS_FOLDER_PREFIX = "kestimator-labels-"
MAX_CMDLINE_BYTES = 1 << 16
MAX_CONFIG_BYTES = 1 << 22
LABEL_TIMEOUT_S = 240.0
MAX_TAIL_BYTES = 64 << 20
COPY_CHUNK = 1 << 20
TABLE_LINES_RE = re.compile(rb"; kestimator_table v\d+ [^\n]*\blines=(\d+)\b")
# Run by Moonraker's interpreter: its metadata.py's own labelling, with the slicer it
# identified from the uploaded file (argv: metadata.py, the uploaded file, the copy to label).
# Prints "labelled" or "unchanged"; exit status 3: this Moonraker has another interface.
# Its standard input is a pipe whose other end only we hold: at its end (we are gone, even
# killed) it exits at once.
_LABEL_PROGRAM = r"""
import importlib.util, os, sys, threading
def _orphaned():
    while os.read(0, 1 << 16):
        pass
    os._exit(4)
threading.Thread(target=_orphaned, daemon=True).start()
spec = importlib.util.spec_from_file_location("moonraker_metadata", sys.argv[1])
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
base = getattr(module, "BaseSlicer", None)
process = getattr(module, "process_objects", None)
if base is None or not hasattr(base, "from_file") or process is None:
    sys.exit(3)
slicer = base.from_file(sys.argv[2])
sys.stdout.write("labelled" if process(sys.argv[3], slicer) else "unchanged")
"""


@dataclass(frozen=True)
class Labeller:
    """Moonraker's labelling that will run after us: its interpreter and metadata.py."""

    python: str
    metadata_script: str

    def label(self, uploaded: str, copy: str) -> bool:
        """Label `copy` in place as Moonraker will label the file uploaded as `uploaded`;
        True if it changed. Raises OSError/ValueError when the labelling cannot run."""
        # Its temporary files (Moonraker's labelling makes one) go beside the copy, into
        # our private folder.
        env = dict(os.environ, TMPDIR=os.path.dirname(os.path.abspath(copy)))
        ours, theirs = os.pipe()[::-1]
        try:
            done = subprocess.run(
                [self.python, "-c", _LABEL_PROGRAM, self.metadata_script,
                 os.path.abspath(uploaded), os.path.abspath(copy)],
                cwd=os.path.dirname(self.metadata_script), stdin=theirs, env=env,
                capture_output=True, timeout=LABEL_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise ValueError("Moonraker's labelling took over %d s" % LABEL_TIMEOUT_S) from None
        finally:
            os.close(theirs)
            os.close(ours)
        answer = done.stdout.strip()
        if done.returncode != 0 or answer not in (b"labelled", b"unchanged"):
            raise ValueError("Moonraker's labelling could not run here (status %d)"
                             % done.returncode)
        return answer == b"labelled"


def _parent_args(pid: int) -> list[str]:
    with open("/proc/%d/cmdline" % pid, "rb") as f:
        raw = f.read(MAX_CMDLINE_BYTES)
    return [os.fsdecode(arg) for arg in raw.split(b"\0") if arg]


def moonraker_labeller(pid: int | None = None) -> Labeller | None:
    """The labelling Moonraker will do after us, or None: our parent (`pid`) is not
    Moonraker's metadata run, or its configuration turns object processing off."""
    parent = os.getppid() if pid is None else pid
    try:
        args = _parent_args(parent)
    except OSError:
        return None
    scripts = [i for i, arg in enumerate(args)
               if tuple(arg.replace(os.sep, "/").split("/")[-2:]) == METADATA_SCRIPT]
    if not scripts or scripts[0] == 0:
        return None
    at = scripts[0]
    rest = args[at + 1:]
    if "-c" in rest:
        flag = "-c"
    elif "--config" in rest:
        flag = "--config"
    else:
        return None  # the command-line form: -o says it (Moonraker itself passes -c)
    place = rest.index(flag) + 1
    if place >= len(rest):
        return None
    try:
        # Relative names are the parent's: from its working folder.
        here = os.readlink("/proc/%d/cwd" % parent)
        with open(os.path.join(here, rest[place]), "rb") as f:
            config = json.loads(f.read(MAX_CONFIG_BYTES))
    except (OSError, ValueError):
        return None
    if not isinstance(config, dict) or config.get("check_objects") is not True:
        return None
    return Labeller(python=args[at - 1], metadata_script=os.path.join(here, args[at]))


def _blocks(path: str, length: int | None = None) -> Iterator[bytes]:
    """The first `length` bytes of `path` (all of it for None), a block at a time."""
    with open(path, "rb") as f:
        left = os.path.getsize(path) if length is None else length
        while left > 0:
            block = f.read(min(COPY_CHUNK, left))
            if not block:
                raise ValueError("%s ended early" % path)
            yield block
            left -= len(block)


def _digest(path: str, length: int | None = None, then: bytes = b"") -> bytes:
    """SHA-256 of the first `length` bytes of `path` (all for None) followed by `then`."""
    sha = hashlib.sha256()
    for block in _blocks(path, length):
        sha.update(block)
    sha.update(then)
    return sha.digest()


def _crc32(path: str, length: int) -> int:
    crc = 0
    for block in _blocks(path, length):
        crc = zlib.crc32(block, crc)
    return crc & 0xFFFFFFFF


def _copy_head(source: str, dest: str, length: int, tail: bytes) -> None:
    """`dest` = the first `length` bytes of `source`, then `tail`."""
    with open(dest, "wb") as out:
        for block in _blocks(source, length):
            out.write(block)
        out.write(tail)


def _tail(path: str, start: int) -> bytes:
    """The bytes of `path` from `start` to its end (at most MAX_TAIL_BYTES)."""
    if os.path.getsize(path) - start > MAX_TAIL_BYTES:
        raise ValueError("the lines after the table are too long")
    with open(path, "rb") as f:
        f.seek(start)
        return f.read()


def _text_mode(data: bytes) -> bytes:
    """`data` as Python's text mode reads and writes it back on POSIX (universal
    newlines: CRLF and a lone CR become LF), as Moonraker's labelling copies every line."""
    return data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")


def _split_table(tail: bytes) -> tuple[bytes, bytes]:
    """`tail` (from a table's header line on) as the table's lines and what follows."""
    header = TABLE_LINES_RE.match(tail)
    if header is None:
        raise ValueError("the table's header is not where it was written")
    end = 0
    for _ in range(int(header.group(1)) + 1):
        end = tail.index(b"\n", end) + 1
    return tail[:end], tail[end:]


@dataclass(frozen=True)
class Prelabel:
    """What `table_for_labelled_file` did: `labelled` is True when Moonraker will label the
    file and our output now carries the table of the labelled file; `why` says why it
    does not (empty when Moonraker will not label it)."""

    labelled: bool
    why: str = ""


def table_points(path: str, limits: Limits, limits_source: str = "",
                 homing_time: float = 0.0, heat_time: float = 0.0,
                 macros: MacroTimes | None = None) -> tuple[Selection, Settings | None]:
    """The progress table's points for `path` as it stands and the settings it records,
    from the estimate `kestimator inject` makes (`kestimator.rewrite.plan_file`)."""
    plan = plan_file(path, limits, limits_source, homing_time, heat_time, None, macros,
                     layer_info=False, table=True)[0]
    if plan.table is None:
        raise ValueError("the estimate gave no progress table")
    return plan.table, plan.table_settings


def table_for_labelled_file(output: str, uploaded: str, labeller: Labeller,
                            plan: Callable[[str], tuple[Selection, Settings | None]]
                            ) -> Prelabel:
    """Give `output` (our rewrite of `uploaded`, not yet in its place) the progress table of
    the file Moonraker's labelling will make of it. `plan(path)` estimates a file as our
    output was estimated (same printer, same options) and gives the table's points and the
    settings it records.

    Moonraker's labelling inserts lines only before the table (its lines are comments it
    copies), so the labelled file is L + our table's lines + what follows them, L being the
    labelled content: the new table is the one of L (points from an estimate of the labelled
    copy, offsets of its lines, L's length and CRC-32), with LF line endings as the labelling
    writes every line. Kept only when labelling our output with the new table gives exactly
    L + new table + what follows.
    """
    try:
        with private_folder(LABELS_FOLDER_PREFIX) as work:
            return _table_for_labelled_file(output, uploaded, labeller, plan,
                                            os.path.join(work, os.path.basename(uploaded)))
    except (OSError, ValueError) as exc:
        return Prelabel(False, str(exc))


def _table_for_labelled_file(output: str, uploaded: str, labeller: Labeller,
                             plan: Callable[[str], tuple[Selection, Settings | None]],
                             copy: str) -> Prelabel:
    shutil.copyfile(output, copy)
    if not labeller.label(uploaded, copy):
        return Prelabel(False)
    start = read_table_file(output).content_bytes
    ours, after = _split_table(_tail(output, start))
    old_lines, after_lines = _text_mode(ours), _text_mode(after)
    labelled_bytes = os.path.getsize(copy) - len(old_lines) - len(after_lines)
    if labelled_bytes < 0 or _tail(copy, labelled_bytes) != old_lines + after_lines:
        return Prelabel(False, "Moonraker's labelling changes the table's lines: the "
                               "table holds for the unlabelled file only")
    selection, settings = plan(copy)
    with open(copy, "rb") as f:
        offsets = line_offsets(f.read, selection.wanted_lines())
    table = ProgressTable.from_selection(selection, offsets, labelled_bytes, settings,
                                         _crc32(copy, labelled_bytes))
    new_lines = table.encode(b"\n")
    expected = _digest(copy, labelled_bytes, new_lines + after_lines)
    _copy_head(output, copy, start, new_lines + after)
    if not labeller.label(uploaded, copy) or _digest(copy) != expected:
        return Prelabel(False, "Moonraker's labelling of this file moves the table's "
                               "lines: the table holds for the unlabelled file only")
    with open(output, "rb+") as f:
        f.seek(start)
        f.truncate()
        f.write(new_lines + after)
        f.flush()
        os.fsync(f.fileno())
    return Prelabel(True)
