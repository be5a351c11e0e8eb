"""Configuration: pydantic models for the station, run plan, tracking, bus and output.

These models are the single source of truth: defaults, units and validation live here.
``load_config`` reads YAML and turns a validation failure into a ``ConfigError`` that names
the file, the line, the field path, the bad value and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from drivers.config import ArmConfig, CameraConfig, GripperConfig, SimObjectConfig, StrictModel
from orchestrator.zenoh_security import BusAclConfig, BusTlsConfig, check_endpoints
from tdcommon.objects import Category
from tracking.params import TrackingParams

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
DEFAULT_CONFIG = CONFIG_DIR / "mock.yaml"

Speed = Literal["slow", "medium", "fast"]


class ArmSlot(StrictModel):
    """One arm of the station and the gripper mounted on it."""

    arm: ArmConfig
    gripper: GripperConfig


class StationConfig(StrictModel):
    """The hardware: two arms with grippers and one RGB-D camera, with their calibration."""

    name: str = Field("station0", pattern=r"^[A-Za-z0-9_\-]+$", description="used in zenoh keys")
    left: ArmSlot
    right: ArmSlot
    camera: CameraConfig

    @property
    def simulated(self) -> bool:
        """True when any device is simulated (then a simulated object is needed)."""
        devices = (self.left.arm, self.right.arm, self.left.gripper, self.right.gripper, self.camera)
        return any(d.type == "fake" for d in devices)


class ObjectConfig(StrictModel):
    """A deformable object of the plan and the programs run with it."""

    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    category: Category
    programs: list[str] = Field(min_length=1, description="library names or program file paths")
    n_keypoints: int | None = Field(
        None, ge=3, le=400, description="keypoints to track; default by category: 20 (dlo), 25 (bdlo), 36 (cloth 6x6)"
    )
    sim: SimObjectConfig | None = Field(None, description="how the simulator builds it (mock mode)")

    @model_validator(mode="before")
    @classmethod
    def _sim_category_from_object(cls, data: Any) -> Any:  # noqa: ANN401 - raw YAML
        """The simulator builds what the object is: ``sim.category`` defaults to the object's category."""
        if isinstance(data, dict) and isinstance(data.get("sim"), dict) and "category" not in data["sim"]:
            data = {**data, "sim": {**data["sim"], "category": data.get("category")}}
        return data

    @model_validator(mode="after")
    def _sim_matches_category(self) -> ObjectConfig:
        if self.sim is not None:
            if self.sim.category != self.category:
                raise ValueError(
                    f"sim.category {self.sim.category!r} does not match category {self.category!r} "
                    "(leave sim.category out: the simulator builds the object's category)"
                )
        return self


class PlanConfig(StrictModel):
    """What to collect: objects × their programs × speeds × repeats, cut into fixed-length episodes."""

    objects: list[ObjectConfig] = Field(min_length=1)
    speeds: list[Speed] = Field(default=["slow", "medium", "fast"], min_length=1)
    repeats: int = Field(1, ge=1, le=10000)
    fast_duration: float = Field(1.25, ge=1.0, le=1.5, description="seconds per waypoint at 'fast'")
    episode_seconds: float = Field(5.0, gt=0.5, le=600.0, description="length of one episode file, s")
    settle_seconds: float = Field(0.5, ge=0.0, le=10.0, description="rest recorded before each program, s")

    @field_validator("objects")
    @classmethod
    def _unique_names(cls, v: list[ObjectConfig]) -> list[ObjectConfig]:
        names = [o.name for o in v]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"object names must be unique; repeated: {dup}")
        return v


class LiveInitConfig(StrictModel):
    """The paper's per-object initialisation before recording (``orchestrator.liveinit``): the arms at the
    run's start pose (reference P0), a short move of both grippers to a second configuration (P1) and back,
    the worker initialises from the difference, the session checks the result; retried, else the object's
    runs are skipped. Runs only with the session's own tracking worker."""

    enabled: bool = Field(True, description="run the initialisation before each object's first recorded run")
    displacement: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.05), description="the second configuration: both TCPs moved by this vector (world frame), m")
    move_seconds: float = Field(3.0, ge=0.3, le=10.0,
                                description="requested time of each move (out and back; ruckig-timed), s")
    hold_seconds: float = Field(
        2.0, ge=0.2, le=10.0,
        description="rest at the second configuration (P1), s: the worker initialises once the difference "
                    "segmentation stops growing")
    settle_seconds: float = Field(0.5, ge=0.0, le=10.0,
                                  description="rest before the reference P0 and after the move back, s")
    attempts: int = Field(3, ge=1, le=20, description="attempts per object before its runs are skipped")
    check_frames: int = Field(
        5, ge=1, le=300, description="worker results at rest after the move back that the check looks at, frames")
    max_edge_error: float = Field(
        0.15, gt=0.0, le=10.0,
        description="the median edge-length RMSE of the checked results (the messages' abs_mm) must be below this "
                    "fraction of the mean rest edge length (unitless: the same check for any object size)")
    max_gripper_distance_m: float = Field(
        0.04, gt=0.0, le=1.0, description="a keypoint must lie this close to each closed gripper's TCP, m")
    worker_timeout_s: float = Field(
        20.0, gt=0.0, le=3600.0,
        description="wall time the worker may take to answer the reference frames, and to report a result "
                    "after the move back, s")
    on_failure: Literal["skip", "record"] = Field(
        "skip", description="after the last failed attempt: skip the object's runs (journaled skipped, with the "
                            "reason), or record them without a live initialisation")
    reinitialise: bool = Field(
        True, description="initialise again before a later run of the object when the worker restarted or its "
                          "track was lost in the previous run")

    @field_validator("displacement")
    @classmethod
    def _short_move(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        norm = sum(c * c for c in v) ** 0.5
        if not 0.01 <= norm <= 0.15:
            raise ValueError(f"must move the grippers by 0.01-0.15 m (a short move within reach), got {norm:.3f} m")
        return v


class TrackingConfig(StrictModel):
    """The tracking worker and the TrackDeform3D parameters that a lab may tune."""

    enabled: bool = True
    voxel_size: float = Field(TrackingParams.voxel_m, gt=0.0005, le=0.05, description="down-sampling voxel, m")
    solver_iterations: int = Field(TrackingParams.track_iterations, ge=1, le=1000, description="solver sweeps a frame")
    use_anchors: bool = Field(True, description="ablation: anchor constraints")
    use_edge_projection: bool = Field(True, description="ablation: edge-length projection")
    use_cloud_projection: bool = Field(True, description="ablation: projection onto the cloud")
    live_window: int = Field(
        TrackingParams.causal_window, ge=1, le=31, description="causal moving-average window, frames")
    final_window: int = Field(
        TrackingParams.symmetric_window, ge=1, le=31, description="symmetric moving-average window, frames (odd)")
    worker_start_timeout: float = Field(
        90.0, gt=0.0, le=3600.0, description="s a started worker may take to declare its liveliness token")
    worker_max_lag: float = Field(
        15.0, gt=0.0, le=3600.0,
        description="s of camera time the worker's newest keypoints may trail the newest frame before a restart")
    worker_restart_backoff: float = Field(1.0, gt=0.0, le=600.0, description="first restart delay, s; doubles")
    worker_restart_backoff_max: float = Field(30.0, gt=0.0, le=3600.0, description="longest restart delay, s")
    worker_max_restarts: int = Field(20, ge=0, le=100000, description="restarts per session before giving up")
    gap_seconds: float = Field(
        1.0, gt=0.0, le=600.0,
        description="frames without keypoints for at least this long (camera time, s) count as a tracking gap")
    final: bool = Field(True, description="after each run, track its frames offline and add /keypoints/final")
    live_init: LiveInitConfig = Field(default_factory=LiveInitConfig)

    @field_validator("final_window")
    @classmethod
    def _odd(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"must be odd so the window is symmetric, got {v}")
        return v


class BusConfig(StrictModel):
    """The zenoh session: the daemon a router on explicit endpoints, multicast scouting off by default."""

    enabled: bool = True
    prefix: str = Field("trackdeform", pattern=r"^[A-Za-z0-9_\-/]+$")
    mode: Literal["router", "peer", "client"] = Field(
        "router", description="the daemon's zenoh mode: 'router' routes the worker's keypoints to every client; "
        "'client' or 'peer' when it connects to a separate zenohd router. Processes that only connect "
        "(worker, watch, status, ctl) are clients.")
    listen: list[str] = Field(default=["tcp/127.0.0.1:7447"], description="zenoh endpoints to listen on")
    connect: list[str] = Field(default=[], description="zenoh endpoints (peers or a zenohd router)")
    multicast_scouting: bool = False
    health_period: float = Field(1.0, gt=0.0, le=60.0, description="s between <prefix>/<station>/health messages")
    tls: BusTlsConfig | None = Field(None, description="TLS files for tls/ endpoints (several hosts)")
    access_control: BusAclConfig | None = Field(None, description="zenoh ACL: who may put/subscribe on which keys")

    @model_validator(mode="after")
    def _tls_endpoints(self) -> BusConfig:
        check_endpoints(self.tls, self.listen, self.connect)
        return self

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for e in v:
            proto, sep, rest = e.partition("/")
            if not sep or proto not in ("tcp", "udp", "quic", "tls", "unixsock-stream", "ws") or not rest:
                raise ValueError(f"{e!r} is not a zenoh endpoint like 'tcp/127.0.0.1:7447'")
        return v

    def key(self, station: str, *parts: str) -> str:
        """A key expression ``<prefix>/<station>/<parts...>``."""
        return "/".join([self.prefix.strip("/"), station, *parts])


class ColorOutputConfig(StrictModel):
    """How colour is stored: H.264 (foxglove.CompressedVideo), JPEG or raw (see tdrecord.codecs)."""

    codec: Literal["h264", "jpeg", "raw"] = Field("h264", description="h264 (default), jpeg (fallback) or raw rgb8")
    crf: int = Field(18, ge=0, le=51, description="H.264 constant rate factor: lower is better and larger")
    preset: Literal["ultrafast", "superfast", "veryfast", "faster", "fast", "medium"] = Field(
        "ultrafast", description="libx264 speed preset (slower presets: smaller files, more CPU)"
    )
    gop: int = Field(30, ge=1, le=9000, description="frames between H.264 keyframes; every episode starts with one")
    jpeg_quality: int = Field(90, ge=1, le=100, description="JPEG quality (codec jpeg)")


class DepthOutputConfig(StrictModel):
    """How depth is stored, always lossless: 16-bit PNG (foxglove.CompressedImage) or raw 16UC1."""

    codec: Literal["png", "planes", "raw"] = Field(
        "png", description="png (default: 16-bit PNG, which Foxglove draws), planes (about 20 % smaller on noisy "
        "stereo depth; Foxglove opens it but does not draw it) or raw 16UC1; all bit-exact")


class OutputConfig(StrictModel):
    """Where and how episodes are written."""

    directory: Path = Field(Path("runs"), description="episodes go to <directory>/<session>/")
    compression: Literal["zstd", "lz4", "none"] = Field("zstd", description="MCAP chunk compression")
    color: ColorOutputConfig = Field(default_factory=ColorOutputConfig)
    depth: DepthOutputConfig = Field(default_factory=DepthOutputConfig)
    min_free_gb: float = Field(
        2.0, ge=0.0, description="below this free disk space, GiB, no episode opens and the open one closes"
    )
    on_low_disk: Literal["stop", "pause"] = Field(
        "stop", description="below min_free_gb: stop the session, or pause (arms at rest) until space returns"
    )
    disk_check_seconds: float = Field(1.0, gt=0.0, le=60.0, description="free space is checked this often, s")
    low_disk_poll_seconds: float = Field(10.0, gt=0.0, le=600.0, description="paused: check for space this often, s")


class SyncConfig(StrictModel):
    """Camera–arm time sync: frames paired with the joint states at their capture time (orchestrator.timesync)."""

    camera_latency_s: float = Field(
        0.0, ge=0.0, le=1.0,
        description="fixed delay from a frame's capture to its arrival at the host, s, beyond the clock offset "
                    "(timestamps cannot tell it from the offset: measure it once per camera)",
    )
    offset_window_s: float = Field(30.0, ge=2.0, le=3600.0, description="the clock offset and drift are fitted "
                                   "over this much recent device time, s")
    max_pairing_gap_s: float = Field(0.05, gt=0.0, le=1.0, description="a frame with no joint state this close to "
                                     "its capture time is recorded unpaired, s")


class Config(StrictModel):
    """Everything a collection session needs."""

    station: StationConfig
    plan: PlanConfig
    tracking: TrackingConfig = Field(default_factory=TrackingConfig)
    bus: BusConfig = Field(default_factory=BusConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    sync: SyncConfig = Field(default_factory=SyncConfig)
    clock: Literal["real", "sim"] = Field("real", description="'sim': simulated time (tests), fake devices only")

    @model_validator(mode="after")
    def _consistent(self) -> Config:
        if self.station.simulated:
            missing = [o.name for o in self.plan.objects if o.sim is None]
            if missing:
                raise ValueError(f"a simulated station needs plan.objects[*].sim; missing for {missing}")
        elif self.clock == "sim":
            raise ValueError("clock 'sim' needs a simulated station (devices of type 'fake')")
        return self


class ConfigError(ValueError):
    """A config file that cannot be used; the message lists every problem with its location."""


def _line_of(root: yaml.Node | None, loc: tuple[Any, ...]) -> int | None:
    """1-based line of the YAML node at ``loc`` (or of its deepest existing parent)."""
    node, line = root, None
    for key in loc:
        if node is None:
            break
        line = node.start_mark.line + 1
        if isinstance(node, yaml.MappingNode):
            node = next((v for k, v in node.value if k.value == str(key)), None)
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
        else:
            node = None
    if node is not None:
        line = node.start_mark.line + 1
    return line


def _format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def _clean_loc(data: Any, loc: tuple[Any, ...]) -> tuple[Any, ...]:
    """``loc`` without the union tags pydantic inserts (``station.left.arm.fake.lag`` -> ``...arm.lag``)."""
    out, node = [], data
    for part in loc:
        if isinstance(node, dict) and part not in node and node.get("type") == part:
            continue  # discriminated-union tag, not a key of the file
        if isinstance(part, str) and part.startswith("function-"):
            continue
        out.append(part)
        if isinstance(node, dict):
            node = node.get(part)
        elif isinstance(node, list) and isinstance(part, int) and part < len(node):
            node = node[part]
        else:
            node = None
    return tuple(out)


def format_validation_error(
    err: ValidationError, source: str, root: yaml.Node | None = None, data: Any = None
) -> str:
    """One line per problem: ``file:line: field.path: message (got value)``."""
    lines = []
    for e in err.errors():
        loc = _clean_loc(data, tuple(e["loc"]))
        line = _line_of(root, loc) if root is not None else None
        where = f"{source}:{line}" if line else source
        got = e.get("input")
        got_txt = "" if e["type"] == "missing" or isinstance(got, dict) else f" (got {got!r})"
        lines.append(f"{where}: {_format_loc(loc)}: {e['msg']}{got_txt}")
    return "\n".join(lines)


def parse_config(data: Any, source: str = "<config>", root: yaml.Node | None = None) -> Config:
    """Validate a plain dict into a :class:`Config`, raising ConfigError with located messages."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        return Config.model_validate(data)
    except ValidationError as err:
        details = format_validation_error(err, source, root, data)
        raise ConfigError(f"{source}: invalid configuration\n{details}") from None


def load_config(path: str | Path, overrides: dict[str, Any] | None = None) -> Config:
    """Read and validate a YAML config; ``overrides`` are dotted keys set after reading."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start}); a config is a YAML file"
        ) from None
    try:
        root = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML: {e}") from None
    if data is None:
        raise ConfigError(f"{path}: the file is empty")
    for dotted, value in (overrides or {}).items():
        _set_dotted(data, dotted, value)
    return parse_config(data, str(path), root)


def _set_dotted(data: dict, dotted: str, value: Any) -> None:
    node = data
    parts = dotted.split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value
