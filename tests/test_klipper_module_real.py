"""The Klipper module in real Klipper: virtual-SD prints of corpus files from five slicers
in the oracle's Klipper (batch mode, tests/klipper_module/run_print.py), the module's
remaining time sampled at 12+ points and compared with the time Klipper then really took
to the end. Runs where the oracle's Klipper is set up (.ci/klipper-setup builds it from
../shared/upstream; CI always has it, elsewhere these skip without it). The module's logic also runs
without Klipper in tests/test_klipper_module.py."""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "klipper_module"))
import run_print  # noqa: E402

from tests.conftest import require_klipper  # noqa: E402

CORPUS = Path(run_print.SHARED) / "corpus" / "gcode"
FILES = {
    "prusaslicer": "prusaslicer/ps25_nut_accelA_small.gcode",
    "orcaslicer": "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode",
    "superslicer": "superslicer/cancelobj_ss2.4_inverted_pyramid.gcode",
    "slic3r": "slic3r/cancelobj_slic3r1.3.1dev.gcode",
    "cura": "cura/cancelobj_cura5.0.0_inverted_pyramid.gcode",
    "ideamaker": "ideamaker/cancelobj_ideamaker4.2.0.gcode",
}
# The bars (run_print's): plain prints 0.5 s + 0.2 %; after a change 1 s + 1 %.
PLAIN_ABS, PLAIN_REL = run_print.PLAIN_ABS, run_print.PLAIN_REL
CHANGED_ABS, CHANGED_REL = run_print.CHANGED_ABS, run_print.CHANGED_REL
ANSWER_WITHIN_S = run_print.ANSWER_WITHIN_S



@pytest.fixture(autouse=True)
def _klipper() -> None:
    require_klipper()


def _print(tmp_path: Path, slicer: str, **kw: Any) -> dict[str, Any]:
    result = run_print.run_print(str(CORPUS / FILES[slicer]), str(tmp_path), **kw)
    assert result["kestimator_error"] is None
    assert result["errors"] == []
    # Klipper's own times are those of a real printer: no look-ahead run dry by batch mode.
    assert result["n_runout_flushes"] == 0
    assert len(result["samples"]) >= 10
    return result


@pytest.mark.parametrize("slicer", sorted(FILES))
def test_remaining_time_follows_klipper_through_a_plain_print(tmp_path: Path,
                                                              slicer: str) -> None:
    result = _print(tmp_path, slicer)
    assert run_print.samples_off_bar(result["samples"], PLAIN_ABS, PLAIN_REL) == []
    assert {s["source"] for s in result["samples"]} == {"estimate"}


@pytest.mark.parametrize("slicer", ["prusaslicer", "cura", "orcaslicer"])
def test_an_injected_table_starts_at_once_and_is_as_true(tmp_path: Path, slicer: str) -> None:
    result = _print(tmp_path, slicer, inject=True)
    assert {s["source"] for s in result["samples"]} == {"table"}
    assert run_print.samples_off_bar(result["samples"], PLAIN_ABS, PLAIN_REL) == []


@pytest.mark.parametrize("slicer", ["cura", "prusaslicer"])
def test_a_velocity_limit_typed_mid_print_is_re_estimated(tmp_path: Path, slicer: str) -> None:
    """Mainsail's and Fluidd's limit sliders send SET_VELOCITY_LIMIT."""
    result = _print(tmp_path, slicer, users=[
        (0.4, "SET_VELOCITY_LIMIT ACCEL=700 SQUARE_CORNER_VELOCITY=2")])
    after = run_print.samples_after_change(result, ANSWER_WITHIN_S)
    assert len(after) >= 5
    assert run_print.samples_off_bar(after, CHANGED_ABS, CHANGED_REL) == []


@pytest.mark.parametrize("slicer", sorted(FILES))
@pytest.mark.parametrize("factor", [50, 150])
def test_a_speed_change_typed_mid_print_is_re_estimated(tmp_path: Path, slicer: str,
                                                        factor: int) -> None:
    result = _print(tmp_path, slicer, users=[(0.4, "M220 S%d" % factor)])
    after = run_print.samples_after_change(result, ANSWER_WITHIN_S)
    assert len(after) >= 5
    assert run_print.samples_off_bar(after, CHANGED_ABS, CHANGED_REL) == []


# Files with several objects, labelled as Moonraker labels them (preprocess_cancellation;
# tests/exclude_refs/runs.py), and the OrcaSlicer file that labels its one object.
LABELLED = {
    "orcaslicer": "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode",
    "prusaslicer": "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode",
    "superslicer": "superslicer/cancelobj_ss2.4_inverted_pyramid.gcode",
    "slic3r": "slic3r/cancelobj_slic3r1.3.1dev.gcode",
    "cura": "cura/cancelobj_cura4.10.0.gcode",
    "ideamaker": "ideamaker/cancelobj_ideamaker4.2.0.gcode",
}


def _labelled(tmp_path: Path, slicer: str) -> tuple[Path, list[str]]:
    sys.path.insert(0, str(Path(__file__).parent / "exclude_refs"))
    import runs

    source = CORPUS / LABELLED[slicer]
    data = source.read_bytes() if b"EXCLUDE_OBJECT_DEFINE" in source.read_bytes() \
        else runs.label(source)
    path = tmp_path / source.name
    path.write_bytes(data)
    names = [line.split(b"NAME=")[1].split()[0].decode()
             for line in data.split(b"\n") if line.startswith(b"EXCLUDE_OBJECT_DEFINE")]
    return path, names


@pytest.mark.parametrize("slicer", sorted(LABELLED))
def test_an_object_excluded_mid_print_is_re_estimated(tmp_path: Path, slicer: str) -> None:
    pytest.importorskip("preprocess_cancellation")
    path, names = _labelled(tmp_path, slicer)
    assert names
    work = tmp_path / "print"
    result = run_print.run_print(str(path), str(work),
                                 users=[(0.45, "EXCLUDE_OBJECT NAME=%s" % names[-1])])
    assert result["kestimator_error"] is None and result["errors"] == []
    assert result["n_runout_flushes"] == 0
    after = run_print.samples_after_change(result, ANSWER_WITHIN_S)
    assert len(after) >= 5
    assert run_print.samples_off_bar(after, CHANGED_ABS, CHANGED_REL) == []
    # The excluded object has nothing left; the others still have their time (per-object
    # times are taken at layer markers: the Slic3r 1.3 file has none).
    for sample in after:
        if slicer == "slic3r":
            assert sample["objects"] == {}
            continue
        left = {name.upper(): t for name, t in sample["objects"].items()}
        assert left[names[-1].upper()] == 0.
        if len(names) > 1 and sample["truth_s"] > 10.:
            assert sum(left.values()) > 0.


def test_the_guides_macro_shows_the_remaining_time_in_real_klipper(tmp_path: Path) -> None:
    """plugins/klipper/README.md's macros, as written there, in Klipper's config: Klipper
    loads them, and SHOW_REMAINING puts the module's remaining time in the display
    message."""
    guide = (Path(run_print.ROOT) / "plugins" / "klipper" / "README.md").read_text()
    marker = "# Show the true remaining time"
    block = marker + guide.split("```ini\n" + marker)[1].split("```")[0]
    result = run_print.run_print(str(CORPUS / FILES["prusaslicer"]), str(tmp_path),
                                 users=[(0.5, "SHOW_REMAINING")],
                                 extra_cfg="[respond]\n\n" + block)
    assert result["kestimator_error"] is None and result["errors"] == []
    (user,) = result["users"]
    left = int(user["remaining_s"])
    assert user["message"] == "%dh%02dm left" % (left // 3600, (left % 3600) // 60)


@pytest.mark.parametrize("mode", ["garbage", "huge"])
def test_a_worker_that_answers_garbage_cannot_stop_klipper(tmp_path: Path, mode: str) -> None:
    """A worker that writes a line that is not JSON, or one over the answer limit: in
    real Klipper the fd callback raised into the reactor ("Unhandled exception during
    run", printer shutdown). Klipper finishes the print; the module says why it has no
    time."""
    fake = tmp_path / "python"
    fake.write_text("#!/bin/sh\nexec '%s' '%s' %s\n" % (
        sys.executable, os.path.join(run_print.HERE, "fake_worker.py"), mode))
    fake.chmod(0o755)
    result = run_print.run_print(str(CORPUS / FILES["prusaslicer"]), str(tmp_path / "print"),
                                 samples=3, python=str(fake))
    assert result["errors"] == []
    assert len(result["samples"]) >= 3
    error = result["kestimator_error"] or ""
    assert ("not JSON" if mode == "garbage" else "too large") in error
    log = (tmp_path / "print" / "klippy.log").read_text(errors="replace")
    assert "Unhandled exception" not in log and "Transition to shutdown" not in log


def test_a_worker_killed_mid_print_is_started_again_and_the_time_comes_back(
        tmp_path: Path) -> None:
    """The worker killed (the OOM killer on a small board), then a speed change typed:
    Klipper prints on, and the module estimates again with a new worker."""
    result = _print(tmp_path, "prusaslicer", users=[(0.3, "KTEST_KILL_WORKER"),
                                                    (0.4, "M220 S150")])
    kill, change = result["users"]
    assert change["asked"] and change["answered"]
    change_t = next(s["print_time"] for s in result["samples"]
                    if s["position"] >= change["position"])
    after = [s for s in result["samples"] if s["print_time"] >= change_t]
    assert len(after) >= 5
    assert run_print.samples_off_bar(after, CHANGED_ABS, CHANGED_REL) == []
    assert {s["source"] for s in after} == {"estimate"}


def test_a_storm_of_speed_changes_leaves_one_exact_answer(tmp_path: Path) -> None:
    """A macro loop types 300 M220s (a pipe holds about 72 requests): the module asks
    for the latest state only, Klipper prints on, and the time after it is exact."""
    storm = ("[gcode_macro STORM]\ngcode:\n  {% for i in range(300) %}\n"
             "  M220 S{100 + (i % 60)}\n  {% endfor %}\n  M220 S150\n")
    result = run_print.run_print(str(CORPUS / FILES["cura"]), str(tmp_path),
                                 users=[(0.4, "STORM")], extra_cfg=storm)
    assert result["kestimator_error"] is None and result["errors"] == []
    (user,) = result["users"]
    assert user["asked"] and user["answered"]
    assert user["answer_wait_s"] < ANSWER_WITHIN_S
    after = run_print.samples_after_change(result, ANSWER_WITHIN_S)
    assert len(after) >= 5
    assert run_print.samples_off_bar(after, CHANGED_ABS, CHANGED_REL) == []


@pytest.mark.parametrize("forgery", ["huge_table", "negative_time"])
def test_a_hostile_table_in_the_file_is_refused_and_klipper_prints_on(
        tmp_path: Path, forgery: str) -> None:
    """A table declaring 4,000 objects x 4,000 points (16 KB compressed; it once made the
    worker take 1.1 GB), or an object with -1,000,000 s left: the worker refuses it and
    estimates the file instead, within its memory bound; the time is exact."""
    from tests.table_forgery import forge_payload, forged_block, huge_table_payload

    def forge(path: str) -> None:
        data = Path(path).read_bytes()
        size = len(data)
        payload = (huge_table_payload(size) if forgery == "huge_table" else forge_payload(
            size, 100_000, [(0, 0), (size, 100_000)], names=[b"A"], object_offsets=[0],
            remaining_ms=[[-1_000_000_000]]))
        Path(path).write_bytes(data + forged_block(payload, size))
    result = _print(tmp_path, "prusaslicer", finish_file=forge)
    assert {s["source"] for s in result["samples"]} == {"estimate"}
    assert run_print.samples_off_bar(result["samples"], PLAIN_ABS, PLAIN_REL) == []
    assert result["memory_kib"]["worker"]["VmHWM"] < 300 * 1024
