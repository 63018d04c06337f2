"""A session's line of the fleet summary: the type the fleet CSV writes and the batch fills."""

from __future__ import annotations

from dataclasses import dataclass, field

from mocap.core.classes import DIG_CLASSES, OTHER

CLASSES = (*DIG_CLASSES, OTHER)


@dataclass(frozen=True)
class SessionSummary:
    """One session's figures: hours recorded, cycles, summed cycle and dig seconds, class
    counts (in `CLASSES` order); `status` ok, partial or failed with `error`; stages run / skipped."""

    session: str
    machine: str
    day: str
    status: str = "ok"
    error: str = ""
    stages_run: int = 0
    stages_skipped: int = 0
    stage_seconds: float = 0.0
    hours: float = float("nan")
    cycles: int = 0
    cycle_seconds: float = 0.0
    dig_seconds: float = 0.0
    classes: tuple[int, ...] = field(default=(0, 0, 0, 0))
    analysed: bool = False

    @property
    def cycles_per_hour(self) -> float:
        return self.cycles / self.hours if self.analysed and self.hours > 0 else float("nan")

    @property
    def mean_cycle_s(self) -> float:
        return self.cycle_seconds / self.cycles if self.cycles else float("nan")

    @property
    def mean_dig_s(self) -> float:
        return self.dig_seconds / self.cycles if self.cycles else float("nan")
