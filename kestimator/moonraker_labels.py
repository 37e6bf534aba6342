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
``check_objects``), our output gets the table of the file Moonraker's labelling will make of
it, at a cost of at most half a plain post-process more (`MAX_EXTRA_SHARE`; a host may allow
another share in ``KESTIMATOR_LABEL_AHEAD_SHARE``, and a host whose CPU is never idle a nice
value for the labelling, instead of idle CPU time only, in ``KESTIMATOR_LABEL_AHEAD_NICE``):

- as we start, Moonraker's own labelling (its interpreter and metadata.py, with the slicer it
  identified from the uploaded file, as it will) runs on a private copy of the upload, beside
  our estimate and niced below it (`Labeller.start`). Of what it makes we take only what
  cannot be derived without it: the object definitions it puts at the top (their polygons
  come from every extrusion of each object) and whether it labels the file at all;
- where its labels go in our output follows from its rules for PrusaSlicer-style labels
  (``; printing object`` / ``; stop printing object``, preprocess_cancellation's
  `preprocess_slicer`): the definitions before the first line that is neither blank nor a
  comment, EXCLUDE_OBJECT_START/END after each marker line. Our rewrite changes no line those
  rules read, so the labelled output's bytes are known line by line (`labelled_layout`);
- EXCLUDE_OBJECT_DEFINE/START/END take no time and sit right after the comments that
  already set each move's object, so the labelled file's times are our table's, at the
  offsets the insertions (and LF line endings) move them to, its objects named as the
  labels name them (`table_for_labelled_output`).

Cura's, ideaMaker's and M486 labels are not done ahead: the one line says so, and the table
is estimated at print start, as when the labelling ahead does not fit in the time left of
the processor's limit (read from the same ``-c`` config) or takes over its share. A table
that does not fit the stored file (content length and CRC-32) is refused when printed, never
trusted.

The copy lives in a private temporary folder (as Moonraker's own labelling does), its own
temporary files in that folder. Killed outright (Moonraker's time limit is a SIGKILL), we
leave nothing running and nothing for long: the labelling program reads a pipe only we hold
and exits when it closes, and the next run removes the folder
(`kestimator.files.private_folder`).
"""

from __future__ import annotations

import bisect
import json
import os
import re
import shutil
import subprocess
import time
import zlib
from dataclasses import dataclass, replace

from kestimator.progress_table import ProgressTable, read_table_file

METADATA_SCRIPT = ("file_manager", "metadata.py")
LABELS_FOLDER_PREFIX = "kestimator-labels-"
MAX_CMDLINE_BYTES = 1 << 16
MAX_CONFIG_BYTES = 1 << 22
MAX_TAIL_BYTES = 64 << 20
COPY_CHUNK = 1 << 20
TABLE_LINES_RE = re.compile(rb"; kestimator_table v\d+ [^\n]*\blines=(\d+)\b")
# The labelling ahead costs at most this share of a plain post-process more; a host where
# the table is worth more waiting may set another in the environment (SHARE_ENVIRONMENT).
MAX_EXTRA_SHARE = 0.5
SHARE_ENVIRONMENT = "KESTIMATOR_LABEL_AHEAD_SHARE"
# Kept free before the processor's time limit (of the limit, at least MIN_MARGIN_S).
MARGIN_SHARE = 0.05
MIN_MARGIN_S = 2.0
# Moonraker's metadata run's own limit with object processing on (file_manager.py, 0.11:
# _run_extract_metadata), when the processors' limits add up to less.
METADATA_TIMEOUT_S = 300.0
# Its processors' limit when their config gives none (metadata.py: run_gcode_processors).
PROCESSOR_TIMEOUT_S = 120.0
# Where SCHED_IDLE is missing, the labelling program runs this nice: our own run goes first.
LABEL_NICE = 19
# A host whose CPU is never idle (a camera stream, other uploads) may run the labelling at a
# nice value (0 to 19) instead of on idle CPU time only, where it could get none at all.
NICE_ENVIRONMENT = "KESTIMATOR_LABEL_AHEAD_NICE"
# preprocess_cancellation's header: "\n\n", this line, "; N known objects", N definitions.
HEADER_MARKER = b"; Pre-Processed for Cancel-Object support by preprocess_cancellation "
KNOWN_OBJECTS_RE = re.compile(rb"; (\d+) known objects\n")
DEFINE_NAME_RE = re.compile(rb"EXCLUDE_OBJECT_DEFINE NAME=(\S*)")
# Its `preprocess_slicer` rules, on text-mode lines (LF): what follows these lines.
MARKER_RE = re.compile(rb"^; (stop )?printing object ([^\n]*)\n", re.MULTILINE)
# Run by Moonraker's interpreter: its metadata.py's own labelling, with the slicer it
# identified from the uploaded file (argv: metadata.py, the uploaded file, the copy to label).
# Prints "labelled <rules>" or "unchanged", the rules being preprocess_cancellation's
# (slicer, cura, ideamaker, m486) as process_objects picks them; exit status 3: this Moonraker
# has another interface. Its standard input is a pipe whose other end only we hold: at its
# end (we are gone, even killed) it exits at once.
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
rules = "other"
if getattr(slicer, "has_m486_objects", False):
    rules = "m486"
else:
    for name in ("PrusaSlicer", "Cura", "IdeaMaker"):
        kind = getattr(module, name, None)
        if isinstance(kind, type) and isinstance(slicer, kind):
            rules = {"PrusaSlicer": "slicer"}.get(name, name.lower())
            break
sys.stdout.write("labelled " + rules if process(sys.argv[3], slicer) else "unchanged")
"""


def _start_ticks(pid: int) -> int | None:
    """When process `pid` started, in clock ticks since boot (Linux /proc), or None."""
    try:
        with open("/proc/%d/stat" % pid, "rb") as f:
            return int(f.read().rsplit(b")", 1)[1].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def _started_ago(pid: int) -> float | None:
    """Seconds since process `pid` started (Linux /proc), None where unknown."""
    ticks = _start_ticks(pid)
    try:
        with open("/proc/uptime", "rb") as f:
            uptime = float(f.read().split()[0])
        return None if ticks is None else max(0.0, uptime - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


@dataclass(frozen=True)
class Labeller:
    """Moonraker's labelling that will run after us: its interpreter and metadata.py, and
    the time limits of our run (`processor_timeout_s`, from our start) and of the whole
    metadata run (`metadata_timeout_s`, from its start `metadata_ago_s` seconds before ours)."""

    python: str
    metadata_script: str
    processor_timeout_s: float = PROCESSOR_TIMEOUT_S
    metadata_timeout_s: float = METADATA_TIMEOUT_S
    metadata_ago_s: float = 0.0

    def start(self, uploaded: str, folder: str) -> LabelRun:
        """Start labelling a copy (in `folder`) of the file uploaded as `uploaded`, as
        Moonraker will label it; the answer comes from `LabelRun.wait`."""
        copy = os.path.join(folder, "upload" + os.path.splitext(uploaded)[1])
        shutil.copyfile(uploaded, copy)
        # Its temporary files (Moonraker's labelling makes one) go into our folder.
        env = dict(os.environ, TMPDIR=folder)
        ours, theirs = os.pipe()[::-1]
        try:
            proc = subprocess.Popen(
                [self.python, "-c", _LABEL_PROGRAM, self.metadata_script,
                 os.path.abspath(uploaded), copy],
                cwd=os.path.dirname(self.metadata_script), stdin=theirs, env=env,
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        except BaseException:
            os.close(ours)
            raise
        finally:
            os.close(theirs)
        _lower_priority(proc.pid, label_nice())
        return LabelRun(proc, ours, copy, time.monotonic())


def label_nice() -> int | None:
    """The nice value NICE_ENVIRONMENT asks for the labelling (0 to 19), or None: idle CPU
    time only (the default, and for any other value)."""
    try:
        nice = int(os.environ.get(NICE_ENVIRONMENT, ""))
    except ValueError:
        return None
    return nice if 0 <= nice <= 19 else None


def _lower_priority(pid: int, nice: int | None) -> None:
    """Put process `pid` below us: by default, on Linux, on otherwise idle CPU time only
    (SCHED_IDLE), so our own run never waits for it (it is stopped when it has not finished
    in time); with `nice`, at that nice value (never above our own priority)."""
    if nice is None:
        try:
            os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))
            return
        except (OSError, AttributeError):
            nice = LABEL_NICE
    try:
        os.setpriority(os.PRIO_PROCESS, pid, max(nice, os.getpriority(os.PRIO_PROCESS, 0)))
    except (OSError, AttributeError):
        pass


@dataclass
class LabelRun:
    """Moonraker's labelling of a private copy of the upload, running."""

    proc: subprocess.Popen[bytes]
    pipe: int
    copy: str
    started: float

    def wait(self, until: float) -> str:
        """The labelling's rules ("slicer", "cura", ...; "" when it leaves the file as it
        is), waiting until the monotonic time `until` at most. ValueError when it failed or
        takes longer (it is stopped then)."""
        try:
            out, _ = self.proc.communicate(timeout=max(0.0, until - time.monotonic()))
        except subprocess.TimeoutExpired:
            self.stop()
            raise ValueError("its labelling takes longer than there is time for") from None
        finally:
            self._close_pipe()
        answer = out.strip()
        if self.proc.returncode != 0 or not (answer == b"unchanged"
                                             or answer.startswith(b"labelled ")):
            raise ValueError("Moonraker's labelling could not run here (status %d)"
                             % self.proc.returncode)
        return "" if answer == b"unchanged" else answer.split()[1].decode("ascii", "replace")

    def stop(self) -> None:
        """Stop it now (it writes nothing but its private copy)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._close_pipe()

    def _close_pipe(self) -> None:
        if self.pipe >= 0:
            os.close(self.pipe)
            self.pipe = -1


def _parent_args(pid: int) -> list[str]:
    with open("/proc/%d/cmdline" % pid, "rb") as f:
        raw = f.read(MAX_CMDLINE_BYTES)
    return [os.fsdecode(arg) for arg in raw.split(b"\0") if arg]


def _timeouts(config: dict[str, object]) -> tuple[float, float]:
    """Our processor's time limit and the metadata run's, from its config (Moonraker's
    file_manager.py and metadata.py, 0.11)."""
    limits: list[float] = []
    ours = PROCESSOR_TIMEOUT_S
    processors = config.get("processors")
    for proc in processors if isinstance(processors, list) else []:
        if not isinstance(proc, dict):
            continue
        value = proc.get("timeout", PROCESSOR_TIMEOUT_S)
        limit = float(value) if isinstance(value, (int, float)) and value > 0 else 0.0
        limits.append(limit)
        if proc.get("name") == "klipper_estimator" and limit > 0:
            ours = limit
    return ours, max(METADATA_TIMEOUT_S, sum(limits))


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
    ours, whole = _timeouts(config)
    mine, theirs = _start_ticks(os.getpid()), _start_ticks(parent)
    ago = ((mine - theirs) / os.sysconf("SC_CLK_TCK")
           if mine is not None and theirs is not None else 0.0)
    return Labeller(python=args[at - 1], metadata_script=os.path.join(here, args[at]),
                    processor_timeout_s=ours, metadata_timeout_s=whole,
                    metadata_ago_s=max(0.0, ago))


def extra_share() -> float:
    """The share of a plain post-process labelling ahead may cost more: MAX_EXTRA_SHARE,
    or SHARE_ENVIRONMENT's value where it is a number from 0 to 100."""
    try:
        share = float(os.environ.get(SHARE_ENVIRONMENT, ""))
    except ValueError:
        return MAX_EXTRA_SHARE
    return share if 0.0 <= share <= 100.0 else MAX_EXTRA_SHARE


def run_started() -> float:
    """The monotonic time this process started (where /proc tells; else now)."""
    ago = _started_ago(os.getpid())
    return time.monotonic() - (ago or 0.0)


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
    """What `table_for_labelled_output` did: `labelled` is True when Moonraker will label
    the file and our output now carries the table of the labelled file; `why` says why it
    does not (empty when Moonraker will not label it)."""

    labelled: bool
    why: str = ""


def object_definitions(labelled_copy: str) -> tuple[bytes, list[bytes]]:
    """The header preprocess_cancellation put into `labelled_copy` ("\\n\\n", its marker
    line, "; N known objects", N EXCLUDE_OBJECT_DEFINE lines) and the N names, in order."""
    found = -1
    data = b""
    with open(labelled_copy, "rb") as f:
        while found < 0:
            block = f.read(COPY_CHUNK)
            if not block:
                raise ValueError("Moonraker's labelling wrote no object definitions")
            data += block
            found = data.find(b"\n" + HEADER_MARKER)
            if found < 0:
                data = data[-len(HEADER_MARKER) - 2:]
        rest = data[found:] + f.read(COPY_CHUNK)
        while True:
            known = KNOWN_OBJECTS_RE.search(rest)
            line_end = rest.find(b"\n", 1)
            count = int(known.group(1)) if known and known.start() == line_end + 1 else -1
            if count < 0:
                raise ValueError("Moonraker's labelling wrote an unknown header")
            end = known.end() if known else 0
            names: list[bytes] = []
            for _ in range(count):
                stop = rest.find(b"\n", end)
                if stop < 0:
                    break
                name = DEFINE_NAME_RE.match(rest, end)
                if name is None:
                    raise ValueError("Moonraker's labelling wrote an unknown definition")
                names.append(name.group(1))
                end = stop + 1
            if len(names) == count:
                break
            more = f.read(COPY_CHUNK)
            if not more:
                raise ValueError("Moonraker's labelling wrote a header cut short")
            rest += more
    # The copy's header starts with the "\n\n" preprocess_cancellation writes before it.
    if found < 1 or not data[found - 1:found + 1] == b"\n\n":
        raise ValueError("Moonraker's labelling wrote its header where it never does")
    return b"\n" + rest[:end], names


@dataclass(frozen=True)
class Layout:
    """The labelled file's content: its length, CRC-32, and the bytes inserted before each
    text-mode offset (`points`, ascending; `inserted[k]`: inserted up to points[k])."""

    length: int
    crc32: int
    points: list[int]
    inserted: list[int]
    crlf: int
    """CRLF pairs in our output's content (each one byte less in text mode)."""
    object_names: dict[str, str]
    """A `; printing object` label (as kestimator's estimate names the object) -> the name
    its labels give it."""

    def offset(self, raw: int, crlf_before: int) -> int:
        """Where the line starting at raw offset `raw` of our output (`crlf_before` CRLF
        pairs before it) starts in the labelled file: after what is inserted before it
        (those lines take no time)."""
        if raw == 0:
            return 0
        text = raw - crlf_before
        k = bisect.bisect_right(self.points, text)
        return text + (self.inserted[k - 1] if k else 0)


def _first_command(block: bytes, start: int) -> int:
    """The offset of the first line at or after `start` (a line start) of text-mode `block`
    that Python's str.strip() leaves non-empty and that does not start with ';'; -1 if
    none is in it (its last line ends the block)."""
    pos = start
    while pos < len(block):
        end = block.index(b"\n", pos) + 1
        line = block[pos:end]
        if not line.startswith(b";") and line.decode("utf-8", "replace").strip():
            return pos
        pos = end
    return -1


def labelled_layout(output: str, content_bytes: int, header: bytes,
                    names: list[bytes]) -> Layout:
    """The labelled file Moonraker's `preprocess_slicer` makes of the first `content_bytes`
    bytes of `output` (text mode: LF line endings), given the `header` and object `names`
    its labelling of the upload wrote: its length and CRC-32, and where its insertions are.
    ValueError when the file's markers do not match the names (the labelling would fail,
    or name them otherwise)."""
    points: list[int] = []
    inserted: list[int] = []
    total_inserted = 0
    crc = 0
    text_done = 0
    crlf = 0
    header_at: int | None = None
    known: dict[bytes, bytes] = {}
    labels: dict[str, str] = {}
    carry = b""
    with open(output, "rb") as f:
        left = content_bytes
        while left > 0 or carry:
            chunk = f.read(min(COPY_CHUNK, left)) if left > 0 else b""
            if left > 0 and not chunk:
                raise ValueError("%s ended early" % output)
            left -= len(chunk)
            data = carry + chunk
            if left > 0:
                cut = data.rfind(b"\n") + 1
                if cut == 0:
                    carry = data
                    continue
                data, carry = data[:cut], data[cut:]
            else:
                carry = b""
            crlf += data.count(b"\r\n")
            block = _text_mode(data)
            if not block.endswith(b"\n"):
                raise ValueError("the content before the table does not end its last line")
            pieces: list[tuple[int, bytes]] = []
            # Markers up to the first command are copied as they are (the labelling's
            # first loop), though they name objects.
            labels_from = len(block)
            if header_at is None:
                first = _first_command(block, 0)
                if first >= 0:
                    header_at = text_done + first
                    pieces.append((first, header))
                    labels_from = first
            else:
                labels_from = 0
            for found in MARKER_RE.finditer(block):
                label = found.group(2).decode("utf-8", "surrogateescape").strip()
                key = label.encode("utf-8", "surrogateescape")
                if found.group(1) is None and key not in known:
                    if len(known) >= len(names):
                        raise ValueError("the file has more objects than Moonraker defined")
                    known[key] = names[len(known)]
                    labels[label] = names[len(known) - 1].decode("utf-8", "surrogateescape")
                if key not in known:
                    raise ValueError("an object stops that never started: Moonraker's "
                                     "labelling fails on it")
                if found.start() < labels_from:
                    continue
                pieces.append((found.end(), b"EXCLUDE_OBJECT_%s NAME=%s\n" % (
                    b"END" if found.group(1) else b"START", known[key])))
            pieces.sort(key=lambda piece: piece[0])
            at = 0
            for where, text in pieces:
                crc = zlib.crc32(block[at:where], crc)
                crc = zlib.crc32(text, crc)
                total_inserted += len(text)
                points.append(text_done + where)
                inserted.append(total_inserted)
                at = where
            crc = zlib.crc32(block[at:], crc)
            text_done += len(block)
    if header_at is None or len(known) != len(names):
        raise ValueError("the file's objects are not the ones Moonraker defined")
    return Layout(length=text_done + total_inserted, crc32=crc & 0xFFFFFFFF, points=points,
                  inserted=inserted, crlf=crlf, object_names=labels)


def _crlf_before(path: str, offsets: list[int], layout: Layout) -> list[int]:
    """CRLF pairs before each of `offsets` (ascending line starts) in `path`: one read of
    the file up to the last of them, none when it has no CRLF."""
    if not layout.crlf:
        return [0] * len(offsets)
    counts: list[int] = []
    done = count = 0
    last = b""
    with open(path, "rb") as f:
        for offset in offsets:
            while done < offset:
                block = f.read(min(COPY_CHUNK, offset - done))
                if not block:
                    raise ValueError("%s ended early" % path)
                count += block.count(b"\r\n") + (last == b"\r" and block[:1] == b"\n")
                last = block[-1:]
                done += len(block)
            counts.append(count)
    return counts


def relabel_table(table: ProgressTable, output: str, layout: Layout) -> ProgressTable:
    """`table` (our output's) for the labelled file: offsets (its stops' too) where the
    labelling moves them, the objects named as its labels name them, its length and CRC-32."""
    def moved(offsets: list[int]) -> list[int]:
        if not offsets:
            return []
        crlf = _crlf_before(output, offsets, layout)
        return [layout.length if raw >= table.content_bytes else layout.offset(raw, pairs)
                for raw, pairs in zip(offsets, crlf)]

    names = []
    for name in table.object_names:
        if name not in layout.object_names:
            raise ValueError("object %r is not one Moonraker labels" % name)
        names.append(layout.object_names[name])
    if len({name.upper() for name in names}) != len(names):
        raise ValueError("two objects would have one name in Klipper")
    return replace(table, content_bytes=layout.length, offsets=moved(table.offsets),
                   object_offsets=moved(table.object_offsets), object_names=names,
                   stop_offsets=moved(table.stop_offsets), content_crc32=layout.crc32)


def table_for_labelled_output(output: str, run: LabelRun, until: float) -> Prelabel:
    """Give `output` (our rewrite of the upload, not yet in its place) the progress table
    of the file Moonraker's labelling will make of it, from `run` (its labelling of the
    upload), waited for until the monotonic time `until` at most.

    Moonraker's labelling inserts lines only before the table (its lines are comments it
    copies): the labelled file is L + our table's lines + what follows them, in text mode,
    L being the labelled content; the new table is L's.
    """
    try:
        rules = run.wait(until)
        if not rules:
            return Prelabel(False)
        if rules != "slicer":
            return Prelabel(False, "Moonraker labels this file's objects after us (%s "
                                   "labels), which is not done ahead: its table is "
                                   "estimated at print start" % rules)
        header, names = object_definitions(run.copy)
        table = read_table_file(output)
        start = table.content_bytes
        ours, after = _split_table(_tail(output, start))
        if MARKER_RE.search(_text_mode(ours + after)):
            return Prelabel(False, "object labels after the table: the table holds for the "
                                   "unlabelled file only")
        layout = labelled_layout(output, start, header, names)
        new_lines = relabel_table(table, output, layout).encode(b"\n")
        with open(output, "rb+") as f:
            f.seek(start)
            f.truncate()
            f.write(new_lines + after)
            f.flush()
            os.fsync(f.fileno())
        return Prelabel(True)
    except (OSError, ValueError) as exc:
        return Prelabel(False, "the objects Moonraker labels after us are not labelled "
                               "ahead (%s): the table is estimated at print start" % exc)
    finally:
        run.stop()

