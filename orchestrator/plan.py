"""The run plan: the ordered list of (object, program, speed, repeat) items of a session."""

from __future__ import annotations

from dataclasses import dataclass

from orchestrator.config import ObjectConfig, PlanConfig


@dataclass(frozen=True)
class RunItem:
    """One program run: an object, a program, a speed and a repeat number (0-based)."""

    index: int
    object: ObjectConfig
    program: str
    speed: str
    repeat: int

    @property
    def label(self) -> str:
        """Short human label, e.g. ``rope · rope_swing · medium · #2``."""
        return f"{self.object.name} · {self.program} · {self.speed} · #{self.repeat + 1}"


def build_plan(plan: PlanConfig) -> list[RunItem]:
    """Objects × their programs × repeats × speeds, in that nesting (speeds vary fastest)."""
    items: list[RunItem] = []
    for obj in plan.objects:
        for program in obj.programs:
            for repeat in range(plan.repeats):
                for speed in plan.speeds:
                    items.append(RunItem(len(items), obj, program, speed, repeat))
    return items
