"""Dual-arm waypoint programs: the versioned file format, loading with located errors, saving.

A program is a list of joint-space waypoints for the ``left`` and ``right`` Panda (rad, (7,) each)
with the gripper state to hold at each waypoint. The arms move rest to rest from waypoint to
waypoint; ``trajectories.timing`` gives every segment its duration.

File format ``trackdeform-program/1`` (YAML or JSON)::

    format: trackdeform-program/1
    name: rope_swing
    description: ...
    category: dlo            # dlo | bdlo | cloth | any
    arms: [left, right]
    waypoints:
      - left:  [q1, ..., q7]          # rad
        right: [q1, ..., q7]
        grippers: {left: closed, right: {state: closed, width: 0.01, force: 20}}
        duration: 3.0                  # optional, s: overrides the speed profile for the move here
        speed_scale: 0.5               # optional: the move here takes profile duration / speed_scale
        dwell: 0.5                     # optional, s: hold still after arriving (e.g. let a gripper close)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

FORMAT = "trackdeform-program/1"
ARMS: tuple[str, str] = ("left", "right")
MAX_WIDTH = 0.08  # m, Franka hand opening
MAX_FORCE = 70.0  # N, Franka hand continuous force


class ProgramError(ValueError):
    """A program file that cannot be used; the message names the file, waypoint and joint."""


class ProgramUnreadable(ProgramError):
    """A program file that cannot be read at all (missing, not UTF-8, not YAML/JSON); the message names it."""


class GripperCommand(BaseModel):
    """What a gripper does at a waypoint: ``open`` or ``closed``, optional width (m) and force (N)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    state: Literal["open", "closed"]
    width: Annotated[float, Field(ge=0.0, le=MAX_WIDTH)] | None = None
    force: Annotated[float, Field(gt=0.0, le=MAX_FORCE)] | None = None

    def same_as(self, other: GripperCommand) -> bool:
        """True when the command would not change the gripper."""
        return self == other


JointVector = Annotated[list[float], Field(min_length=7, max_length=7)]


class Waypoint(BaseModel):
    """One dual-arm waypoint: joints (rad) of both arms and the gripper commands held there."""

    model_config = ConfigDict(extra="forbid")

    left: JointVector
    right: JointVector
    grippers: dict[Literal["left", "right"], GripperCommand] = Field(default_factory=dict)
    duration: Annotated[float, Field(gt=0.0, le=60.0)] | None = None
    speed_scale: Annotated[float, Field(gt=0.0, le=2.0)] = 1.0
    dwell: Annotated[float, Field(ge=0.0, le=60.0)] = 0.0

    @field_validator("grippers", mode="before")
    @classmethod
    def _short_form(cls, v: Any) -> Any:  # noqa: ANN401 - raw YAML
        """Accept ``open`` / ``closed`` strings as shorthand for ``{state: ...}``."""
        if isinstance(v, dict):
            return {k: ({"state": g} if isinstance(g, str) else g) for k, g in v.items()}
        return v

    @field_validator("left", "right")
    @classmethod
    def _finite(cls, v: list[float]) -> list[float]:
        if not np.all(np.isfinite(v)):
            raise ValueError("joint values must be finite")
        return v

    def q(self) -> np.ndarray:
        """(14,) float64 rad: left joints then right joints."""
        return np.asarray(self.left + self.right, dtype=np.float64)


class Program(BaseModel):
    """A versioned dual-arm waypoint program."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["trackdeform-program/1"] = FORMAT
    name: Annotated[str, Field(min_length=1)]
    description: str = ""
    category: Literal["dlo", "bdlo", "cloth", "any"] = "any"
    arms: list[Literal["left", "right"]] = Field(default_factory=lambda: list(ARMS))
    waypoints: Annotated[list[Waypoint], Field(min_length=1)]

    @model_validator(mode="after")
    def _dual_arm(self) -> Program:
        if tuple(self.arms) != ARMS:
            raise ValueError(f"format {FORMAT} supports the station arms [left, right], got {self.arms}")
        return self

    def q(self) -> np.ndarray:
        """(W, 14) float64 rad: every waypoint, left joints then right joints."""
        return np.stack([w.q() for w in self.waypoints])

    def gripper_states(self) -> list[dict[str, GripperCommand]]:
        """Gripper command of each arm at each waypoint, carried forward where a waypoint omits one.

        Before the first explicit command a gripper is taken as ``open``.
        """
        state = {a: GripperCommand(state="open") for a in ARMS}
        out = []
        for w in self.waypoints:
            state = {**state, **w.grippers}
            out.append(dict(state))
        return out


def limit_violations(program: Program, margin: float = 0.0) -> list[str]:
    """Every waypoint joint outside the Panda's position limits (shrunk by ``margin`` rad), as messages."""
    from tdcommon.robot import joint_limits

    lim = joint_limits()
    lo, hi = lim["lower"] + margin, lim["upper"] - margin
    out = []
    for i, w in enumerate(program.waypoints):
        for arm in ARMS:
            q = np.asarray(getattr(w, arm))
            for j in np.flatnonzero(q > hi):
                out.append(f"waypoints[{i}].{arm}[{j}] = {q[j]:.4g} rad is above the Panda limit {hi[j]:.4f}")
            for j in np.flatnonzero(q < lo):
                out.append(f"waypoints[{i}].{arm}[{j}] = {q[j]:.4g} rad is below the Panda limit {lo[j]:.4f}")
    return out


def _loc(loc: tuple) -> str:
    """Pydantic error location as ``waypoints[3].left[5]``."""
    s = ""
    for p in loc:
        s += f"[{p}]" if isinstance(p, int) else (f".{p}" if s else str(p))
    return s or "<root>"


def parse_program(data: Any, source: str = "<program>") -> Program:  # noqa: ANN401 - raw YAML/JSON
    """Validate raw YAML/JSON data; raise ProgramError naming ``source``, waypoint and joint."""
    if not isinstance(data, dict):
        raise ProgramError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    fmt = data.get("format")
    if fmt != FORMAT:
        raise ProgramError(f"{source}: format is {fmt!r}, expected {FORMAT!r}")
    try:
        program = Program.model_validate(data)
    except ValidationError as e:
        msgs = [f"{source}: {_loc(err['loc'])}: {err['msg']}" for err in e.errors()]
        raise ProgramError("\n".join(msgs)) from None
    bad = limit_violations(program)
    if bad:
        raise ProgramError("\n".join(f"{source}: {m}" for m in bad))
    return program


def load_program(path: str | Path) -> Program:
    """Load and validate a program file (.yaml/.yml/.json); errors name the file, waypoint and joint."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ProgramUnreadable(f"{path}: cannot read: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ProgramUnreadable(
            f"{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start}); "
            "a program is a YAML or JSON file"
        ) from None
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (yaml.YAMLError, json.JSONDecodeError) as e:
        raise ProgramUnreadable(
            f"{path.name}: not valid {'JSON' if path.suffix == '.json' else 'YAML'}: {e}"
        ) from None
    return parse_program(data, path.name)


def save_program(program: Program, path: str | Path) -> None:
    """Write ``program`` as YAML (or JSON for a .json path), joint values rounded to 1e-6 rad."""
    path = Path(path)
    data = program.model_dump(mode="json", exclude_defaults=False)
    data["format"] = FORMAT
    for w, raw in zip(program.waypoints, data["waypoints"], strict=True):
        raw["left"] = [round(float(x), 6) for x in w.left]
        raw["right"] = [round(float(x), 6) for x in w.right]
        raw["grippers"] = {
            k: (g.state if g.width is None and g.force is None else g.model_dump(exclude_none=True))
            for k, g in w.grippers.items()
        }
        if not raw["grippers"]:
            raw.pop("grippers")
        for key, default in (("duration", None), ("speed_scale", 1.0), ("dwell", 0.0)):
            if raw.get(key) == default:
                raw.pop(key, None)
    if path.suffix == ".json":
        path.write_text(json.dumps(data, indent=2) + "\n")
    else:
        path.write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120))


LIBRARY_DIR = Path(__file__).resolve().parent / "library"


def list_library() -> list[str]:
    """Names of the shipped programs (``trajectories/library/*.yaml`` and ``*.json``), sorted."""
    return sorted({p.stem for p in LIBRARY_DIR.glob("*.yaml")} | {p.stem for p in LIBRARY_DIR.glob("*.json")})


def library_path(name: str) -> Path:
    """Path of the shipped program ``name`` (e.g. ``rope_swing``): its ``.yaml``, else its ``.json``."""
    for suffix in (".yaml", ".json"):
        p = LIBRARY_DIR / f"{name}{suffix}"
        if p.is_file():
            return p
    raise ProgramError(f"no library program {name!r}; available: {', '.join(list_library()) or 'none'}")


def resolve_program(ref: str | Path, base: Path | None = None) -> Path:
    """The program file ``ref`` names: a file (absolute, else relative to ``base`` and then to the working
    folder) or, when no such file exists and ``ref`` is a bare name, the library program of that name.

    The one resolver of the project: the CLI, the session and the journal's plan fingerprint all use it.
    """
    p = Path(ref)
    candidates = [p] if p.is_absolute() else ([base / p] if base is not None else []) + [p]
    for c in candidates:
        if c.is_file():
            return c
    if p.suffix == "" and p.parent == Path("."):
        return library_path(str(ref))
    raise ProgramError(f"{ref}: no such file (and not a library name: {', '.join(list_library())})")
