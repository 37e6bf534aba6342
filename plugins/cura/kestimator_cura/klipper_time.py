"""One slice's Klipper time, computed once and applied at save; no Cura needed.

Owns the unit of work the Cura-facing layer runs in the background when slicing finishes
(`compute`: limits, pass 1 and pass 2 over a snapshot of the chunk list) and at save time
(`apply_to`: put the rewritten chunks into Cura's own list, in place), plus the text shown
to the user. A result applies only to the exact chunks it was computed from (`matches`):
when anything changed them since (a post-processing script, a new slice), it is computed
again from what is there now.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

from kestimator.api import format_duration

from .chunks import ChunkPlan, file_ends, plan_chunks, rewrite_chunks, same_chunks
from .machine import ChosenLimits, LimitsChoice, choose_limits

MAX_NOTES_SHOWN = 3


@dataclasses.dataclass(frozen=True)
class Outcome:
    """Klipper's times for one chunk list and that list rewritten."""

    source_chunks: tuple[str, ...]
    rewritten: tuple[str, ...]
    plan: ChunkPlan
    limits: ChosenLimits

    @property
    def total_s(self) -> float:
        """Klipper's print time in seconds."""
        return self.plan.total_s

    def matches(self, chunks: Sequence[str]) -> bool:
        """True if ``chunks`` are the very chunks this was computed from."""
        return same_chunks(chunks, self.source_chunks)

    def apply_to(self, gcode_list: list[str], source: Sequence[str] | None = None) -> None:
        """Write the rewritten chunks into Cura's list in place (same list, same length).

        ``source``: what the list stands for when it no longer holds those chunks itself
        (it holds what an earlier save wrote into it); by default the list itself.
        """
        if len(gcode_list) != len(self.rewritten) or not self.matches(
                gcode_list if source is None else source):
            raise ValueError("the G-code changed since its Klipper time was computed")
        for index, chunk in enumerate(self.rewritten):
            if gcode_list[index] is not chunk:
                gcode_list[index] = chunk

    def summary(self, in_panel: bool = False, cura_estimate_s: float | None = None) -> str:
        """What the user reads in Cura. ``in_panel``: Cura's panel shows Klipper's time;
        ``cura_estimate_s``: what the panel showed before (else the G-code's ``;TIME:``)."""
        est = self.plan.estimate
        lines = ["Klipper print time: %s" % format_duration(self.total_s)]
        parts = est.parts
        if est.timed_parts:
            lines[0] += " until the part is done"
            lines.append("Motion %s (Klipper's planner) + macros and prep %s: %s." % (
                format_duration(parts.motion_s), format_duration(parts.added_s),
                ", ".join("%s x%d %s (%s)" % (p.name, p.count, format_duration(p.seconds),
                                              p.source) for p in est.timed_parts)))
            if parts.before_first_extrusion_s:
                lines.append("%s of it before the first extrusion: not in the time the "
                             "printer's web page counts down." % format_duration(
                                 parts.before_first_extrusion_s))
        slicer_s = cura_estimate_s if cura_estimate_s else self.plan.slicer_estimate_s
        motion_s = parts.motion_s
        if slicer_s is not None and motion_s > 0:
            lines.append("Cura estimated %s (%+.0f %%)." % (
                format_duration(slicer_s), 100.0 * (slicer_s - motion_s) / motion_s))
        if est.untimed_macros:
            lines.append("No time known (0 s) for: %s." % ", ".join(
                "%s x%d" % kv for kv in est.untimed_macros.items()))
        first_layer_s = est.first_layer_s
        if first_layer_s is not None:
            lines.append("First layer: %s." % format_duration(first_layer_s))
        lines.append("Limits: %s." % self.limits.source)
        lines.extend(self.limits.notes[:MAX_NOTES_SHOWN])
        if in_panel:
            lines.append("Cura's print information shows Klipper's time.")
        lines.append("Saved G-code gets M73 progress and these times.")
        return "\n".join(lines)


PANEL_OTHER_FEATURE = "none"
"""The feature Cura's panel files time under when the engine gave no breakdown."""


def klipper_feature_times(cura_times: Mapping[str, float],
                          total_s: float) -> dict[str, float]:
    """Cura's seconds per feature (as the engine reports them) scaled so that they add up to
    Klipper's ``total_s``: the panel's total is Klipper's, its breakdown keeps Cura's
    proportions. The largest feature takes the rounding remainder, so the sum is exact."""
    usable = {key: float(value) for key, value in cura_times.items()
              if value == value and float(value) > 0.0}
    result = {key: 0.0 for key in cura_times}
    cura_total = sum(usable.values())
    if cura_total <= 0.0:
        result[PANEL_OTHER_FEATURE] = total_s
        return result
    scale = total_s / cura_total
    for key, value in usable.items():
        result[key] = value * scale
    largest = max(usable, key=lambda key: usable[key])
    result[largest] = total_s - sum(value for key, value in result.items() if key != largest)
    return result


def compute(chunks: Sequence[str], choice: LimitsChoice, settings: Mapping[str, object],
            environ: Mapping[str, str] | None = None) -> Outcome:
    """Limits, estimate and rewrite for ``chunks`` (seconds of work: run it off the GUI
    thread). Raises KestimatorError when the limits or the G-code cannot be used."""
    snapshot = tuple(chunks)
    limits = choose_limits(choice, settings, *file_ends(snapshot), environ=environ)
    plan = plan_chunks(snapshot, limits.limits, limits.marker_source, limits.macros)
    rewritten = rewrite_chunks(snapshot, plan.plan)
    return Outcome(source_chunks=snapshot, rewritten=tuple(rewritten), plan=plan,
                   limits=limits)
