"""ProgressSamples holds samples back in lists and moves them into its arrays in blocks
(kestimator/estimate.py); what it keeps must be what one append per sample keeps."""

from __future__ import annotations

import random
from array import array
from collections import deque

from kestimator.estimate import (
    FIRST_SAMPLE_SPACING_S,
    MAX_SAMPLES,
    TAIL_SAMPLES,
    TAIL_SPACING_S,
    ProgressSamples,
)


class _OneByOne:
    """The samples as ProgressSamples kept them before: every sample appended at once."""

    def __init__(self) -> None:
        self.lines, self.times = array("q"), array("d")
        self.spacing = FIRST_SAMPLE_SPACING_S
        self.next_t = self.next_regular_t = 0.0
        self.tail: deque[tuple[int, float]] = deque(maxlen=TAIL_SAMPLES)

    def add(self, line: int, t: float) -> None:
        if t >= self.next_regular_t:
            if len(self.lines) >= MAX_SAMPLES:
                del self.lines[1::2]
                del self.times[1::2]
                self.spacing *= 2.0
            self.lines.append(line)
            self.times.append(t)
            self.next_regular_t = t + self.spacing
        if self.spacing > TAIL_SPACING_S:
            self.tail.append((line, t))
            self.next_t = min(self.next_regular_t, t + TAIL_SPACING_S)
        else:
            self.next_t = self.next_regular_t


def test_samples_held_back_end_as_those_appended_one_by_one() -> None:
    rng = random.Random(41)
    samples, reference = ProgressSamples(), _OneByOne()
    t = 0.0
    for line in range(1, 1_200_000):
        t += rng.expovariate(1.0 / 0.02)
        if t >= samples.next_t:
            samples.add(line, t)
        if t >= reference.next_t:
            reference.add(line, t)
        assert samples.next_t == reference.next_t
    samples.flush()
    assert reference.spacing > TAIL_SPACING_S and len(reference.tail) == TAIL_SAMPLES
    assert samples.spacing == reference.spacing
    assert samples.lines == reference.lines and samples.times == reference.times
    assert list(zip(samples.tail_lines, samples.tail_times)) == list(reference.tail)
    samples.add_tail(1_200_000, t + 1.0)
    reference.tail.append((1_200_000, t + 1.0))
    assert list(zip(samples.tail_lines, samples.tail_times)) == list(reference.tail)
