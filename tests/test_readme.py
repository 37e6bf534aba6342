"""What a newcomer reads first is true: the README's first screen, its first command, its
figures, and the docs a user reads.

The README opens with what kestimator is and a table of measured facts, then one command that
runs on the bundled example from a fresh checkout with nothing installed, then the two set-up
commands (the second is `.ci/run`'s test command). The accuracy table is measured here, on
the corpus against Klipper's own times (klipper_estimator from ../shared/peers, the slicers'
own estimates from the files); the speed table is the "Current figures" table of
benchmarks/RESULTS.md, which the benchmarks named in it produce.
"""

from __future__ import annotations

import json
import lzma
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.cli import _build_parser
from kestimator.durations import format_duration
from kestimator.slicers import detect_file

from .conftest import CORPUS, IN_CI, PROJECT, SHARED
from .test_accuracy_corpus import TOL_ABS_S

README = PROJECT / "README.md"
RESULTS = PROJECT / "benchmarks" / "RESULTS.md"
PEERS = SHARED / "peers"
# How far into the README the first command and the set-up commands must come.
FIRST_SCREEN_LINES = 60
# What users read: no word of how the product was made. Every Markdown file of the project
# (the README links benchmarks/RESULTS.md, the guides link the test references' READMEs);
# not the venv's or a build's.
USER_DOCS = sorted(path for path in PROJECT.rglob("*.md") if not any(
    part.startswith(".") or part in ("build", "node_modules")
    for part in path.relative_to(PROJECT).parts[:-1]))
MAKING_OF = re.compile(r"\b(sessions?|issues?) ?#?\d+|\bsession\b|\bthe issue\b|\bissue's\b",
                       re.IGNORECASE)


def _code_blocks(text: str) -> list[tuple[int, str, str]]:
    """(line number of the opening fence, language, body) of every fenced block."""
    blocks = []
    lines = text.splitlines()
    index = 0
    while index < len(lines):
        if lines[index].startswith("```"):
            start, language = index, lines[index][3:].strip()
            index += 1
            body = []
            while not lines[index].startswith("```"):
                body.append(lines[index])
                index += 1
            blocks.append((start + 1, language, "\n".join(body)))
        index += 1
    return blocks


def _section(text: str, heading: str) -> str:
    start = text.index(heading + "\n")
    end = text.find("\n## ", start + len(heading))
    return text[start:] if end < 0 else text[start:end]


def _table_rows(text: str) -> list[list[str]]:
    """The cells of every row of the first Markdown table in `text`, header row first."""
    rows = []
    for line in text.splitlines():
        if line.startswith("|"):
            if not set(line) <= set("|-: "):
                rows.append([cell.strip() for cell in line.strip("|").split(" | ")])
        elif rows:
            break
    return rows


def test_the_first_screen_says_what_it_is_before_any_command() -> None:
    text = README.read_text()
    blocks = _code_blocks(text)
    intro = text[:text.index("```")]
    assert intro.startswith("# kestimator\n")
    assert "Klipper" in intro and "klipper_estimator" in intro and "slicer" in intro
    assert _table_rows(intro), "the measured facts come before the first command"
    assert [language for _, language, _ in blocks[:3]] == ["sh", "", "sh"]
    assert blocks[2][0] < FIRST_SCREEN_LINES


def test_the_first_command_runs_on_the_example_in_a_fresh_checkout_without_installing(
        tmp_path: Path) -> None:
    """The README's first command, in a copy of what a clone holds, with no kestimator
    installed: it prints the lines the README shows."""
    (_, _, command), (_, _, shown) = _code_blocks(README.read_text())[:2]
    assert "\n" not in command
    words = shlex.split(command)
    assert words[:3] == ["python3", "-m", "kestimator"]
    checkout = tmp_path / "clone"
    # What a clone holds of what the command reads: the package and the examples.
    for name in ("kestimator", "examples"):
        shutil.copytree(PROJECT / name, checkout / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.so", "*.c"))
    env = {key: value for key, value in os.environ.items()
           if not key.startswith(("PYTHON", "KESTIMATOR", "SLIC3R_"))}
    (tmp_path / "home").mkdir()
    env.update(HOME=str(tmp_path / "home"), XDG_CONFIG_HOME=str(tmp_path / "home" / "config"),
               XDG_CACHE_HOME=str(tmp_path / "home" / "cache"))
    # The system's python3 outside any venv, as on a fresh clone; this one when there is none.
    python = shutil.which("python3", path="/usr/bin:/bin") or sys.executable
    probe = subprocess.run([python, "-c", "import kestimator"], cwd=tmp_path / "home", env=env,
                           capture_output=True)
    assert probe.returncode != 0, "kestimator is installed for %s" % python
    proc = subprocess.run([python, *words[1:]], cwd=checkout, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    printed = proc.stdout.splitlines()
    assert shown.splitlines() == printed[:len(shown.splitlines())]
    assert any(line.startswith("  Difference   :") for line in shown.splitlines())


def test_the_readme_gives_two_setup_commands_and_ci_runs_the_second() -> None:
    (_, _, setup) = _code_blocks(README.read_text())[2]
    install, tests = setup.splitlines()
    assert install.startswith("python3 -m venv .venv && .venv/bin/pip install ")
    assert "kestimator inject examples/" in install
    assert tests.startswith("python3 -m venv .venv && ") and tests.endswith(" -m pytest")
    ci_lines = (PROJECT / ".ci" / "run").read_text().rstrip("\n").splitlines()
    assert ci_lines[-1] == tests


def _klipper_estimator_total(program: Path, gcode: Path) -> float:
    proc = subprocess.run(
        [str(program), "--config_file", str(PEERS / "klipper_estimator_corpus.json"),
         "estimate", "-f", "json", str(gcode)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # Its total is the sum of its sequences (it starts one at every dwell or wait).
    return sum(sequence["total_time"] for sequence in json.loads(proc.stdout)["sequences"])


def _percent(error: float) -> str:
    return "%.1f %%" % error if error >= 1 else "%.2f %%" % error


def test_the_accuracy_table_is_what_the_corpus_measures(tmp_path: Path) -> None:
    """Every figure of the README's first table, measured: Klipper's own times (the corpus's
    references), klipper_estimator's and the slicers' estimates of the same files."""
    program = PEERS / "klipper_estimator"
    if not CORPUS.is_dir() or not os.access(program, os.X_OK):
        if IN_CI:
            pytest.fail("the corpus and %s must be beside the checkout" % program)
        pytest.skip("the corpus or klipper_estimator is not beside this checkout")
    references = sorted((CORPUS / "reference").glob("*/*.json"))
    peer: list[tuple[float, float]] = []
    slicer: list[tuple[float, float]] = []
    for path in references:
        reference = json.loads(path.read_text())
        gcode = CORPUS / reference["file"]
        if not gcode.exists():
            gcode = tmp_path / gcode.name
            with lzma.open(CORPUS / (reference["file"] + ".xz")) as packed, \
                    gcode.open("wb") as out:
                shutil.copyfileobj(packed, out)
        truth = reference["total_s"]
        peer.append((abs(_klipper_estimator_total(program, gcode) - truth), truth))
        said = detect_file(gcode).estimate_s
        if said is not None:
            slicer.append((abs(said - truth), truth))

    def row(errors: list[tuple[float, float]]) -> tuple[str, str]:
        median = statistics.median(100 * off / truth for off, truth in errors)
        worst_off, worst_truth = max(errors, key=lambda e: e[0] / e[1])
        return (_percent(median), "%s (%s)" % (_percent(100 * worst_off / worst_truth),
                                             format_duration(worst_off)))

    text = README.read_text()
    header, ours, theirs, slicers = _table_rows(text[:text.index("```")])
    slicer_count = len({path.parent.name for path in references})
    assert header[0] == "Against the time Klipper itself computes (%d files from %d slicers)" % (
        len(references), slicer_count)
    assert ours == ["kestimator", "within %g s" % TOL_ABS_S,
                    "within %g s, every layer too" % TOL_ABS_S]
    assert theirs == ["klipper_estimator 3.7.3", *row(peer)]
    assert slicers == ["the slicer's own estimate (%d of the files carry one)" % len(slicer),
                       *row(slicer)]


def test_the_speed_table_is_the_benchmarks_current_figures() -> None:
    readme = _table_rows(_section(README.read_text(), "## Speed and memory"))
    results = _table_rows(_section(RESULTS.read_text(), "## Current figures"))
    assert readme == results
    assert len(readme) > 5
    for what, figure, source in readme[1:]:
        assert re.search(r"\d", figure), what
        assert re.search(r"\d{4}-\d\d-\d\d", source) or source == "the same run", what


def test_no_word_of_sessions_or_issues_where_users_read() -> None:
    assert {README, RESULTS, PROJECT / "tests" / "oracle_refs" / "README.md",
            PROJECT / "tests" / "frontends" / "README.md"} <= set(USER_DOCS)
    found = []
    for path in USER_DOCS:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            # Other projects' issue trackers may be cited by their address.
            if MAKING_OF.search(re.sub(r"https?://\S+", "", line)):
                found.append("%s:%d: %s" % (path.relative_to(PROJECT), number, line))
    for action in _build_parser()._actions:
        for choice, sub in (getattr(action, "choices", None) or {}).items():
            help_text = sub.format_help()
            if MAKING_OF.search(help_text):
                found.append("kestimator %s --help" % choice)
    assert not found, "\n".join(found)


def test_every_command_line_option_is_documented_in_the_cli_guide() -> None:
    guide = (PROJECT / "docs" / "CLI.md").read_text()
    readme = README.read_text()
    missing = []
    for action in _build_parser()._actions:
        for command, sub in (getattr(action, "choices", None) or {}).items():
            if "`%s`" % command not in readme and "kestimator %s" % command not in readme:
                missing.append("the README does not name `%s`" % command)
            for option in sub._actions:
                flags = [flag for flag in option.option_strings if flag not in ("-h", "--help")]
                if flags and not any(re.search(r"`%s\b" % re.escape(flag), guide)
                                     or re.search(r"\[%s\b" % re.escape(flag), guide)
                                     for flag in flags):
                    missing.append("%s %s" % (command, "/".join(flags)))
    assert not missing, missing


def test_the_readme_names_every_exit_status() -> None:
    from kestimator import cli

    codes = sorted({getattr(cli, name) for name in cli.__all__ if name.startswith("EXIT_")})
    said = _section(README.read_text(), "## Estimate a file")
    for code in codes:
        assert re.search(r"\b%d\b (success|the|a|\(`inject`)" % code, said), code
