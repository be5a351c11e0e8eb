"""Safety checks of a timed dual-arm program before any motion.

Along the whole trajectory sampled at ``rate_hz`` (50 Hz by default), not only at waypoints:

- joint position and velocity limits (the Panda's published limits);
- self-collision of each arm and collision between the two arms, with pinocchio's collision
  model of the Panda (``example_robot_data``), meshes replaced by their convex hulls
  (conservative, and GJK on hulls is fast); pairs on the same or adjacent links and pairs
  already touching at the home pose are skipped; a bounding-sphere pre-pass keeps coal to the
  few pairs that are close;
- every link above the table top (links touching it at home, the bases, excepted);
- both TCPs inside a workspace box, and above the table by ``Workspace.lower[2]`` (0.02 m);
- the start state: within limits and where the trajectory starts.

``check_program(timed, bases, workspace)`` returns a ``SafetyReport``; each violation names the
time, the segment and what, e.g. ``t=3.20 s (segment 1 (move to waypoint 1)): left panda_link5
collides with right panda_hand``. Consecutive samples with the same fault are one violation.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from tdcommon.robot import HOME_Q, N_JOINTS, TCP_FRAME, joint_limits
from trajectories.timing import TimedProgram

HOME = np.array(HOME_Q)
ARM_NAMES = ("left", "right")
MOCK_BASES: dict[str, np.ndarray] = {
    "left": np.array([[1, 0, 0, 0], [0, 1, 0, 0.45], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64),
    "right": np.array([[1, 0, 0, 0], [0, 1, 0, -0.45], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64),
}


@dataclass(frozen=True)
class Workspace:
    """Box the TCPs must stay in (world frame, m); ``lower[2]`` is the clearance above the table."""

    lower: tuple[float, float, float] = (-0.2, -0.9, 0.02)
    upper: tuple[float, float, float] = (1.0, 0.9, 1.2)
    table_z: float = 0.0  # m, table top; no link may go below it
    collision_margin: float = 0.005  # m, two bodies closer than this collide


@dataclass(frozen=True)
class Violation:
    """One safety fault over a run of samples: kind, first/last time (s), segment index, message."""

    kind: str  # start | joint_limit | velocity_limit | self_collision | arm_collision | table | workspace
    time: float
    until: float
    segment: int
    message: str

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class SafetyReport:
    """Result of ``check_program``: ``ok`` when there is no violation."""

    violations: tuple[Violation, ...] = field(default_factory=tuple)
    samples: int = 0
    rate_hz: float = 0.0

    @property
    def ok(self) -> bool:
        """True when the program may run."""
        return not self.violations

    def summary(self) -> str:
        """Multi-line human-readable report."""
        if self.ok:
            return f"safe: {self.samples} samples at {self.rate_hz:g} Hz checked"
        return "\n".join(str(v) for v in self.violations)


def _pretty(geom_name: str) -> str:
    """``left/panda_link5_0`` -> ``left panda_link5``."""
    arm, _, rest = geom_name.partition("/")
    return f"{arm} {rest.rsplit('_', 1)[0]}"


@dataclass
class _DualModel:
    """Both Pandas in one pinocchio model (q = left 7 + 2 fingers, right 7 + 2 fingers) with hull geometry."""

    model: object
    data: object
    geom: object
    gdata: object
    tcp_frames: tuple[int, int]
    pairs: np.ndarray  # (P, 2) geometry indices checked
    pair_kind: list[str]  # self_collision | arm_collision
    sphere_center: np.ndarray  # (G, 3) local bounding-sphere centres (geometry frame)
    sphere_radius: np.ndarray  # (G,)
    hull_points: list[np.ndarray]  # per geometry (Np, 3), geometry frame
    table_geoms: np.ndarray  # geometry indices checked against the table
    margin: float

    def q_full(self, q14: np.ndarray) -> np.ndarray:
        """(18,) pinocchio configuration from (14,) arm joints, fingers open."""
        f = np.full(2, 0.04)
        return np.concatenate([q14[:7], f, q14[7:], f])

    def placements(self, q14: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World placements (G, 4, 4) of every geometry and TCP positions (2, 3) at joints (14,)."""
        import pinocchio as pin

        pin.forwardKinematics(self.model, self.data, self.q_full(q14))
        pin.updateGeometryPlacements(self.model, self.data, self.geom, self.gdata)
        tcp = np.stack([pin.updateFramePlacement(self.model, self.data, f).translation for f in self.tcp_frames])
        return np.stack([m.homogeneous for m in self.gdata.oMg]), tcp

    def collide(self, q14: np.ndarray, pair_ids: np.ndarray) -> np.ndarray:
        """Subset of ``pair_ids`` (indices into ``pairs``) in collision at joints (14,)."""
        import pinocchio as pin

        pin.forwardKinematics(self.model, self.data, self.q_full(q14))
        pin.updateGeometryPlacements(self.model, self.data, self.geom, self.gdata)
        hit = [p for p in pair_ids if pin.computeCollision(self.geom, self.gdata, int(p))]
        return np.asarray(hit, dtype=np.int64)


def _prefixed(prefix: str) -> tuple:
    """Copies of the Panda model and collision model with names prefixed, meshes as convex hulls."""
    import pinocchio as pin

    from tdcommon.robot import panda_models

    model, cmodel = panda_models()
    m = pin.Model(model)
    for i in range(1, m.njoints):
        m.names[i] = prefix + m.names[i]
    for i in range(len(m.frames)):
        f = m.frames[i]
        f.name = prefix + f.name
        m.frames[i] = f
    c = pin.GeometryModel()
    for g in cmodel.geometryObjects:
        g = g.copy()
        g.name = prefix + g.name
        geo = g.geometry
        if hasattr(geo, "buildConvexHull"):
            geo = geo.clone()
            geo.buildConvexHull(False, "Qt")
            hull = geo.convex
            hull.computeLocalAABB()
            g.geometry = hull
        c.addGeometryObject(g)
    return m, c


def _points(geo: object) -> np.ndarray:
    """(Np, 3) vertices of a convex hull or box, geometry frame."""
    if hasattr(geo, "halfSide"):
        h = np.asarray(geo.halfSide)
        return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * h
    return np.asarray(geo.points(), dtype=np.float64)


@functools.lru_cache(maxsize=8)
def _dual_model(bases_key: bytes, margin: float, table_z: float) -> _DualModel:
    """Build (once per base placement) the combined two-arm collision model and its checked pairs."""
    import pinocchio as pin

    bases = np.frombuffer(bases_key, dtype=np.float64).reshape(2, 4, 4)
    model, geom = pin.Model(), pin.GeometryModel()
    arm_of: list[int] = []
    for a, name in enumerate(ARM_NAMES):
        m, c = _prefixed(name + "/")
        T = bases[a]
        model, geom = pin.appendModel(model, m, geom, c, 0, pin.SE3(T[:3, :3].copy(), T[:3, 3].copy()))
        arm_of += [a] * len(c.geometryObjects)
    arm = np.asarray(arm_of)
    pts = [_points(g.geometry) for g in geom.geometryObjects]
    lo = np.stack([p.min(0) for p in pts])
    hi = np.stack([p.max(0) for p in pts])
    centre = (lo + hi) / 2
    radius = np.array([np.linalg.norm(p - c, axis=1).max() for p, c in zip(pts, centre, strict=True)])
    parent_joint = np.array([g.parentJoint for g in geom.geometryObjects])
    parents = np.asarray(model.parents)

    def related(i: int, j: int) -> bool:
        ji, jj = parent_joint[i], parent_joint[j]
        return bool(ji == jj or parents[ji] == jj or parents[jj] == ji or parents[ji] == parents[jj])

    G = len(pts)
    cand = [(i, j) for i in range(G) for j in range(i + 1, G) if arm[i] != arm[j] or not related(i, j)]
    geom.removeAllCollisionPairs()
    for i, j in cand:
        geom.addCollisionPair(pin.CollisionPair(i, j))
    data, gdata = model.createData(), pin.GeometryData(geom)
    for req in gdata.collisionRequests:
        req.security_margin = margin
    tcp = tuple(model.getFrameId(f"{n}/{TCP_FRAME}") for n in ARM_NAMES)
    dm = _DualModel(model, data, geom, gdata, tcp, np.asarray(cand, dtype=np.int64).reshape(-1, 2),  # type: ignore[arg-type]
                    ["self_collision" if arm[i] == arm[j] else "arm_collision" for i, j in cand],
                    centre, radius, pts, np.arange(G), margin)
    home = np.concatenate([HOME, HOME])
    touching = set(dm.collide(home, np.arange(len(cand))).tolist())
    keep = np.array([p not in touching for p in range(len(cand))], dtype=bool)
    geom.removeAllCollisionPairs()
    for i, j in np.asarray(cand)[keep]:
        geom.addCollisionPair(pin.CollisionPair(int(i), int(j)))
    dm.gdata = pin.GeometryData(geom)
    for req in dm.gdata.collisionRequests:
        req.security_margin = margin
    dm.pairs = np.asarray(cand, dtype=np.int64)[keep].reshape(-1, 2)
    dm.pair_kind = [k for k, ok in zip(dm.pair_kind, keep, strict=True) if ok]
    P, _ = dm.placements(home)
    zmin = np.array([(p @ T[:3, :3].T + T[:3, 3])[:, 2].min() for p, T in zip(pts, P, strict=True)])
    dm.table_geoms = np.flatnonzero(zmin > table_z + margin)
    return dm


def dual_model(bases: dict[str, np.ndarray], workspace: Workspace) -> _DualModel:
    """The cached collision model for these base placements (4, 4) world <- base."""
    key = np.stack([np.asarray(bases[a], dtype=np.float64) for a in ARM_NAMES]).tobytes()
    return _dual_model(key, float(workspace.collision_margin), float(workspace.table_z))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[(first, last)] index runs where the 1-D boolean ``mask`` is True."""
    if not mask.any():
        return []
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1, strict=True))


def _at(timed: TimedProgram, times: np.ndarray, seg: np.ndarray, a: int, b: int) -> str:
    s = timed.segments[int(seg[a])].label() if timed.segments else "segment 0"
    span = f"t={times[a]:.2f} s" if a == b else f"t={times[a]:.2f}–{times[b]:.2f} s"
    return f"{span} ({s})"


def check_trajectory(timed: TimedProgram, times: np.ndarray, q: np.ndarray, dq: np.ndarray,
                     bases: dict[str, np.ndarray], workspace: Workspace) -> list[Violation]:
    """All violations along samples ``times`` (K,) s, ``q``/``dq`` (K, 14) of ``timed``."""
    lim = joint_limits()
    lower, upper, vmax = (np.tile(lim[k], 2) for k in ("lower", "upper", "velocity"))
    seg = timed.segment_at(times) if timed.segments else np.zeros(len(times), dtype=int)
    out: list[Violation] = []

    def add(kind: str, mask: np.ndarray, what: str) -> None:
        for a, b in _runs(mask):
            out.append(Violation(kind, float(times[a]), float(times[b]), int(seg[a]),
                                 f"{_at(timed, times, seg, a, b)}: {what}"))

    for j in range(2 * N_JOINTS):
        arm, k = ARM_NAMES[j // N_JOINTS], j % N_JOINTS
        add("joint_limit", q[:, j] > upper[j] + 1e-9,
            f"{arm} joint {k} = {q[:, j].max():.4f} rad is above the Panda limit {upper[j]:.4f}")
        add("joint_limit", q[:, j] < lower[j] - 1e-9,
            f"{arm} joint {k} = {q[:, j].min():.4f} rad is below the Panda limit {lower[j]:.4f}")
        add("velocity_limit", np.abs(dq[:, j]) > vmax[j] * (1 + 1e-6),
            f"{arm} joint {k} velocity {np.abs(dq[:, j]).max():.3f} rad/s exceeds the Panda limit {vmax[j]:.3f}")

    dm = dual_model(bases, workspace)
    K, G = len(times), len(dm.hull_points)
    place = np.empty((K, G, 4, 4))
    tcp = np.empty((K, 2, 3))
    for k in range(K):
        place[k], tcp[k] = dm.placements(q[k])
    # TCP workspace box
    lo, hi = np.asarray(workspace.lower), np.asarray(workspace.upper)
    axes = "xyz"
    for a, arm in enumerate(ARM_NAMES):
        for d in range(3):
            add("workspace", tcp[:, a, d] < lo[d],
                f"{arm} TCP {axes[d]} = {tcp[:, a, d].min():.3f} m is below the workspace bound {lo[d]:.3f}")
            add("workspace", tcp[:, a, d] > hi[d],
                f"{arm} TCP {axes[d]} = {tcp[:, a, d].max():.3f} m is above the workspace bound {hi[d]:.3f}")
    # links against the table top (finger pads are several boxes: one message per link)
    names = [g.name for g in dm.geom.geometryObjects]
    low: dict[str, np.ndarray] = {}
    for g in dm.table_geoms:
        z = np.einsum("kj,pj->kp", place[:, g, 2, :3], dm.hull_points[g]).min(1) + place[:, g, 2, 3]
        key = _pretty(names[g])
        low[key] = np.minimum(low[key], z) if key in low else z
    for key, z in low.items():
        add("table", z < workspace.table_z + dm.margin,
            f"{key} reaches z = {z.min():.3f} m, below the table top {workspace.table_z:.3f} m "
            f"(+{dm.margin * 1000:.0f} mm margin)")
    # collisions: bounding spheres first, coal on the close pairs only
    centres = np.einsum("kgij,gj->kgi", place[:, :, :3, :3], dm.sphere_center) + place[:, :, :3, 3]
    i, j = dm.pairs[:, 0], dm.pairs[:, 1]
    dist = np.linalg.norm(centres[:, i] - centres[:, j], axis=2)  # (K, P)
    close = dist < (dm.sphere_radius[i] + dm.sphere_radius[j] + dm.margin)[None]
    hits = np.zeros_like(close)
    for k in np.flatnonzero(close.any(1)):
        hit = dm.collide(q[k], np.flatnonzero(close[k]))
        hits[k, hit] = True
    merged: dict[tuple[str, str, str], np.ndarray] = {}
    for p in np.flatnonzero(hits.any(0)):
        key = (dm.pair_kind[p], _pretty(names[dm.pairs[p, 0]]), _pretty(names[dm.pairs[p, 1]]))
        merged[key] = merged[key] | hits[:, p] if key in merged else hits[:, p]
    for (kind, a, b), mask in merged.items():
        add(kind, mask, f"{a} collides with {b}")
    out.sort(key=lambda v: (v.time, v.kind))
    return out


def check_program(timed: TimedProgram, bases: dict[str, np.ndarray] | None = None,
                  workspace: Workspace | None = None, start: np.ndarray | None = None,
                  rate_hz: float = 50.0, start_tol: float = 0.01) -> SafetyReport:
    """Check ``timed`` before motion; ``bases`` maps left/right to (4, 4) world <- base (default mock).

    ``start`` (14,) rad, left then right: the arms' current joints; the trajectory must start there
    (within ``start_tol`` rad), otherwise time the program with ``current=start``.
    """
    bases = MOCK_BASES if bases is None else bases
    workspace = workspace or Workspace()
    times, q, dq = timed.sample(rate_hz)
    violations: list[Violation] = []
    if start is not None:
        start = np.asarray(start, dtype=np.float64).reshape(2 * N_JOINTS)
        err = np.abs(start - timed.q_start)
        j = int(np.argmax(err))
        if err[j] > start_tol:
            violations.append(Violation(
                "start", 0.0, 0.0, 0,
                f"t=0.00 s: the {ARM_NAMES[j // N_JOINTS]} arm is at joint {j % N_JOINTS} = {start[j]:.4f} rad but "
                f"the trajectory starts at {timed.q_start[j]:.4f} rad ({err[j]:.4f} rad away): time the program "
                f"from the current state"))
            times = np.concatenate([[0.0], times])
            q = np.concatenate([start[None], q])
            dq = np.concatenate([np.zeros((1, 2 * N_JOINTS)), dq])
    violations += check_trajectory(timed, times, q, dq, bases, workspace)
    return SafetyReport(tuple(violations), len(times), rate_hz)
