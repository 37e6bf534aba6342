"""`kestimator-compat`: klipper_estimator's command line, answered by kestimator.

Owns the contract Moonraker's ``[analysis]`` component (Arksine/moonraker,
moonraker/components/analysis.py, 0.11) has with the program it runs from
``<data_path>/tools/klipper_estimator/klipper_estimator_<platform>``:

- Moonraker runs ``--version`` and ``estimate`` with stderr merged into stdout, so those two
  write nothing to stderr unless they fail;
- ``--version`` prints ``klipper_estimator <version> ...``; Moonraker matches
  ``klipper_estimator (v?\\d+(?:\\.\\d+)*)`` at the start of stdout and refuses a program that
  does not answer so. The version printed is kestimator's own (the line says so);
- ``--config_file FILE post-process PATH`` rewrites PATH in place: kestimator's real job
  (`kestimator.rewrite.inject_file`: true ``M73 P R`` lines, the slicer's time comments, the
  ``; kestimator ...`` marker), then the line Moonraker recognises a processed file by,
  ``; Processed by klipper_estimator <version>, ...`` (Moonraker's ``IDENT_REGEX``, looked
  for in the last 64 KiB), as the file's last line. The source is replaced atomically;
- ``--config_file FILE estimate -f json PATH`` prints ``{"sequences": [{...}]}`` with
  klipper_estimator's fields (``total_time``, ``total_distance``, ``total_extrude_distance``,
  ``num_moves``, ``total_z_time``, ``phase_times``, ``kind_times``, ``layer_times``); Moonraker
  answers ``/server/analysis/estimate`` with ``sequences[0]``, so there is exactly one;
- ``[--config_file FILE] --config_moonraker_url URL [--config_moonraker_api_key KEY] dump-config``
  prints a klipper_estimator config (JSON) from the limits resolved from Moonraker.

What it runs of the core it takes from `kestimator.api`, as every front end outside the
command line does; only the output helpers it shares with that (`kestimator.cli_output`),
klipper_estimator's config format, `kestimator.files.Terminated` and `spooled_stdin` (`-` as
the input) come from their modules.
Limits come from `kestimator.config.resolve.resolve_limits`: the config file is a
klipper_estimator config source, a URL the machine, and kestimator's profile (if any) as
everywhere else. Exit codes: 0 success, 1 the input could not be processed, 2 a wrong
command line.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from typing import Any, BinaryIO, TextIO

from kestimator import __version__
from kestimator.api import (
    NO_FEATURE,
    Estimate,
    KestimatorError,
    LimitRequest,
    MacroTimes,
    Move,
    ResolvedLimits,
    check_gcode_file,
    estimate_lines,
    inject_file,
    iter_lines,
    macro_times_for,
    resolve_limits,
)
from kestimator.cli_output import parts_to_json, printable, quiet_stdout
from kestimator.config.klipper_estimator import dump_config
from kestimator.errors import fixed
from kestimator.files import (
    Terminated,
    private_folder,
    remove_abandoned_folders,
    spooled_stdin,
)
from kestimator.moonraker_labels import (
    LABELS_FOLDER_PREFIX,
    MARGIN_SHARE,
    MIN_MARGIN_S,
    Labeller,
    LabelRun,
    Prelabel,
    extra_share,
    moonraker_labeller,
    run_started,
    table_for_labelled_output,
)

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
PROGRAM = "klipper_estimator"
VERSION_LINE = "%s %s (kestimator-compat: this is kestimator %s, not klipper_estimator)" % (
    PROGRAM, __version__, __version__)
IDENT_PREFIX = "; Processed by klipper_estimator "
IDENT_LINE = "%s%s, kestimator %s (Klipper times; see the '; kestimator' line)" % (
    IDENT_PREFIX, __version__, __version__)
# Moonraker's analysis.IDENT_REGEX matches IDENT_LINE; a file whose last 64 KiB hold it is
# not processed again.
IDENT_SEARCH_BYTES = 64 * 1024
# klipper_estimator's name for moves before any feature marker (its `kind_times`).
OTHER_KIND = "Other"
# A move is on a layer when its start and end Z agree this closely (klipper_estimator's
# f64::EPSILON test); layers are keyed by Z rounded to the micrometre, as it does.
SAME_Z_MM = sys.float_info.epsilon
LAYER_Z_DECIMALS = 3
STDIN_NAME = "-"
STDIN_SHOWN = "<stdin>"
# The guessed-limits line's fix, in terms this program accepts (Moonraker passes only
# --config_file to post-process and estimate).
COMPAT_GUESS_FIX = ("name the printer in kestimator's profile (printer_cfg or moonraker in "
                    "~/.config/kestimator/config.toml of the user Moonraker runs as), or pass "
                    "--config_moonraker_url URL")
# Of the labelling ahead's share (`extra_share()`), what placing the labels in our output
# and moving the table takes at most; the rest is for waiting on Moonraker's labelling.
TRANSFER_SHARE = 0.4
# An internal error's text is cut to this many characters (it may quote a file or a server).
MAX_ERROR_CHARS = 300


class MoveTotals:
    """klipper_estimator's per-sequence sums, gathered from kestimator's planned moves."""

    def __init__(self) -> None:
        self.total_distance = 0.0
        self.total_extrude_distance = 0.0
        self.total_z_time = 0.0
        self.acceleration = 0.0
        self.cruise = 0.0
        self.deceleration = 0.0
        self.layer_times: dict[float, float] = defaultdict(float)

    def __call__(self, moves: list[Move], start_t: float) -> None:
        for move in moves:
            move_t = move.accel_t + move.cruise_t + move.decel_t
            self.total_distance += move.move_d
            self.total_extrude_distance += move.axes_d[3]
            self.acceleration += move.accel_t
            self.cruise += move.cruise_t
            self.deceleration += move.decel_t
            start_z, end_z = move.start_pos[2], move.end_pos[2]
            if abs(start_z - end_z) < SAME_Z_MM:
                self.layer_times[round(start_z, LAYER_Z_DECIMALS)] += move_t
            else:
                self.total_z_time += move_t


def estimate_document(est: Estimate, totals: MoveTotals, limits_source: str,
                      warnings: Sequence[str] = ()) -> dict[str, Any]:
    """``estimate -f json`` output: one klipper_estimator sequence holding the whole file."""
    kinds = {OTHER_KIND if name == NO_FEATURE else name: t
             for name, t in est.features.items()}
    return {"sequences": [{
        "total_time": est.total_s,
        "total_distance": totals.total_distance,
        "total_extrude_distance": totals.total_extrude_distance,
        "num_moves": est.n_moves,
        "total_z_time": totals.total_z_time,
        "phase_times": {"acceleration": totals.acceleration, "cruise": totals.cruise,
                        "deceleration": totals.deceleration},
        "kind_times": dict(sorted(kinds.items())),
        "layer_times": [[z, t] for z, t in sorted(totals.layer_times.items())],
        "kestimator_version": __version__,
        "limits_source": limits_source,
        "kestimator_warnings": list(warnings) + est.warnings,
        "kestimator_parts": parts_to_json(est),
    }]}


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kestimator-compat",
        description="klipper_estimator's command line, answered by kestimator (for "
                    "Moonraker's [analysis]; see plugins/moonraker/README.md).")
    parser.add_argument("-V", "--version", action="store_true",
                        help="print 'klipper_estimator <version>' as Moonraker expects")
    parser.add_argument("--config_file", metavar="FILE",
                        help="a klipper_estimator config (JSON or JSON5) to take limits from")
    parser.add_argument("--config_moonraker_url", metavar="URL",
                        help="read the printer's Klipper settings from this Moonraker")
    parser.add_argument("--config_moonraker_api_key", "--api_key", dest="api_key",
                        metavar="KEY", help="Moonraker's API key")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    est = sub.add_parser("estimate", help="print the time of a G-code file")
    est.add_argument("-f", "--format", choices=("human", "json"), default="human")
    est.add_argument("input", help="the G-code file ('-' reads standard input)")
    post = sub.add_parser("post-process",
                          help="rewrite a G-code file in place with Klipper's times")
    post.add_argument("filename", help="the G-code file")
    sub.add_parser("dump-config", help="print a klipper_estimator config of the limits")
    return parser


def _request(args: argparse.Namespace, gcode: str | None) -> LimitRequest:
    return LimitRequest(gcode=gcode, moonraker_url=args.config_moonraker_url,
                        api_key=args.api_key, estimator_config=args.config_file,
                        read_slicer_environment=False, guess_fix=COMPAT_GUESS_FIX)


def _warn(resolved: ResolvedLimits, err: TextIO) -> None:
    for warning in resolved.warnings:
        err.write("kestimator-compat: warning: %s\n" % printable(warning))


def cmd_estimate(args: argparse.Namespace, out: TextIO, err: TextIO,
                 stdin: BinaryIO | None) -> int:
    """``estimate [-f json] INPUT``."""
    if args.input == STDIN_NAME:
        if stdin is None:  # started with standard input closed (<&-)
            raise KestimatorError("standard input is closed: there is no G-code to read",
                                  STDIN_SHOWN)
        # Kept in a temporary file, so it is checked as a named file is (an STL, a 3MF,
        # an empty input are one line) and named `<stdin>`.
        with spooled_stdin(stdin, STDIN_SHOWN) as path:
            return _estimate(args, path, STDIN_SHOWN, out)
    return _estimate(args, args.input, args.input, out)


def _estimate(args: argparse.Namespace, path: str, shown: str, out: TextIO) -> int:
    check_gcode_file(path)
    resolved, macros = _limits_and_macros(_request(args, None if shown != path else path))
    totals = MoveTotals()
    est = estimate_lines(iter_lines(path), resolved.limits, shown, observer=totals,
                         homing_time=resolved.homing_time_s or 0.0,
                         heat_time=resolved.heat_time_s or 0.0, macros=macros)
    doc = estimate_document(est, totals, resolved.summary, resolved.warnings)
    if args.format == "json":
        # Moonraker reads this command's stdout and stderr as one stream (its exec_cmd
        # without log_stderr): the warnings go into the document, nothing to stderr.
        json.dump(doc, out, indent=2)
        out.write("\n")
        return EXIT_OK
    seq = doc["sequences"][0]
    lines = ["Sequences:", " Run 0:",
             "  Total moves: %d" % seq["num_moves"],
             "  Total distance: %smm" % fixed(seq["total_distance"]),
             "  Total extrude distance: %smm" % fixed(seq["total_extrude_distance"]),
             "  Klipper time: %.3fs (kestimator %s; limits: %s)"
             % (seq["total_time"], __version__, resolved.summary)]
    out.write("\n".join(lines + ["  warning: " + w for w in resolved.warnings]) + "\n")
    return EXIT_OK


def _limits_and_macros(request: LimitRequest) -> tuple[ResolvedLimits, MacroTimes]:
    """The limits and the macro times, with the learned store's warnings among the limits'
    (a damaged store is said, never silently dropped, as `kestimator` says it)."""
    resolved = resolve_limits(request)
    macros = macro_times_for(resolved)
    if macros.warnings:
        resolved = dataclasses.replace(resolved, warnings=resolved.warnings + macros.warnings)
    return resolved, macros


def cmd_post_process(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    """``post-process PATH``: inject kestimator's times, then the line Moonraker looks for.

    One atomic in-place rewrite (`inject_file`: its lock, so concurrent runs take turns, its
    checks, owner/mode/xattrs kept, the directory synced); the ident line is appended to the
    temporary file before it replaces PATH, and that file exists only while it is written.
    """
    started = run_started()
    path = args.filename
    if path == STDIN_NAME:
        raise KestimatorError("post-process rewrites a file in place: standard input cannot "
                              "be; give the file's path")
    check_gcode_file(path)
    # What a run killed at Moonraker's time limit left (the copy beside PATH goes with the
    # next write into its folder: `write_atomically`).
    remove_abandoned_folders(LABELS_FOLDER_PREFIX)
    resolved, macros = _limits_and_macros(_request(args, path))
    _warn(resolved, err)
    options: dict[str, Any] = dict(limits_source=resolved.marker_source,
                                   homing_time=resolved.homing_time_s or 0.0,
                                   heat_time=resolved.heat_time_s or 0.0, macros=macros)
    labelled: list[Prelabel] = []
    with contextlib.ExitStack() as stack:
        labeller = moonraker_labeller()
        run: LabelRun | None = None
        if labeller is not None:
            # Moonraker's labelling of the upload runs beside our estimate.
            work = stack.enter_context(private_folder(LABELS_FOLDER_PREFIX))
            try:
                run = labeller.start(path, work)
            except OSError as exc:
                labelled.append(Prelabel(False, "Moonraker's labelling could not start: %s"
                                                % (exc.strerror or exc)))
            else:
                stack.callback(run.stop)

        def finish(temp: str) -> None:
            append_ident_line(temp)
            if run is None or labeller is None:
                return
            until = labelling_deadline(labeller, started, run)
            if until <= time.monotonic():
                run.stop()
                labelled.append(Prelabel(False, (
                    "the objects Moonraker labels after us are not labelled ahead: that "
                    "does not fit in the time left (its limit: %.0f s): the table is "
                    "estimated at print start") % labeller.processor_timeout_s))
                return
            labelled.append(table_for_labelled_output(temp, run, until))

        result = inject_file(path, resolved.limits, finish=finish, **options)
    out.write("kestimator-compat: %s: Klipper time %.3f s, %d M73 lines (limits: %s)%s\n"
              % (_printable(path), result.estimate.total_s, result.m73_written,
                 _printable(resolved.summary),
                 "; table made for the file as Moonraker labels its objects"
                 if labelled and labelled[0].labelled else ""))
    if labelled and labelled[0].why:
        err.write("kestimator-compat: %s: %s\n" % (_printable(path),
                                                   _printable(labelled[0].why)))
    return EXIT_OK


def labelling_deadline(labeller: Labeller, started: float, run: LabelRun) -> float:
    """Until when (monotonic) labelling ahead may go on, asked once the plain post-process
    that began at `started` has its output: at most `extra_share()` of the time that took
    more, and ending a margin before Moonraker's limit for us, and before the metadata
    run's own limit less what its own labelling after us will take (as long as ours)."""
    now = time.monotonic()
    plain = now - started
    limit = labeller.processor_timeout_s
    margin = max(MIN_MARGIN_S, MARGIN_SHARE * limit)
    metadata_end = started - labeller.metadata_ago_s + labeller.metadata_timeout_s
    theirs = now - run.started  # their labelling takes as long as ours, at least this
    return min(now + extra_share() * plain * (1.0 - TRANSFER_SHARE),
               started + limit - margin, metadata_end - margin - theirs)


def _printable(text: str) -> str:
    """One line, control characters escaped (file names may hold newlines)."""
    return "".join(ch if ch.isprintable() else ascii(ch)[1:-1] for ch in text)


def append_ident_line(path: str) -> bool:
    """End the file with ``IDENT_LINE`` unless its last line already is it; True if added.

    The line takes the line ending of the file's last line; a file not ending in one gets
    one first, so the marker stands on its own line.
    """
    with open(path, "rb+") as f:
        size = f.seek(0, os.SEEK_END)
        f.seek(max(0, size - IDENT_SEARCH_BYTES))
        tail = f.read()
        lines = tail.splitlines(keepends=True)
        last = lines[-1] if lines else b""
        if last.rstrip(b"\r\n") == IDENT_LINE.encode():
            return False
        ended = [line for line in lines[-2:] if line.endswith(b"\n")]
        eol = b"\r\n" if ended and ended[-1].endswith(b"\r\n") else b"\n"
        text = b"" if not tail or tail.endswith(b"\n") else eol
        f.write(text + IDENT_LINE.encode() + eol)
        f.flush()
        os.fsync(f.fileno())
    return True


def cmd_dump_config(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    """``dump-config``: the resolved limits as a klipper_estimator config."""
    resolved = resolve_limits(_request(args, None))
    _warn(resolved, err)
    json.dump(dump_config(resolved.limits, resolved.sources), out, indent=2)
    out.write("\n")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `kestimator-compat`; returns the exit status.

    Installs no signal handlers: the program's entry points do (`kestimator.entry`), so a
    library caller keeps its own. A `Terminated` raised under them is 128 + the signal.
    """
    parser = _build_parser()
    args = parser.parse_args(argv)
    out, err = sys.stdout, sys.stderr
    if args.command is None and not args.version:
        parser.print_help(err)
        return EXIT_USAGE
    try:
        if args.version:
            out.write(VERSION_LINE + "\n")
            status = EXIT_OK
        elif args.command == "estimate":
            status = cmd_estimate(args, out, err, getattr(sys.stdin, "buffer", None))
        elif args.command == "post-process":
            status = cmd_post_process(args, out, err)
        else:
            status = cmd_dump_config(args, out, err)
        # Here, not at the interpreter's exit, so a reader that went away is caught below.
        out.flush()
        return status
    except BrokenPipeError:
        # The reader went away (`kestimator-compat estimate F | head`): not our failure, as
        # `kestimator` says (its main). A post-process run has replaced its file by then.
        quiet_stdout()
        return EXIT_OK
    except KestimatorError as exc:
        err.write("kestimator-compat: error: %s\n" % _printable(str(exc)))
        return EXIT_FAILURE
    except KeyboardInterrupt:
        err.write("kestimator-compat: interrupted\n")
        return EXIT_FAILURE
    except MemoryError:
        err.write("kestimator-compat: error: out of memory\n")
        return EXIT_FAILURE
    except Terminated as exc:
        err.write("kestimator-compat: terminated by signal %d\n" % exc.signum)
        return 128 + exc.signum
    except Exception as exc:  # noqa: BLE001 - Moonraker's log gets one line, never a traceback
        # (RecursionError, MemoryError's kin, a bug): the file is untouched (atomic write).
        err.write("kestimator-compat: internal error: %s: %s\n"
                  % (type(exc).__name__, _printable(str(exc))[:MAX_ERROR_CHARS]))
        return EXIT_FAILURE


if __name__ == "__main__":
    from kestimator.entry import run_program

    sys.exit(run_program(main))
