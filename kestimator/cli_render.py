"""How the `kestimator` command draws on a terminal: `rich` when it can, plain text else.

Owns the `rich` rendering of the estimate (`print_estimate_rich`: layer table, summary
panel, feature table, pre-flight and warnings), the limits table in plain text and with
rich (`print_limits_text`, `print_limits_rich`, its rows `limit_rows`), and the progress bar
(`ProgressBar`, `progress_for`). Whether rich is used is decided here (`rich_console`:
installed, stdout a terminal, $KESTIMATOR_RICH). `rich` is imported only in this module,
only when drawing, and only if it is installed: without it (or when stdout is not a
terminal) the output is plain text. The documents drawn are built elsewhere: the `--json`
objects and the plain text of the estimate in `kestimator.cli_output`.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any

from kestimator import __version__
from kestimator.cli_output import (
    approximate_text,
    difference_text,
    excluded_text,
    feature_rows,
    filament_text,
    parts_rows,
    printable,
    shown_warnings,
    slicer_label,
    stop_rows,
    stops_note,
    untimed_detail,
    untimed_summary,
    untimed_waits_summary,
)
from kestimator.config.resolve import GUESS_WARNING_STARTS
from kestimator.durations import format_duration
from kestimator.preflight import KIND_STOP, summary_lines

# "1" draws with rich even when stdout is not a terminal, "0" never (docs/CLI.md).
RICH_ENV = "KESTIMATOR_RICH"
# Files at least this large get a progress bar (when stderr is a terminal).
PROGRESS_MIN_BYTES = 5 * 1024 * 1024
BAR_WIDTH = 20
# The slicer's estimate is drawn green within this many percent of Klipper's, red beyond
# the second.
DIFFERENCE_OK_PCT = 5.0
DIFFERENCE_BAD_PCT = 20.0
# A list setting (extruders, macros, sections) shows this many names in the limits table.
LIST_SHOWN = 4


def rich_console(stderr: bool = False) -> Any:
    """A rich Console for stdout (or stderr), or None for plain text.

    Rich is used when it is installed and the stream is a terminal; $KESTIMATOR_RICH=1
    forces it (a pager, a test), $KESTIMATOR_RICH=0 turns it off.
    """
    wanted = os.environ.get(RICH_ENV, "").strip()
    stream = sys.stderr if stderr else sys.stdout
    if wanted == "0" or (wanted != "1" and not is_terminal(stream)):
        return None
    try:
        from rich.console import Console
    except ImportError:
        return None
    return Console(file=stream, force_terminal=True if wanted == "1" else None,
                   highlight=False, soft_wrap=False)


def is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class ProgressBar:
    """Bytes read, drawn on stderr with the time spent and the time left: with rich when
    installed, else one rewritten line.

    Shown only for files of at least PROGRESS_MIN_BYTES when stderr is a terminal; calling
    it is then `progress(bytes_done)`. Used as a context manager, it clears itself.
    """

    def __init__(self, label: str, total_bytes: int) -> None:
        self.label = label
        self.total = max(total_bytes, 1)
        self._rich: Any = None
        self._task: Any = None
        self._last_shown = ""
        self._started = 0.0
        self._width = 0

    def __enter__(self) -> ProgressBar:
        import time
        self._started = time.monotonic()
        console = rich_console(stderr=True)
        if console is not None:
            from rich.progress import (
                BarColumn,
                Progress,
                TaskProgressColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )
            self._rich = Progress(TextColumn("{task.description}"), BarColumn(),
                                  TaskProgressColumn(), TimeElapsedColumn(),
                                  TextColumn("elapsed,"), TimeRemainingColumn(),
                                  TextColumn("left"), console=console, transient=True)
            self._rich.start()
            self._task = self._rich.add_task(self.label, total=self.total)
        return self

    def __call__(self, done: int) -> None:
        if self._rich is not None:
            self._rich.update(self._task, completed=min(done, self.total))
            return
        import time
        fraction = min(1.0, done / self.total)
        elapsed = time.monotonic() - self._started
        left = elapsed * (1.0 - fraction) / fraction if fraction > 0 else None
        text = "%s %3d %%  %s elapsed, %s left" % (
            self.label, int(100 * fraction), _clock(elapsed),
            "?" if left is None else _clock(left))
        if text != self._last_shown:
            self._last_shown = text
            self._width = max(self._width, len(text))
            sys.stderr.write("\r" + text.ljust(self._width))
            sys.stderr.flush()

    def __exit__(self, *exc: object) -> None:
        if self._rich is not None:
            self._rich.stop()
        elif self._last_shown:
            sys.stderr.write("\r%s\r" % (" " * self._width))
            sys.stderr.flush()


def _clock(seconds: float) -> str:
    """`0:07` or `1:02:03`: a duration as a clock shows it."""
    whole = int(seconds + 0.5)
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    return "%d:%02d:%02d" % (hours, minutes, secs) if hours else "%d:%02d" % (minutes, secs)


def print_estimate_rich(doc: dict[str, Any], console: Any, layers: bool = False,
                verbose: bool = False) -> None:
    """The optional layer table, then the summary, feature table, untimed commands and
    warnings, drawn with rich (the summary last, so hundreds of layers do not push it off
    the screen)."""
    from rich import box
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text

    if layers and doc["layers"]:
        longest = max(layer["duration_s"] for layer in doc["layers"])
        table = Table(title="Time per layer", title_justify="left", box=box.SIMPLE_HEAD)
        for title in ("Layer", "Line", "Starts at", "Takes"):
            table.add_column(title, justify="right")
        table.add_column("", no_wrap=True)
        for number, layer in enumerate(doc["layers"], 1):
            table.add_row(str(number), str(layer["line"]), format_duration(layer["t"]),
                          format_duration(layer["duration_s"]),
                          Text(bar(layer["duration_s"], longest), style="magenta"))
        console.print(table)
    total = doc["total_s"]
    grid = Table.grid(padding=(0, 2))
    grid.add_column(style="bold")
    grid.add_column()
    approximate = approximate_text(doc)
    parts = parts_rows(doc)
    grid.add_row("Total" if parts else "Klipper time",
                 Text.assemble((format_duration(total),
                                "bold yellow" if approximate else "bold green"),
                               ("  %.3f s" % total, "dim"),
                               ("  until the part is done" if parts else "", ""),
                               ("  " + approximate if approximate else "", "yellow")))
    for label, text in parts[1:]:
        grid.add_row(label, Text(text))
    slicer = doc["slicer"]
    if slicer["estimate_s"] is None:
        grid.add_row("Slicer", Text.assemble(slicer_label(doc),
                                             ("  no estimate in the file", "dim")))
    else:
        pct = abs(slicer["difference_pct"] or 0.0)
        style = "green" if pct < DIFFERENCE_OK_PCT else "yellow" if pct < DIFFERENCE_BAD_PCT \
            else "red"
        grid.add_row("Slicer", Text.assemble(format_duration(slicer["estimate_s"]),
                                             ("  " + slicer_label(doc), "dim")))
        grid.add_row("Difference", Text(difference_text(doc), style=style))
    if doc["first_layer_s"] is not None:
        grid.add_row("First layer", format_duration(doc["first_layer_s"]))
    grid.add_row("Layers", str(doc["layer_count"]))
    grid.add_row("Filament", Text(filament_text(doc).replace("cm3", "cm³")))
    grid.add_row("Limits from", Text(doc["limits_source"]))
    if doc.get("excluded"):
        grid.add_row("Excluded", Text(excluded_text(doc)))
    console.print(Panel(grid, title=Text(os.path.basename(doc["file"]), style="bold"),
                        title_align="left", subtitle="kestimator " + __version__,
                        subtitle_align="right", expand=False, border_style="blue"))
    rows = feature_rows(doc)
    if rows:
        table = Table(title="Time per feature", title_justify="left", box=box.SIMPLE_HEAD)
        table.add_column("Feature")
        table.add_column("Time", justify="right")
        table.add_column("Share", justify="right")
        table.add_column("", no_wrap=True)
        for name, t, share in rows:
            table.add_row(Text(name), format_duration(t), "%.1f %%" % share,
                          Text(bar(share, 100.0), style="cyan"))
        console.print(table)
    stop_table = stop_rows(doc)
    if stop_table:
        table = Table(title="Stops: the printer waits for you", title_justify="left",
                      box=box.SIMPLE_HEAD)
        table.add_column("Stop")
        for title in ("Line", "Layer", "At", "After"):
            table.add_column(title, justify="right")
        for row in stop_table:
            table.add_row(Text(row[0]), *row[1:])
        note = stops_note(doc)
        if note is not None:
            table.caption = note
        console.print(table)
    preflight = summary_lines(doc["preflight"])
    if preflight:
        stops = any(f["kind"] == KIND_STOP for f in doc["preflight"])
        console.print(Text(printable(preflight[0]),
                           style="bold red" if stops else "bold yellow"))
        for line in preflight[1:]:
            console.print(Text(printable(line)))
    summary = untimed_summary(doc)
    if summary is not None:
        if verbose:
            for text in untimed_detail(doc):
                console.print(Text("Not counted, " + text, style="dim"))
        else:
            console.print(Text(summary, style="dim"))
    waits = untimed_waits_summary(doc)
    if waits is not None:
        console.print(Text(waits, style="dim"))
    for warning in shown_warnings(doc, verbose):
        console.print(Text.assemble(("warning: ", "bold yellow"), warning))
    if doc["warnings_dropped"]:
        console.print(Text("warning: %d more warnings not shown" % doc["warnings_dropped"],
                           style="yellow"))


def bar(value: float, full: float) -> str:
    """A bar of block characters, BAR_WIDTH long when value == full."""
    if full <= 0:
        return ""
    eighths = int(round(BAR_WIDTH * 8 * min(max(value / full, 0.0), 1.0)))
    whole, part = divmod(eighths, 8)
    return "█" * whole + (" ▏▎▍▌▋▊▉"[part] if part else "")


# The unit of each limit, as `kestimator limits` shows it.
LIMIT_UNITS = {
    "max_velocity": "mm/s", "max_accel": "mm/s²", "square_corner_velocity": "mm/s",
    "max_z_velocity": "mm/s", "max_z_accel": "mm/s²", "nozzle_diameter": "mm",
    "filament_diameter": "mm", "max_extrude_cross_section": "mm²",
    "max_extrude_only_velocity": "mm/s", "max_extrude_only_accel": "mm/s²",
    "max_extrude_only_distance": "mm", "instantaneous_corner_velocity": "mm/s",
    "arc_resolution": "mm", "retract_length": "mm", "retract_speed": "mm/s",
    "unretract_extra_length": "mm", "unretract_speed": "mm/s", "max_accel_to_decel": "mm/s²",
}
SLICER_SOURCE_PREFIX = "slicer:"


# What the printer config holds besides limits of motion (its section names, macro texts,
# the heaters' temperature ranges the pre-flight checks): in `limits --json`, not in the
# table, where a list of names would widen every row.
TABLE_HIDDEN_LIMITS = frozenset(("configured_sections", "gcode_macros", "heaters"))


def limit_rows(doc: dict[str, Any]) -> list[tuple[str, str, str, str, str]]:
    """(setting, value, unit, source, what the slicer assumed) for every limit; the last is
    empty unless the file's slicer settings proposed another value that lost."""
    rows = []
    for field, entry in doc["limits"].items():
        if field in TABLE_HIDDEN_LIMITS:
            continue
        assumed = [c["value"] for c in entry["overridden"]
                   if str(c["source"]).startswith(SLICER_SOURCE_PREFIX)]
        rows.append((field, shown_value(entry["value"]), LIMIT_UNITS.get(field, ""),
                     str(entry["source"]),
                     "" if not assumed or assumed[0] == entry["value"]
                     else shown_value(assumed[0])))
    return rows


def limits_head(doc: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, text) lines above the limits table: file, slicer, machine and profile."""
    slicer = doc["slicer"]
    head = [("file", doc["file"] or "(no file)")]
    if slicer is not None:
        head.append(("slicer", slicer["name"] + (" " + slicer["version"]
                                                 if slicer["version"] else "")))
    head.append(("machine", doc["machine"] or "none (no printer.cfg or Moonraker)"))
    head.append(("profile", doc["profile"] or "none"))
    return head


def limits_tail(doc: dict[str, Any]) -> list[str]:
    """The lines below the limits table: the file's own accelerations, notes, warnings."""
    lines = []
    accelerations = doc["slicer_settings"]["accelerations"]
    if accelerations:
        lines.append("accelerations the file sets itself (mm/s², not limits): " + ", ".join(
            "%s %g" % (key, value) for key, value in accelerations.items()))
    lines.extend("note: " + note for note in doc["slicer_settings"]["notes"])
    lines.extend("warning: " + w for w in doc["warnings"]
                 if not w.startswith(GUESS_WARNING_STARTS))  # that one is said on stderr
    return lines


def print_limits_text(doc: dict[str, Any], out: Any) -> None:
    """The limits as a table: setting, value and unit, where it came from, and what the
    slicer assumed where its settings in the file say something else."""
    lines = ["  %-8s: %s" % pair for pair in limits_head(doc)]
    rows = limit_rows(doc)
    any_assumed = any(row[4] for row in rows)
    titles = ("setting", "value", "unit", "source", "slicer assumed")
    widths = [max(len(titles[i]), *(len(row[i]) for row in rows)) for i in range(3)]
    header = "  %-*s  %*s %-*s  %s" % (widths[0], titles[0], widths[1], titles[1], widths[2],
                                       titles[2], titles[3])
    lines.append(header + ("  | " + titles[4] if any_assumed else ""))
    for name, value, unit, source, assumed in rows:
        line = "  %-*s  %*s %-*s  %s" % (widths[0], name, widths[1], value, widths[2], unit,
                                         source)
        lines.append(line + ("  | slicer: %s" % assumed if assumed else ""))
    lines.extend("  " + text for text in limits_tail(doc))
    out.write("\n".join(lines) + "\n")


def print_limits_rich(doc: dict[str, Any], console: Any) -> None:
    """The same table drawn with rich."""
    from rich import box
    from rich.table import Table
    from rich.text import Text

    for label, text in limits_head(doc):
        console.print(Text.assemble(("%-8s " % label, "bold"), text))
    rows = limit_rows(doc)
    table = Table(box=box.SIMPLE_HEAD)
    table.add_column("Setting")
    table.add_column("Value", justify="right")
    table.add_column("Unit")
    table.add_column("Source", overflow="fold")
    assumed = any(row[4] for row in rows)
    if assumed:
        table.add_column("Slicer assumed", justify="right", style="yellow")
    for row in rows:
        table.add_row(*(Text(cell) for cell in (row if assumed else row[:4])))
    console.print(table)
    for text in limits_tail(doc):
        console.print(Text(text, style="yellow" if text.startswith("warning") else "dim"))


def shown_value(value: object) -> str:
    """A limit's value for people: 300, 0.64, true, mainline."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "%g" % value
    if isinstance(value, list):
        names = [str(item.get("name")) if isinstance(item, dict)
                 else str(item[0]) if isinstance(item, list) else str(item)
                 for item in value]
        if len(names) > LIST_SHOWN:
            return "%s, ... (%d)" % (", ".join(names[:LIST_SHOWN]), len(names))
        return ", ".join(names) or "none"
    return str(value)


def progress_for(path: str, label: str, passes: int = 1, wanted: bool = True,
                 shown: str | None = None
                 ) -> contextlib.AbstractContextManager[ProgressBar | None]:
    """A progress bar for reading `path` `passes` times, labelled `label` and the file's
    name (`shown`, by default `path`'s), when it is `wanted`, the file is large and stderr
    is a terminal; else a context yielding None."""
    if not wanted or not is_terminal(sys.stderr):
        return contextlib.nullcontext()
    try:
        size = os.path.getsize(path)
    except OSError:
        return contextlib.nullcontext()
    if size < PROGRESS_MIN_BYTES:
        return contextlib.nullcontext()
    return ProgressBar("%s %s" % (label, os.path.basename(path if shown is None else shown)),
                       size * passes)
