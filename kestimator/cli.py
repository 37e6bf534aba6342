"""The `kestimator` command: a thin layer over the library API.

Owns argument parsing, the command functions, exit codes and one-line errors. It computes
and draws nothing itself: estimates come from `kestimator.estimate`, limits from
`kestimator.config`, slicer facts from `kestimator.slicers`; the `--json` documents and the
plain text are built in `kestimator.cli_output`; the `rich` rendering, the limits table and
the progress bar are `kestimator.cli_render`'s. Files are written by `kestimator.files`.
`main` installs no signal handlers (the console entry points in `kestimator.entry` do).

Exit codes (docs/CLI.md): 0 success; 1 the input could not be processed (one line on
stderr names file and line); 2 the command line was wrong; 3 kestimator itself failed (a
bug: one line, the traceback with --debug).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shlex
import sys
import traceback
from collections.abc import Sequence
from typing import Any

from kestimator import __version__, build, learn
from kestimator.cli_output import (
    JSON_SCHEMA_VERSION,
    estimate_to_json,
    limits_to_json,
    print_text,
    printable,
    printable_doc,
    quiet_stdout,
    set_slicer_estimate,
    write_json,
)
from kestimator.cli_render import (
    RICH_ENV,
    ProgressBar,
    is_terminal,
    print_estimate_rich,
    print_limits_rich,
    print_limits_text,
    progress_for,
    rich_console,
)
from kestimator.config import resolve
from kestimator.config.moonraker import DEFAULT_TIMEOUT_S
from kestimator.config.resolve import (
    API_KEY_ENVIRONMENT,
    LimitRequest,
    ResolvedLimits,
)
from kestimator.durations import MAX_PRINT_S, format_duration
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, Event, estimate_lines, iter_lines
from kestimator.files import (
    STDIO_NAME,
    STDOUT_SHOWN,
    Terminated,
    spooled_stdin,
    write_bytes_atomically,
)
from kestimator.gcode import extended_params, parse_line
from kestimator.klipper_modules import loaded_modules
from kestimator.limits import Limits
from kestimator.preflight import (
    EXIT_KLIPPER_STOPS,
    SUMMARY_HEAD,
    stderr_line,
    summary_lines,
)
from kestimator.rewrite import NO_MOVES, check_gcode_file, inject_file, slicer_of_file

__all__ = ["EXIT_FAILURE", "EXIT_INTERNAL", "EXIT_KLIPPER_STOPS", "EXIT_OK", "EXIT_USAGE",
           "JSON_SCHEMA_VERSION", "RICH_ENV",
           "estimate_to_json", "limits_to_json", "main"]

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERNAL = 3
# EXIT_KLIPPER_STOPS (4, kestimator.preflight): inject/check when Klipper will stop the print.
# PrusaSlicer/OrcaSlicer run post-processing on a temporary copy and name the final file here.
SLICER_OUTPUT_NAME_ENV = "SLIC3R_PP_OUTPUT_NAME"

DESCRIPTION = ("Print-time estimates equal to what Klipper's motion planner computes, "
               "written back into your G-code.")

EPILOG = """examples:
  kestimator estimate print.gcode --printer-cfg ~/printer_data/config/printer.cfg
  kestimator estimate print.gcode --layers             also a table of layer times
  kestimator estimate print.gcode --json > times.json  one JSON object (docs/CLI.md)
  kestimator estimate print.gcode -q                   just the seconds, for scripts
  kestimator inject print.gcode --printer-cfg printer.cfg
  kestimator report print.gcode -o report.html

exit status: 0 success, 1 the file or settings could not be used (one line on stderr
names file and line), 2 a wrong command line, 3 a bug in kestimator, 4 (inject and check)
Klipper will stop this print (the pre-flight's stop).
Output is drawn with rich on a terminal when it is installed; set KESTIMATOR_RICH=0 for
plain text or KESTIMATOR_RICH=1 to force rich. --debug shows tracebacks.
"""

ESTIMATE_EPILOG = """examples:
  kestimator estimate print.gcode --printer-cfg ~/printer_data/config/printer.cfg
  kestimator estimate print.gcode --moonraker http://voron.local:7125 --layers
  kestimator estimate print.gcode --json > times.json
  seconds=$(kestimator estimate print.gcode -q)
  kestimator estimate print.gcode --exclude part_2,part_3 --at 52011

--json prints one object whose fields docs/CLI.md documents (schema 1); -q prints only
Klipper's total in seconds. Exit status: 0 success, 1 the file or settings could not be
used, 2 a wrong command line, 3 a bug in kestimator.
"""


# A help line this short ending in ':' is a heading ("examples:"), kept on its own.
HEADING_MAX_CHARS = 30


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and epilogs wrapped at the terminal's width: lines that start at the
    margin are joined into paragraphs and filled; indented lines (examples) are kept."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        import textwrap
        out: list[str] = []
        paragraph: list[str] = []

        def flush() -> None:
            if paragraph:
                out.extend(textwrap.wrap(" ".join(paragraph), width,
                                         initial_indent=indent, subsequent_indent=indent,
                                         break_on_hyphens=False))
                paragraph.clear()
        for line in text.splitlines():
            if not line.strip():
                flush()
                out.append("")
            elif line[:1] in (" ", "\t") or (line.rstrip().endswith(":")
                                             and len(line) <= HEADING_MAX_CHARS):
                flush()
                out.append(indent + line)
            else:
                paragraph.append(line.strip())
        flush()
        return "\n".join(out)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kestimator",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=_HelpFormatter)
    parser.add_argument("-V", "--version", action="version",
                        version="kestimator %s (%s)" % (__version__, build()))
    parser.add_argument("--debug", action="store_true",
                        help="show a traceback when something fails")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    est = sub.add_parser(
        "estimate", help="print Klipper's time for a G-code file",
        description="Replay a G-code file through Klipper's planner and print its time, the "
                    "slicer's own estimate and the difference, first-layer time, layers, "
                    "filament, where the limits came from, warnings and the time per "
                    "feature.",
        epilog=ESTIMATE_EPILOG, formatter_class=_HelpFormatter)
    est.add_argument("file", help="the G-code file")
    _add_limit_options(est)
    output = est.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true",
                        help="print one JSON object (fields in docs/CLI.md)")
    output.add_argument("-q", "--quiet", action="store_true",
                        help="print only Klipper's total time in seconds")
    est.add_argument("--layers", action="store_true",
                     help="also show the time of every layer (before the summary)")
    est.add_argument("-v", "--verbose", action="store_true",
                     help="name every command whose time is not counted, with its warnings")
    est.add_argument("--exclude", action="append", default=[], metavar="NAME[,NAME...]",
                     help="time the print with these objects cancelled (EXCLUDE_OBJECT NAME=, "
                          "names as the file's EXCLUDE_OBJECT_DEFINE/START give them)")
    est.add_argument("--at", type=int, default=None, metavar="LINE",
                     help="cancel the --exclude objects right before this line of the file, "
                          "1 to its last (default: before its first line)")
    _add_debug_option(est)
    inj = sub.add_parser(
        "inject", help="write Klipper's times into a G-code file (M73 and time comments)",
        description="Rewrite a G-code file so M73 progress lines and the slicer's time "
                    "comments show Klipper's time. In place (atomically) unless -o is given; "
                    "every other line is kept byte for byte.",
        epilog=INJECT_EPILOG, formatter_class=_HelpFormatter)
    inj.add_argument("file", help="the G-code file (the slicer appends it last)")
    inj.add_argument("-o", "--output", metavar="OUT",
                     help="write the result here and leave FILE untouched")
    inj.add_argument("--no-layer-info", dest="layer_info", action="store_false",
                     help="do not add SET_PRINT_STATS_INFO TOTAL_LAYER/CURRENT_LAYER lines "
                          "(added where the file sets no layer numbers and the printer knows "
                          "the command, so Mainsail, Fluidd and KlipperScreen show the "
                          "layer)")
    _add_limit_options(inj)
    output = inj.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true",
                        help="print the estimate's JSON object plus output and m73_written")
    output.add_argument("-q", "--quiet", action="store_true",
                        help="print nothing on success")
    _add_debug_option(inj)
    chk = sub.add_parser(
        "check", help="only the pre-flight check: where Klipper stops or skips commands",
        description="Run the file through Klipper's rules for this printer and report what "
                    "Klipper will do: the line where it stops the print (exit status 4) and "
                    "the commands it will skip.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    chk.add_argument("file", help="the G-code file")
    _add_limit_options(chk)
    output = chk.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true",
                        help="print one JSON object: file, limits_source, preflight, warnings")
    output.add_argument("-q", "--quiet", action="store_true",
                        help="print nothing; only the exit status tells")
    _add_debug_option(chk)
    lim = sub.add_parser(
        "limits", help="show the printer limits a file would be timed with, and their sources",
        description="Print every printer limit kestimator would use for FILE and where each "
                    "came from: --set, the printer.cfg line or Moonraker, the profile, the "
                    "slicer setting in the file (a guess), or a default.",
        epilog=LIMITS_EPILOG, formatter_class=_HelpFormatter)
    lim.add_argument("file", nargs="?",
                     help="the G-code file (its slicer settings stand in when no printer "
                          "config is known)")
    _add_limit_options(lim, with_times=False)
    lim.add_argument("--json", action="store_true", help="print one JSON object")
    _add_debug_option(lim)
    rep = sub.add_parser(
        "report", help="write an HTML report with charts (time per layer, progress, ...)",
        description="Write one self-contained HTML page (no network, no scripts) with "
                    "Klipper's time per layer, progress against the slicer's own M73, time "
                    "per feature and the speed moves reach against the speed they ask for.",
        epilog=REPORT_EPILOG, formatter_class=_HelpFormatter)
    rep.add_argument("file", help="the G-code file")
    rep.add_argument("-o", "--output", metavar="HTML", required=True,
                     help="where to write the page")
    rep.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")
    _add_limit_options(rep)
    _add_debug_option(rep)
    lrn = sub.add_parser(
        "learn", help="learn this printer's start, timelapse-frame and tool-change times from "
                      "its Moonraker job history",
        description="Read Moonraker's job history, time the file of every completed job with "
                    "the printer's limits, and learn (median of at least %d jobs, outliers "
                    "such as paused jobs rejected) the time before the first extrusion, per "
                    "timelapse frame and per tool change, and whether the printer runs slower "
                    "than Klipper's planner. Stored beside the Moonraker cache and used by "
                    "every command whose limits come from that Moonraker (--no-learned: not)."
                    % learn.MIN_JOBS)
    # Only Moonraker has the job history: no --printer-cfg here.
    _add_limit_options(lrn, with_times=False, with_printer_cfg=False)
    lrn.add_argument("--jobs", type=int, default=learn.MAX_HISTORY_JOBS, metavar="N",
                     help="read the newest N jobs (default %d; more from the server are "
                          "ignored)" % learn.MAX_HISTORY_JOBS)
    lrn.add_argument("--timeout", type=float, default=learn.DEFAULT_DEADLINE_S, metavar="S",
                     help="give up, storing nothing, when learning (the history, every "
                          "download and its timing) takes longer than S seconds in all "
                          "(default %g)" % learn.DEFAULT_DEADLINE_S)
    _add_debug_option(lrn)
    return parser


REPORT_EPILOG = """examples:
  kestimator report print.gcode -o report.html --printer-cfg printer.cfg
"""


LIMITS_EPILOG = """examples:
  kestimator limits print.gcode
  kestimator limits print.gcode --moonraker http://voron.local:7125 --json
  kestimator limits --printer-cfg printer.cfg --set klipper_generation=mcr
"""


INJECT_EPILOG = """examples:
  kestimator inject print.gcode --printer-cfg ~/printer_data/config/printer.cfg
  kestimator inject print.gcode -o print-klipper.gcode
As a PrusaSlicer/SuperSlicer/OrcaSlicer post-processing script, the whole line is:
  kestimator inject --moonraker http://voron.local:7125
(Moonraker's answer is cached, so the hook works with the printer off; or --printer-cfg
with a path, quoted if it has a space; with a profile that names the printer, just
`kestimator inject`.)

Exit status: 0 success, 1 the file or settings could not be used, 2 a wrong command line,
3 a bug in kestimator, 4 Klipper will stop this print (the times are still written).
"""


def _add_debug_option(parser: argparse.ArgumentParser) -> None:
    """--debug after the command name too (its own dest, so the top-level one survives)."""
    parser.add_argument("--debug", dest="sub_debug", action="store_true",
                        help=argparse.SUPPRESS)


def _add_limit_options(parser: argparse.ArgumentParser, with_times: bool = True,
                       with_printer_cfg: bool = True) -> None:
    machine = parser.add_mutually_exclusive_group()
    if with_printer_cfg:
        machine.add_argument("--printer-cfg", metavar="CFG",
                             help="your Klipper printer.cfg (includes and SAVE_CONFIG are "
                                  "read)")
    machine.add_argument("--moonraker", metavar="URL",
                         help="read the printer's live Klipper settings from Moonraker, e.g. "
                              "http://voron.local:7125 (cached for when it is offline, "
                              "%g s timeout)" % DEFAULT_TIMEOUT_S)
    parser.add_argument("--api-key", metavar="KEY",
                        help="Moonraker's API key, if it asks for one (also the profile's "
                             "api_key or $%s)" % API_KEY_ENVIRONMENT)
    parser.add_argument("--profile", metavar="TOML",
                        help="your kestimator profile (default: "
                             "~/.config/kestimator/config.toml if it exists)")
    parser.add_argument("--no-profile", action="store_true", help="read no profile")
    parser.add_argument("--printer", metavar="NAME",
                        help='use the profile\'s [printers."NAME"] table (default: the one '
                             "named like the slicer's printer preset)")
    parser.add_argument("--set", action="append", default=[], dest="overrides",
                        metavar="KEY=VALUE",
                        help="set one limit, above every other source (keys as "
                             "`kestimator limits` shows them, e.g. max_accel=5000 or "
                             "klipper_generation=mcr); repeatable")
    parser.add_argument("--no-learned", action="store_true",
                        help="ignore the times learned from the printer's job history "
                             "(kestimator learn)")
    if with_times:
        parser.add_argument("--homing-time", type=float, default=None, metavar="S",
                            help="seconds each G28 takes on your printer (default: the "
                                 "profile's homing_time_s, else 0)")
        parser.add_argument("--heat-time", type=float, default=None, metavar="S",
                            help="seconds each heater wait (M109/M190/TEMPERATURE_WAIT) takes "
                                 "(default: the profile's heat_time_s, else 0)")


def _resolve(args: argparse.Namespace, gcode_path: str | None) -> ResolvedLimits:
    """The limits for a run (`_say_guessed` tells, once the run succeeded, if guessed)."""
    resolved = resolve.resolve_limits(_limit_request(args, gcode_path))
    # Durations the file cannot tell: the command line, else the profile, else 0 s.
    for name, from_profile in (("homing_time", resolved.homing_time_s),
                               ("heat_time", resolved.heat_time_s)):
        if getattr(args, name, 0.0) is None:
            setattr(args, name, from_profile if from_profile is not None else 0.0)
    args.macros = learn.macro_times_for(resolved, not getattr(args, "no_learned", False))
    if args.macros.warnings:  # a damaged learned store: said, never silently dropped
        resolved = dataclasses.replace(resolved,
                                       warnings=resolved.warnings + args.macros.warnings)
    args.resolved = resolved
    return resolved


def _say_guessed(resolved: ResolvedLimits) -> None:
    """One line on stderr when the limits are guesses, with how to give the real ones.

    Said after the work succeeded (last, so it stays on screen); a failure is one line."""
    if resolved.guess_warning is not None:
        sys.stdout.flush()
        _warn_stderr(resolved.guess_warning)


def _say_flavour(resolved: ResolvedLimits, shown: str) -> None:
    """The sliced-for-another-firmware line on stderr, for the commands whose own output
    lists no warnings (inject, check): a slicer's hook shows stderr."""
    flavour = resolved.slicer_settings.flavour
    if flavour is not None:
        sys.stdout.flush()
        _warn_stderr("%s: %s" % (shown, flavour))


def _warn_stderr(text: str) -> None:
    sys.stderr.write("kestimator: warning: %s\n" % printable(text))
    sys.stderr.flush()


def _learned(args: argparse.Namespace,
             resolved: ResolvedLimits) -> learn.LearnedTimes | None:
    """What `kestimator learn` stored for the Moonraker the limits came from."""
    if getattr(args, "no_learned", False):
        return None
    return learn.learned_for(resolved)


def _limit_request(args: argparse.Namespace, gcode_path: str | None) -> LimitRequest:
    """The command line's limit options as a request to the resolver."""
    overrides: dict[str, str] = {}
    for item in args.overrides:
        key, equals, value = item.partition("=")
        if not equals or not key.strip():
            raise KestimatorError("--set takes KEY=VALUE, e.g. --set max_accel=5000")
        overrides[key.strip()] = value
    return LimitRequest(gcode=gcode_path, overrides=overrides,
                        printer_cfg=getattr(args, "printer_cfg", None),
                        moonraker_url=args.moonraker, api_key=args.api_key,
                        profile=args.profile, use_profile=not args.no_profile,
                        printer=args.printer)


def _progress(args: argparse.Namespace, label: str, passes: int = 1
              ) -> contextlib.AbstractContextManager[ProgressBar | None]:
    """A progress bar for the command's file (`progress_for`), unless --json or -q."""
    return progress_for(args.file, label, passes,
                        wanted=not (getattr(args, "json", False) or args.quiet),
                        shown=args.shown)


def _write_json(doc: dict[str, Any]) -> None:
    write_json(doc, sys.stdout)


def _time_file(args: argparse.Namespace, label: str) -> tuple[ResolvedLimits, Estimate]:
    """The one pass `estimate` and `check` share: the file checked, limits resolved, timed."""
    check_gcode_file(args.file)
    resolved = _resolve(args, args.file)
    _check_time_options(args)
    events = exclusion_events(args, resolved.limits)
    with _progress(args, label) as progress:
        # Named as the user named it (`<stdin>` for `-`, read from a temporary copy).
        est = estimate_lines(iter_lines(args.file, progress), resolved.limits, args.shown,
                             homing_time=args.homing_time, heat_time=args.heat_time,
                             macros=args.macros, events=events)
    _require_moves(est, args.shown)
    return resolved, est


def _require_moves(est: Estimate, shown: str) -> None:
    """Every command refuses a file without a move, as `inject` does (exit status 1)."""
    if est.last_move_line is None:
        raise KestimatorError(NO_MOVES, shown)


def exclusion_events(args: argparse.Namespace, limits: Limits) -> list[Event]:
    """`--exclude NAME[,NAME...] --at LINE` as events: EXCLUDE_OBJECT NAME= for each name,
    right before LINE (line 1 by default). Each name must label an object of the file
    (Klipper upper-cases names, so case does not matter), LINE must be a line of the file,
    and a printer whose config is known must have [exclude_object] (without it Klipper
    ignores EXCLUDE_OBJECT). A command line that cannot mean anything (an empty name, --at
    without --exclude, below 1 or past the file's last line) is a usage error (exit 2)."""
    names: list[str] = []
    for item in getattr(args, "exclude", []):
        parts = [name.strip() for name in item.split(",")]
        if not all(parts):
            raise UsageError("--exclude %s has an empty name: give NAME[,NAME...], the "
                             "objects' names as the file's EXCLUDE_OBJECT_DEFINE/START give "
                             "them" % shlex.quote(item))
        names += parts
    at = getattr(args, "at", None)
    if not names:
        if at is not None:
            raise UsageError("--at needs --exclude (the objects to cancel at that line)")
        return []
    at = 1 if at is None else at
    if at < 1:
        raise UsageError("--at takes a line number (1 is the file's first line), not %d" % at)
    if limits.configured_sections and \
            "exclude_object" not in loaded_modules(limits.configured_sections):
        raise KestimatorError("the printer's config has no [exclude_object] section: Klipper "
                              "would ignore EXCLUDE_OBJECT, so --exclude cannot be timed",
                              args.shown)
    known, n_lines = objects_and_lines(args.file)
    unknown = [name for name in names if name.upper() not in known]
    if unknown:
        raise KestimatorError(
            "no object named %s: the file labels %s" % (
                ", ".join(unknown),
                ", ".join(sorted(known)) if known else "no objects (no EXCLUDE_OBJECT_DEFINE "
                "or EXCLUDE_OBJECT_START; Moonraker's preprocess_cancellation adds them)"),
            args.shown)
    if at > n_lines:
        raise UsageError("--at %d is past the file's end: it has %d lines, so nothing would be "
                         "cancelled (give a line from 1 to %d)" % (at, n_lines, n_lines),
                         args.shown)
    args.excluded = {"names": [name.upper() for name in names], "line": at}
    return [(at, "EXCLUDE_OBJECT NAME=%s" % shlex.quote(name)) for name in names]


def labelled_objects(path: str) -> set[str]:
    """Every object name (upper case, as Klipper keeps it) an EXCLUDE_OBJECT_DEFINE or
    EXCLUDE_OBJECT_START line of the file gives."""
    return objects_and_lines(path)[0]


def objects_and_lines(path: str) -> tuple[set[str], int]:
    """`labelled_objects` of the file, and how many lines it has (a last line without a
    line ending counts)."""
    names: set[str] = set()
    n_lines = 0
    for raw in iter_lines(path):
        n_lines += 1
        if b"EXCLUDE_OBJECT_" not in raw[:40].upper():
            continue
        cmd = parse_line(raw.decode("utf-8", "replace").strip())
        if cmd.name in ("EXCLUDE_OBJECT_DEFINE", "EXCLUDE_OBJECT_START"):
            try:
                name = extended_params(cmd.code).get("NAME", "").strip()
            except ValueError:
                continue
            if name:
                names.add(name.upper())
    return names, n_lines


def cmd_estimate(args: argparse.Namespace) -> int:
    """`kestimator estimate`."""
    resolved, est = _time_file(args, "timing")
    warnings = list(resolved.warnings)
    slicer = slicer_of_file(args.file)
    doc = estimate_to_json(est, slicer, resolved.summary, warnings,
                           limits_guessed=resolved.guessed, source=args.file)
    if getattr(args, "excluded", None) is not None:
        # The time the cancellation saves: a second pass, without it.
        with _progress(args, "timing without the cancellation") as progress:
            whole = estimate_lines(iter_lines(args.file, progress), resolved.limits,
                                   args.shown, homing_time=args.homing_time,
                                   heat_time=args.heat_time, macros=args.macros)
        args.excluded["saved_s"] = round(whole.total_s - est.total_s, 6)
        doc["excluded"] = args.excluded
    if args.json:
        _write_json(doc)
    elif args.quiet:
        sys.stdout.write("%.3f\n" % doc["total_s"])
    else:
        console = rich_console()
        if console is None:
            print_text(printable_doc(doc), sys.stdout, layers=args.layers,
                       verbose=args.verbose)
        else:
            print_estimate_rich(printable_doc(doc), console, layers=args.layers,
                        verbose=args.verbose)
    _say_guessed(resolved)
    return EXIT_OK


def cmd_inject(args: argparse.Namespace) -> int:
    """`kestimator inject`."""
    to_stdout = args.output == STDIO_NAME
    if to_stdout and args.json:
        raise UsageError("-o - writes the G-code to standard output, where --json would go "
                         "too: give -o FILE, or -q")
    check_gcode_file(args.file)
    resolved = _resolve(args, args.file)
    _check_time_options(args)
    with _progress(args, "rewriting", passes=2) as progress:
        result = inject_file(args.file, resolved.limits, output=args.output,
                             limits_source=resolved.marker_source,
                             homing_time=args.homing_time, heat_time=args.heat_time,
                             progress=progress, macros=args.macros,
                             layer_info=args.layer_info)
    shown_output = STDOUT_SHOWN if to_stdout else result.output
    if not to_stdout:
        args.written.append(result.output)
    if args.json:
        doc = estimate_to_json(result.estimate, result.slicer, resolved.summary,
                               list(resolved.warnings), limits_guessed=resolved.guessed)
        set_slicer_estimate(doc, result.slicer_estimate_s)
        if args.shown != args.file:  # standard input, timed from a temporary copy
            doc["file"] = args.shown
            doc["warnings"] = [w.replace(args.file, args.shown) for w in doc["warnings"]]
        doc["output"] = shown_output
        doc["m73_written"] = result.m73_written
        _write_json(doc)
    elif not args.quiet:
        est = result.estimate
        slicer_s = result.slicer_estimate_s
        said = ("" if slicer_s is None else
                ", the slicer said %s" % format_duration(slicer_s))
        approximate = " (approximate: the limits are guesses)" if resolved.guessed else ""
        preflight = summary_lines(_findings(est))
        # One line, as hooks expect: the pre-flight's counts, `kestimator check` the rest.
        found = ("" if not preflight else
                 "; pre-flight: %s (kestimator check FILE shows each)"
                 % preflight[0][len(SUMMARY_HEAD):])
        # With -o -, standard output is the G-code: the summary goes to stderr.
        (sys.stderr if to_stdout else sys.stdout).write(printable(
            "kestimator: %s: Klipper time %s%s%s%s; wrote %d M73 lines%s"
            % (shown_output, format_duration(est.total_s), _parts_text(est), approximate,
               said, result.m73_written, found)) + "\n")
    if not args.json:
        _say_flavour(resolved, args.shown)
    _say_guessed(resolved)
    return _stop_status(result.estimate)


def _findings(est: Estimate) -> list[dict[str, Any]]:
    return [finding.to_json() for finding in est.preflight]


def _stop_status(est: Estimate) -> int:
    """EXIT_KLIPPER_STOPS, with one line on stderr (a slicer's dialog shows it), when
    Klipper will stop this print; else EXIT_OK."""
    line = stderr_line(_findings(est))
    if line is None:
        return EXIT_OK
    sys.stderr.write(printable(line) + "\n")
    return EXIT_KLIPPER_STOPS


def cmd_check(args: argparse.Namespace) -> int:
    """`kestimator check`: only the pre-flight check."""
    resolved, est = _time_file(args, "checking")
    findings = _findings(est)
    if args.json:
        _write_json({"schema": JSON_SCHEMA_VERSION, "kestimator": __version__,
                     "file": est.path, "limits_source": resolved.summary,
                     "limits_guessed": resolved.guessed, "preflight": findings,
                     "warnings": list(resolved.warnings)})
    elif not args.quiet:
        lines = summary_lines(findings) or [
            "Pre-flight: Klipper runs every command of this file on this printer"]
        sys.stdout.write(printable(est.path) + "\n"
                         + "".join("  %s\n" % printable(line) for line in lines))
    if not args.json:
        _say_flavour(resolved, args.shown)
    _say_guessed(resolved)
    if est.stops_print:
        return EXIT_KLIPPER_STOPS
    return EXIT_OK


def _parts_text(est: Estimate) -> str:
    """`` (motion 3m 42s + macros and prep 7m 00s, 7m 00s of it before the first
    extrusion)``, or nothing when no time was added."""
    parts = est.parts
    if not est.timed_parts:
        return ""
    text = " (motion %s + macros and prep %s" % (format_duration(parts.motion_s),
                                                 format_duration(parts.added_s))
    if parts.before_first_extrusion_s:
        text += ", %s of it before the first extrusion" % format_duration(
            parts.before_first_extrusion_s)
    return text + ")"


def _check_time_options(args: argparse.Namespace) -> None:
    for name in ("homing_time", "heat_time"):
        if not 0.0 <= getattr(args, name) <= MAX_PRINT_S:
            raise KestimatorError("--%s must be a number of seconds from 0 to a year (%g)"
                                  % (name.replace("_", "-"), MAX_PRINT_S))


def cmd_limits(args: argparse.Namespace) -> int:
    """`kestimator limits`."""
    if args.file is not None:
        check_gcode_file(args.file)
    resolved = _resolve(args, args.file)
    doc = limits_to_json(resolved, args.shown)
    learned = _learned(args, resolved)
    doc["macros"] = {name: {"seconds": t.seconds, "source": t.source}
                     for name, t in sorted(resolved.macro_times.items())}
    doc["learned"] = None if learned is None else _learned_json(learned)
    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        console = rich_console()
        if console is None:
            print_limits_text(printable_doc(doc), sys.stdout)
        else:
            print_limits_rich(printable_doc(doc), console)
        for name, entry in doc["macros"].items():
            sys.stdout.write(printable("  macro %s: %g s (%s)" % (
                name, entry["seconds"], entry["source"])) + "\n")
        if learned is not None:
            sys.stdout.write(printable("Learned from %s's history (%s):" % (
                learned.url, learned.learned_at)) + "\n")
            for line in learned.lines():
                sys.stdout.write("  " + printable(line) + "\n")
    _say_guessed(resolved)
    return EXIT_OK


def _learned_json(learned: learn.LearnedTimes) -> dict[str, Any]:
    def value(v: learn.LearnedValue | None) -> dict[str, Any] | None:
        return None if v is None else {"value": round(v.value, 6), "spread": round(
            v.spread, 6), "jobs": v.jobs, "rejected": v.rejected}
    return {"url": learned.url, "learned_at": learned.learned_at,
            "before_first_extrusion_s": value(learned.before_first_extrusion_s),
            "per_run_s": {name: value(v) for name, v in sorted(learned.per_run_s.items())},
            "motion_ratio": value(learned.motion_ratio), "jobs_read": learned.jobs_read,
            "notes": list(learned.notes)}


def cmd_learn(args: argparse.Namespace) -> int:
    """`kestimator learn`."""
    import math
    import time

    started = time.monotonic()
    if args.jobs < 1:
        raise UsageError("--jobs must be 1 or more, not %d" % args.jobs)
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise UsageError("--timeout must be a number of seconds above 0, not %s"
                         % args.timeout)
    resolved = resolve.resolve_limits(_limit_request(args, None))
    url = learn.moonraker_url_of(resolved)
    if url is None:
        raise KestimatorError("learn reads a printer's job history from Moonraker: give "
                              "--moonraker URL (or name it in the profile)")
    learn.check_store(url)  # before any download: a cache that cannot be written fails now
    learned = learn.learn_from_moonraker(
        url, resolved.limits, resolved.moonraker_api_key, max_jobs=args.jobs,
        deadline_s=args.timeout, started=started)
    path = learn.save(learned)
    sys.stdout.write(printable("Learned from %s: %d jobs read (%s), stored in %s" % (
        url, learned.jobs_read, learned.learned_at, path)) + "\n")
    for line in learned.lines():
        sys.stdout.write("  " + printable(line) + "\n")
    for note in learned.notes:
        sys.stdout.write("  note: " + printable(note) + "\n")
    return EXIT_OK


REPORT_EXTENSIONS = (".html", ".htm", ".xhtml")


def cmd_report(args: argparse.Namespace) -> int:
    """`kestimator report`."""
    # Only this command draws the page: the other commands do not pay for its import.
    from kestimator.report import collect, render_html

    to_stdout = args.output == STDIO_NAME
    extension = ".html" if to_stdout else os.path.splitext(args.output)[1].lower()
    if not args.output:
        raise KestimatorError("-o names no file (an empty name)")
    check_gcode_file(args.file)
    if (not to_stdout and os.path.exists(args.output)
            and os.path.samefile(args.file, args.output)):
        raise KestimatorError("the report would overwrite the G-code it reports on: give "
                              "another -o", args.output)
    if not to_stdout and os.path.isdir(args.output):
        raise UsageError("-o %s is a directory: give the page's file name, e.g. -o %s"
                         % (printable(args.output), printable(os.path.join(
                             args.output, "report.html"))))
    if extension not in REPORT_EXTENSIONS:
        raise UsageError("report writes one HTML page, not %s: give -o NAME.html (open it "
                         "in a browser to save a picture)" % (extension or "a file without "
                                                              "an extension"))
    resolved = _resolve(args, args.file)
    _check_time_options(args)
    with _progress(args, "timing") as progress:
        data = collect(args.file, resolved.limits, resolved.summary,
                       homing_time=args.homing_time, heat_time=args.heat_time,
                       macros=args.macros, limit_warnings=list(resolved.warnings),
                       limit_sources=resolved.sources, guessed_limits=resolved.guessed,
                       bytes_read=progress, shown=args.shown)
    _require_moves(data.estimate, args.shown)
    page = render_html(data)
    write_bytes_atomically(args.output, page.encode("utf-8"))
    if not args.quiet:
        approximate = ", approximate: the limits are guesses" if resolved.guessed else ""
        # With -o -, standard output is the page: the summary goes to stderr.
        (sys.stderr if to_stdout else sys.stdout).write(printable(
            "kestimator: wrote %s (Klipper time %s%s)" % (
                STDOUT_SHOWN if to_stdout else args.output,
                format_duration(data.estimate.total_s), approximate)) + "\n")
    _say_guessed(resolved)
    return EXIT_OK


class UsageError(KestimatorError):
    """A wrong command line found after parsing: one line, exit status 2."""


# The commands; options given before one of them are moved after it.
COMMANDS = ("estimate", "inject", "check", "limits", "report", "learn")
_TOP_LEVEL_ONLY = frozenset(("-h", "--help", "-V", "--version"))
# Options whose value is a path: a value with an unquoted space or Windows backslashes is
# explained (a slicer's post-processing line splits at spaces).
_PATH_OPTIONS = frozenset(("--printer-cfg", "--profile", "-o", "--output"))


def _fix_argv(argv: list[str]) -> list[str]:
    """`kestimator FILE` runs `estimate FILE`; options before the command go after it."""
    if any(arg in _TOP_LEVEL_ONLY for arg in argv) and not any(a in COMMANDS for a in argv):
        return argv
    index = next((i for i, arg in enumerate(argv) if arg in COMMANDS), None)
    if index is None:
        # `kestimator FILE`: the first word that is not an option names an existing file.
        first = next((arg for arg in argv if not arg.startswith("-")), None)
        if first is None or not os.path.isfile(first):
            return argv
        return ["estimate", *argv]
    if index == 0 or any(arg in _TOP_LEVEL_ONLY for arg in argv[:index]):
        return argv
    return [argv[index], *argv[:index], *argv[index + 1:]]


def _path_mistake(argv: list[str]) -> str | None:
    """One line on a path option whose value a slicer's hook line cut at a space, or that is
    written with Windows backslashes where it does not exist."""
    for i, arg in enumerate(argv[:-1]):
        option, equals, value = arg.partition("=")
        if option not in _PATH_OPTIONS:
            continue
        start = i if equals else i + 1
        value = value if equals else argv[start]
        if option in ("-o", "--output") or os.path.exists(value):
            continue
        joined = value
        for extra in argv[start + 1:]:
            joined += " " + extra
            if os.path.exists(joined):
                return ("%s %s does not exist, but %s does: the path has a space, so quote it "
                        "(in a slicer's post-processing line too): %s \"%s\""
                        % (option, printable(value), printable(joined), option,
                           printable(joined)))
        if "\\" in value:
            return ("%s %s does not exist: write the path with forward slashes (C:/Users/...) "
                    "and quote it if it has a space, e.g. %s \"%s\""
                    % (option, printable(value), option,
                       printable(value.replace("\\", "/"))))
    return None


def _command_parser(parser: argparse.ArgumentParser,
                    command: str | None) -> argparse.ArgumentParser | None:
    """The parser of one command (`kestimator estimate`), or None."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found = action.choices.get(command or "")
            return found if isinstance(found, argparse.ArgumentParser) else None
    return None


def _set_mistake(arguments: list[str]) -> str | None:
    """The line for `--set KEY VALUE` (the value given as a word of its own), or None.

    Only when the word after the key is no file: `--set max_accel print.gcode` is a --set
    without its value, which the resolver names."""
    for i, arg in enumerate(arguments[:-1]):
        flag, equals, key = arg.partition("=")
        if flag != "--set":
            continue
        at = i if equals else i + 1
        if at + 1 >= len(arguments):
            continue
        key, value = (key if equals else arguments[at]), arguments[at + 1]
        if ("=" not in key and key and not value.startswith("-")
                and not os.path.exists(value)):
            return ("--set takes KEY=VALUE, a value needs '=': --set %s=%s"
                    % (printable(key), printable(value)))
    return None


def _unrecognized(parser: argparse.ArgumentParser, args: argparse.Namespace,
                  extras: list[str]) -> None:
    """Words no option of the command takes: its own usage, and what was probably meant (an
    option spelt with `_`, several files, learn's --printer-cfg) on the error line, as
    argparse's own errors look."""
    command = _command_parser(parser, args.command) or parser
    hint = ""
    option = next((extra for extra in extras if extra.startswith("-")), None)
    if option is not None:
        name = option.partition("=")[0]
        known = sorted(s for action in command._actions for s in action.option_strings)
        if args.command == "learn" and name == "--printer-cfg":
            hint = ("learn reads the printer's job history from Moonraker: give --moonraker "
                    "URL")
        else:
            import difflib

            close = difflib.get_close_matches(name.replace("_", "-"), known, n=1, cutoff=0.75)
            if close:
                hint = "did you mean %s?" % close[0]
    elif args.command is not None and getattr(args, "file", None) is not None:
        page = ' -o "${f%.gcode}.html"' if args.command == "report" else ""
        hint = ("one file per run: for several, run kestimator once per file, e.g. "
                "for f in *.gcode; do kestimator %s \"$f\"%s; done" % (args.command, page))
    command.print_usage(sys.stderr)
    sys.stderr.write("%s: error: unrecognized arguments: %s%s\n" % (
        command.prog, printable(" ".join(extras)), "" if not hint else " (%s)" % hint))


def _error_text(exc: KestimatorError) -> str:
    """One line; names the slicer's final file when we ran on its temporary copy."""
    text = str(exc)
    final_name = os.environ.get(SLICER_OUTPUT_NAME_ENV)
    if final_name and exc.path and os.path.basename(final_name) != os.path.basename(exc.path):
        text = "%s (slicer output %s)%s" % (exc.path, final_name, text[len(exc.path):])
    return printable(text)


class StdoutError(Exception):
    """Standard output is closed or cannot take what we write (a full disk, /dev/full)."""


class _GuardedStdout:
    """sys.stdout while a command runs: a failed write or flush becomes `StdoutError`,
    so the command can still say what happened to the file (a broken pipe stays as it is:
    the reader went away on purpose)."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        if self._stream is None:
            raise StdoutError("standard output is closed")
        try:
            return int(self._stream.write(text))
        except BrokenPipeError:
            raise
        except (OSError, ValueError) as exc:
            raise StdoutError(getattr(exc, "strerror", None) or str(exc)) from None

    def flush(self) -> None:
        if self._stream is None:
            return
        try:
            self._stream.flush()
        except BrokenPipeError:
            raise
        except (OSError, ValueError) as exc:
            raise StdoutError(getattr(exc, "strerror", None) or str(exc)) from None

    def isatty(self) -> bool:
        return self._stream is not None and is_terminal(self._stream)

    def __getattr__(self, name: str) -> Any:
        if self._stream is None:
            raise AttributeError(name)
        return getattr(self._stream, name)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `kestimator` command; returns the exit status.

    Standard output failing (closed, full) is reported on stderr as one line; the exit
    status still says what happened to the file: 0 if inject wrote it, 1 otherwise.
    Installs no signal handlers: the program's entry points do (`kestimator.entry`), so a
    library caller keeps its own. A `Terminated` raised under them is 128 + the signal.
    """
    real_stdout = sys.stdout
    sys.stdout = _GuardedStdout(real_stdout)  # type: ignore[assignment]
    written: list[str] = []
    try:
        status = _main(argv, written)
        sys.stdout.flush()
        return status
    except StdoutError as exc:
        quiet_stdout()
        if written:
            sys.stderr.write("kestimator: %s was written; its summary could not be shown: "
                             "standard output: %s\n" % (printable(written[0]), exc))
            return EXIT_OK
        sys.stderr.write("kestimator: error: cannot write to standard output: %s\n" % exc)
        return EXIT_FAILURE
    except BrokenPipeError:
        quiet_stdout()
        return EXIT_OK
    except Terminated as exc:
        # Temporary files are gone (the writers unwind); 128 + signal, as if killed.
        sys.stderr.write("kestimator: terminated by signal %d\n" % exc.signum)
        return 128 + exc.signum
    finally:
        sys.stdout = real_stdout


def _main(argv: Sequence[str] | None, written: list[str]) -> int:
    parser = _build_parser()
    arguments = _fix_argv(list(sys.argv[1:] if argv is None else argv))
    mistake = _path_mistake(arguments)
    if mistake is not None:
        sys.stderr.write("kestimator: error: %s\n" % mistake)
        return EXIT_USAGE
    set_mistake = _set_mistake(arguments)
    if set_mistake is not None:
        command = _command_parser(parser, arguments[0] if arguments else None) or parser
        command.print_usage(sys.stderr)
        sys.stderr.write("%s: error: %s\n" % (command.prog, set_mistake))
        return EXIT_USAGE
    args, extras = parser.parse_known_args(arguments)
    if extras:
        _unrecognized(parser, args, extras)
        return EXIT_USAGE
    args.written = written
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    args.shown = getattr(args, "file", None)
    try:
        if args.shown == STDIO_NAME:
            return _run_on_stdin(args)
        return _run(args)
    except UsageError as exc:
        sys.stderr.write("kestimator: error: %s\n" % _error_text(exc))
        return EXIT_USAGE
    except KestimatorError as exc:
        if args.debug or getattr(args, "sub_debug", False):
            traceback.print_exc()
        sys.stderr.write("kestimator: error: %s\n" % _error_text(exc))
        return EXIT_FAILURE
    except BrokenPipeError:
        # The reader went away (`kestimator estimate --json | head`): not our failure.
        quiet_stdout()
        return EXIT_OK
    except KeyboardInterrupt:
        sys.stderr.write("kestimator: interrupted\n")
        return EXIT_FAILURE
    except MemoryError:  # the file is untouched (atomic write); not a bug of ours
        sys.stderr.write("kestimator: error: out of memory\n")
        return EXIT_FAILURE
    except StdoutError:
        raise
    except Exception as exc:  # a bug: still one line for the user, the traceback on request
        if args.debug or getattr(args, "sub_debug", False):
            traceback.print_exc()
        sys.stderr.write("kestimator: internal error: %s: %s (run with --debug for the "
                         "traceback and please report it)\n"
                         % (type(exc).__name__, printable(str(exc).replace("\n", " "))))
        return EXIT_INTERNAL


STDIN_SHOWN = "<stdin>"


def _run(args: argparse.Namespace) -> int:
    command = {"estimate": cmd_estimate, "inject": cmd_inject, "check": cmd_check,
               "limits": cmd_limits, "report": cmd_report, "learn": cmd_learn
               }.get(args.command)
    if command is None:
        raise UsageError("unknown command %r" % args.command)
    return command(args)


def _run_on_stdin(args: argparse.Namespace) -> int:
    """FILE given as `-`: standard input, kept in a temporary file for the command's passes
    and named `<stdin>` in what it prints (docs/CLI.md)."""
    if args.command == "inject" and args.output is None:
        raise UsageError("standard input cannot be rewritten in place: give -o OUT, or -o - "
                         "for standard output")
    stdin = getattr(sys.stdin, "buffer", None)
    if stdin is None:
        raise KestimatorError("standard input is closed: there is no G-code to read",
                              STDIN_SHOWN)
    with spooled_stdin(stdin, STDIN_SHOWN) as path:
        args.file = path
        args.shown = STDIN_SHOWN
        try:
            return _run(args)
        except KestimatorError as exc:
            # The temporary file's name means nothing to the user.
            exc.message = exc.message.replace(path, STDIN_SHOWN)
            raise
