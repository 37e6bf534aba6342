"""The guides users read say what the code does.

- plugins/moonraker/README.md names every option `install.sh --help` lists;
- the two slicer guides say the same of the zipapp's Python: the version its guard checks
  (tools/build_zipapp.py MIN_PYTHON), macOS's own /usr/bin/python3 included, never "too old";
- each slicer guide names the G-code flavor menu the sliced-for-another-firmware line names;
- docs/CLI.md documents every option `kestimator inject --help` offers, --no-layer-info too.
"""

from __future__ import annotations

import re
import subprocess

import pytest

from kestimator import cli
from kestimator.slicers.prusaslicer import FLAVOUR_MENU, SLIC3R_FLAVOUR_MENU

from .conftest import PROJECT

SLICER_GUIDES = (PROJECT / "plugins" / "prusaslicer" / "README.md",
                 PROJECT / "plugins" / "orca" / "README.md")


def _build_zipapp_min_python() -> tuple[int, int]:
    text = (PROJECT / "tools" / "build_zipapp.py").read_text()
    match = re.search(r"^MIN_PYTHON = \((\d+), (\d+)\)$", text, re.MULTILINE)
    assert match is not None
    return int(match.group(1)), int(match.group(2))


def test_the_moonraker_guide_names_every_option_of_install_sh() -> None:
    usage = subprocess.run(["bash", str(PROJECT / "install.sh"), "--help"],
                           capture_output=True, text=True, timeout=60)
    assert usage.returncode == 0, usage.stderr
    options = set(re.findall(r"^  (-{1,2}[a-z][a-z-]*)", usage.stdout, re.MULTILINE))
    assert {"--frontend-settings", "--moonraker", "--uninstall", "-d", "-k"} <= options
    guide = (PROJECT / "plugins" / "moonraker" / "README.md").read_text()
    assert [option for option in sorted(options) if "`%s" % option not in guide] == []


@pytest.mark.parametrize("guide", SLICER_GUIDES, ids=lambda p: p.parent.name)
def test_the_slicer_guides_agree_on_the_zipapps_python(guide: object) -> None:
    text = guide.read_text()  # type: ignore[attr-defined]
    oldest = "%d.%d" % _build_zipapp_min_python()
    assert "any `python3` %s or newer runs it" % oldest in text
    assert "too old" not in text
    assert "macOS's own `/usr/bin/python3` (%s) included" % oldest in text
    assert "/usr/bin/python3 /Users/you/kestimator.pyz inject" in text


def test_each_slicer_guide_names_the_flavor_menu_the_warning_names() -> None:
    prusa, orca = (guide.read_text() for guide in SLICER_GUIDES)
    assert SLIC3R_FLAVOUR_MENU.replace(" > ", " → ") in prusa
    assert FLAVOUR_MENU["OrcaSlicer"].replace(" > ", " → ") in orca


def test_docs_cli_documents_every_inject_option() -> None:
    inject = cli._command_parser(cli._build_parser(), "inject")
    assert inject is not None
    docs = (PROJECT / "docs" / "CLI.md").read_text()
    undocumented = [action.option_strings for action in inject._actions
                    if action.option_strings and action.help != "==SUPPRESS=="
                    and action.dest != "help"
                    and not any(re.search(r"`[^`\n]*%s\b" % re.escape(option), docs)
                                for option in action.option_strings)]
    assert undocumented == []
    assert "`--no-layer-info` adds none" in docs
