"""The `kestimator` command: a thin layer over the library API.

Owns argument parsing, output formatting (JSON and text) and exit codes. It computes
nothing itself: estimates come from `kestimator.estimate`, limits from
`kestimator.config`, slicer facts from `kestimator.slicers`.

Exit codes: 0 success; 1 the input could not be processed (the message names file and
line); 2 the command line was wrong.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import traceback
from collections.abc import Sequence
from typing import Any

from kestimator import __version__
from kestimator.config import resolve
from kestimator.config.moonraker import DEFAULT_TIMEOUT_S
from kestimator.config.resolve import API_KEY_ENVIRONMENT, LimitRequest, ResolvedLimits
from kestimator.durations import format_duration
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, estimate_file
from kestimator.limits import Limits
from kestimator.report import collect, render_html
from kestimator.rewrite import check_gcode_file, inject_file
from kestimator.slicers import SlicerInfo, detect_file

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
# PrusaSlicer/OrcaSlicer run post-processing on a temporary copy and name the final file here.
SLICER_OUTPUT_NAME_ENV = "SLIC3R_PP_OUTPUT_NAME"
JSON_SCHEMA_VERSION = 1

EPILOG = """examples:
  kestimator estimate print.gcode --printer-cfg ~/printer_data/config/printer.cfg
  kestimator estimate print.gcode --json > times.json
"""


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kestimator",
        description="Print-time estimates equal to what Klipper's motion planner computes.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version="kestimator " + __version__)
    parser.add_argument("--debug", action="store_true",
                        help="show a traceback when something fails")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    est = sub.add_parser(
        "estimate", help="print Klipper's time for a G-code file",
        description="Replay a G-code file through Klipper's planner and print the time.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    est.add_argument("file", help="the G-code file")
    _add_limit_options(est)
    est.add_argument("--json", action="store_true", help="print one JSON object")
    est.add_argument("--debug", dest="sub_debug", action="store_true",
                     help=argparse.SUPPRESS)
    inj = sub.add_parser(
        "inject", help="write Klipper's times into a G-code file (M73 and time comments)",
        description="Rewrite a G-code file so M73 progress lines and the slicer's time "
                    "comments show Klipper's time. In place (atomically) unless -o is given; "
                    "every other line is kept byte for byte.",
        epilog=INJECT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    inj.add_argument("file", help="the G-code file (the slicer appends it last)")
    inj.add_argument("-o", "--output", metavar="OUT",
                     help="write the result here and leave FILE untouched")
    _add_limit_options(inj)
    inj.add_argument("--json", action="store_true", help="print a JSON summary")
    inj.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")
    inj.add_argument("--debug", dest="sub_debug", action="store_true",
                     help=argparse.SUPPRESS)
    lim = sub.add_parser(
        "limits", help="show the printer limits a file would be timed with, and their sources",
        description="Print every printer limit kestimator would use for FILE and where each "
                    "came from: --set, the printer.cfg line or Moonraker, the profile, the "
                    "slicer setting in the file (a guess), or a default.",
        epilog=LIMITS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    lim.add_argument("file", nargs="?",
                     help="the G-code file (its slicer settings stand in when no printer "
                          "config is known)")
    _add_limit_options(lim, with_times=False)
    lim.add_argument("--json", action="store_true", help="print one JSON object")
    lim.add_argument("--debug", dest="sub_debug", action="store_true",
                     help=argparse.SUPPRESS)
    rep = sub.add_parser(
        "report", help="write an HTML report with charts (time per layer, progress, ...)",
        description="Write one self-contained HTML page (no network, no scripts) with "
                    "Klipper's time per layer, progress against the slicer's own M73, time "
                    "per feature and the speed moves reach against the speed they ask for.",
        epilog=REPORT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    rep.add_argument("file", help="the G-code file")
    rep.add_argument("-o", "--output", metavar="HTML", required=True,
                     help="where to write the page")
    _add_limit_options(rep)
    rep.add_argument("--debug", dest="sub_debug", action="store_true",
                     help=argparse.SUPPRESS)
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
  kestimator inject --printer-cfg /path/to/printer.cfg
"""


def _add_limit_options(parser: argparse.ArgumentParser, with_times: bool = True) -> None:
    machine = parser.add_mutually_exclusive_group()
    machine.add_argument("--printer-cfg", metavar="CFG",
                         help="your Klipper printer.cfg (includes and SAVE_CONFIG are read)")
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
    if with_times:
        parser.add_argument("--homing-time", type=float, default=0.0, metavar="S",
                            help="seconds each G28 takes on your printer (default 0)")
        parser.add_argument("--heat-time", type=float, default=0.0, metavar="S",
                            help="seconds each heater wait (M109/M190/TEMPERATURE_WAIT) takes "
                                 "(default 0)")


def resolve_limits(args: argparse.Namespace,
                   gcode_path: str | None) -> tuple[Limits, str, list[str]]:
    """Limits for a run, a one-line description of their source, and warnings."""
    resolved = resolve.resolve_limits(_limit_request(args, gcode_path))
    return resolved.limits, resolved.summary, list(resolved.warnings)


def _limit_request(args: argparse.Namespace, gcode_path: str | None) -> LimitRequest:
    """The command line's limit options as a request to the resolver."""
    overrides: dict[str, str] = {}
    for item in args.overrides:
        key, equals, value = item.partition("=")
        if not equals or not key.strip():
            raise KestimatorError("--set takes KEY=VALUE, e.g. --set max_accel=5000")
        overrides[key.strip()] = value
    return LimitRequest(gcode=gcode_path, overrides=overrides, printer_cfg=args.printer_cfg,
                        moonraker_url=args.moonraker, api_key=args.api_key,
                        profile=args.profile, use_profile=not args.no_profile,
                        printer=args.printer)


def estimate_to_json(est: Estimate, slicer: SlicerInfo, limits_source: str,
                     extra_warnings: list[str]) -> dict[str, Any]:
    """The documented `--json` object (schema version JSON_SCHEMA_VERSION)."""
    return {
        "schema": JSON_SCHEMA_VERSION,
        "kestimator": __version__,
        "file": est.path,
        "total_s": round(est.total_s, 6),
        "first_layer_s": None if est.first_layer_s is None else round(est.first_layer_s, 6),
        "layer_count": len(est.layers),
        "layers": [{"line": line, "t": round(t, 6)} for line, t in est.layers],
        "features": {name: round(t, 6) for name, t in est.features.items()},
        "slicer": {"name": slicer.name, "version": slicer.version,
                   "estimate_s": slicer.estimate_s},
        "limits_source": limits_source,
        "n_moves": est.n_moves,
        "n_lines": est.n_lines,
        "ignored_commands": est.ignored_commands,
        "warnings": extra_warnings + est.warnings,
        "warnings_dropped": est.warnings_dropped,
    }


def _print_text(doc: dict[str, Any], out: Any) -> None:
    total = doc["total_s"]
    lines = ["%s" % doc["file"],
             "  Klipper time : %s (%.3f s)" % (format_duration(total), total)]
    slicer = doc["slicer"]
    name = slicer["name"] + (" " + slicer["version"] if slicer["version"] else "")
    if slicer["estimate_s"] is not None:
        diff = slicer["estimate_s"] - total
        pct = 100.0 * diff / total if total else 0.0
        lines.append("  %-13s: %s (%+.1f %% vs Klipper)" % (
            "Slicer", format_duration(slicer["estimate_s"]), pct))
        lines.append("  %-13s  %s" % ("", name))
    else:
        lines.append("  %-13s: %s, no estimate in the file" % ("Slicer", name))
    if doc["first_layer_s"] is not None:
        lines.append("  First layer  : %s" % format_duration(doc["first_layer_s"]))
    lines.append("  Layers       : %d" % doc["layer_count"])
    lines.append("  Limits from  : %s" % doc["limits_source"])
    if doc["features"]:
        lines.append("  Time per feature:")
        for feature, t in sorted(doc["features"].items(), key=lambda kv: -kv[1]):
            share = 100.0 * t / total if total else 0.0
            lines.append("    %-28s %10s %5.1f %%" % (feature[:28], format_duration(t), share))
    if doc["ignored_commands"]:
        lines.append("  Not Klipper commands (0 s): " + ", ".join(
            "%s x%d" % kv for kv in doc["ignored_commands"].items()))
    for warning in doc["warnings"]:
        lines.append("  warning: " + warning)
    out.write("\n".join(lines) + "\n")


def cmd_estimate(args: argparse.Namespace) -> int:
    """`kestimator estimate`."""
    limits, source, warnings = resolve_limits(args, args.file)
    _check_time_options(args)
    check_gcode_file(args.file)
    est = estimate_file(args.file, limits, homing_time=args.homing_time,
                        heat_time=args.heat_time)
    if est.last_move_line is None:
        warnings = warnings + ["the file has no moves: there is nothing to time"]
    slicer = detect_file(args.file)
    doc = estimate_to_json(est, slicer, source, warnings)
    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        _print_text(doc, sys.stdout)
    return EXIT_OK


def cmd_inject(args: argparse.Namespace) -> int:
    """`kestimator inject`."""
    limits, source, warnings = resolve_limits(args, args.file)
    _check_time_options(args)
    result = inject_file(args.file, limits, output=args.output, limits_source=source,
                         homing_time=args.homing_time, heat_time=args.heat_time)
    doc = estimate_to_json(result.estimate, result.slicer, source, warnings)
    doc["slicer"]["estimate_s"] = result.slicer_estimate_s
    doc["output"] = result.output
    doc["m73_written"] = result.m73_written
    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        sys.stdout.write("\n")
    elif not args.quiet:
        total = result.estimate.total_s
        slicer_s = result.slicer_estimate_s
        said = ("" if slicer_s is None else
                ", the slicer said %s" % format_duration(slicer_s))
        sys.stdout.write("kestimator: %s: Klipper time %s%s; wrote %d M73 lines\n" % (
            result.output, format_duration(total), said, result.m73_written))
    return EXIT_OK


def _check_time_options(args: argparse.Namespace) -> None:
    for name in ("homing_time", "heat_time"):
        if not 0.0 <= getattr(args, name) < float("inf"):
            raise KestimatorError("--%s must be a non-negative number of seconds"
                                  % name.replace("_", "-"))


def limits_to_json(resolved: ResolvedLimits, path: str | None) -> dict[str, Any]:
    """The documented `limits --json` object (schema version JSON_SCHEMA_VERSION)."""
    slicer = resolved.slicer
    settings = resolved.slicer_settings
    return {
        "schema": JSON_SCHEMA_VERSION,
        "kestimator": __version__,
        "file": path,
        "slicer": None if slicer is None else {"name": slicer.name, "version": slicer.version},
        "machine": resolved.machine,
        "profile": resolved.profile,
        "summary": resolved.summary,
        "limits": {
            field: {"value": getattr(resolved.limits, field),
                    "source": resolved.sources[field],
                    "overridden": [{"value": c.value, "source": c.source}
                                   for c in resolved.shadowed.get(field, ())]}
            for field in Limits.field_names()},
        "slicer_settings": {"origin": settings.origin or None,
                            "accelerations": dict(settings.accelerations),
                            "notes": list(settings.notes)},
        "warnings": list(resolved.warnings),
    }


def _print_limits(doc: dict[str, Any], out: Any) -> None:
    slicer = doc["slicer"]
    lines = ["%s" % (doc["file"] or "(no file)")]
    if slicer is not None:
        lines.append("  slicer  : %s%s" % (slicer["name"], " " + slicer["version"]
                                           if slicer["version"] else ""))
    lines.append("  machine : %s" % (doc["machine"] or "none (no printer.cfg or Moonraker)"))
    lines.append("  profile : %s" % (doc["profile"] or "none"))
    width = max(len(field) for field in doc["limits"])
    for field, entry in doc["limits"].items():
        lines.append("  %-*s %-10s %s" % (width, field, _shown(entry["value"]),
                                           entry["source"]))
    accelerations = doc["slicer_settings"]["accelerations"]
    if accelerations:
        lines.append("  accelerations the file sets itself (mm/s^2, not limits): " + ", ".join(
            "%s %g" % (key, value) for key, value in accelerations.items()))
    for note in doc["slicer_settings"]["notes"]:
        lines.append("  note: " + note)
    for warning in doc["warnings"]:
        lines.append("  warning: " + warning)
    out.write("\n".join(lines) + "\n")


def _shown(value: object) -> str:
    """A limit's value for people: 300, 0.64, true, mainline."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "%g" % value
    return str(value)


def cmd_limits(args: argparse.Namespace) -> int:
    """`kestimator limits`."""
    resolved = resolve.resolve_limits(_limit_request(args, args.file))
    doc = limits_to_json(resolved, args.file)
    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        _print_limits(doc, sys.stdout)
    return EXIT_OK


def cmd_report(args: argparse.Namespace) -> int:
    """`kestimator report`."""
    check_gcode_file(args.file)
    limits, source, _warnings = resolve_limits(args, args.file)
    _check_time_options(args)
    data = collect(args.file, limits, source, homing_time=args.homing_time,
                   heat_time=args.heat_time)
    page = render_html(data)
    try:
        with open(args.output, "w", encoding="utf-8") as out:
            out.write(page)
    except OSError as exc:
        raise KestimatorError("cannot write the report: %s" % (exc.strerror or exc),
                              args.output) from None
    sys.stdout.write("kestimator: wrote %s (Klipper time %s)\n"
                     % (args.output, format_duration(data.estimate.total_s)))
    return EXIT_OK


def _error_text(exc: KestimatorError) -> str:
    """One line; names the slicer's final file when we ran on its temporary copy."""
    text = str(exc)
    final_name = os.environ.get(SLICER_OUTPUT_NAME_ENV)
    if final_name and exc.path and os.path.basename(final_name) != os.path.basename(exc.path):
        text = "%s (slicer output %s)%s" % (exc.path, final_name, text[len(exc.path):])
    return text.replace("\n", " ")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `kestimator` command; returns the exit status."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        if args.command == "estimate":
            return cmd_estimate(args)
        if args.command == "inject":
            return cmd_inject(args)
        if args.command == "limits":
            return cmd_limits(args)
        if args.command == "report":
            return cmd_report(args)
    except KestimatorError as exc:
        if args.debug or getattr(args, "sub_debug", False):
            traceback.print_exc()
        sys.stderr.write("kestimator: error: %s\n" % _error_text(exc))
        return EXIT_FAILURE
    except BrokenPipeError:
        # The reader went away (`kestimator estimate --json | head`): not our failure.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except KeyboardInterrupt:
        sys.stderr.write("kestimator: interrupted\n")
        return EXIT_FAILURE
    parser.error("unknown command %r" % args.command)
    return EXIT_USAGE
