"""The frame-by-frame TrackDeform3D pipeline: references -> segmentation -> initialisation -> tracking.

Stateful but free of I/O: the zenoh worker and the offline ``trackdeform track`` feed it the same
arrays (depth, arm meshes, gripper TCPs) and get the same results.

States: ``reference`` (the first depth D0 is kept), ``waiting`` (until the arms have moved the
object enough that differencing against the references isolates it), ``tracking``. A LOST track
goes back to ``waiting`` with the recent frames as references, so it re-initialises by itself.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
from scipy.spatial import cKDTree

from tdcommon.meshes import OutwardCache
from tracking.classify import classify_object
from tracking.colour import ColourModel, classify, measure_object
from tracking.geometry import (
    behind_nearest_occluder,
    cell_samples,
    decimated_intrinsics,
    decimation_stride,
    edge_samples,
    gaps_hidden,
    hidden_behind,
    in_open_space,
    pixel_mask,
)
from tracking.init import InitialisationError, Topology
from tracking.params import TrackingParams
from tracking.segmentation import (
    Segmentation,
    background_from_depths,
    behind_continuing,
    behind_near_object,
    change_threshold,
    complete_thin_parts,
    far_where_no_return,
    grow_attached_tubes,
    refine_object_cloud,
    render_arm_mask,
    segment_against_background,
    segment_by_difference,
    support_plane,
    unchanged_object_pixels,
    update_background,
)
from tracking.tracker import FrameResult, Tracker, TrackStatus, free_tips, held_seeds


@dataclass(frozen=True)
class PipelineOutput:
    """One frame's outcome.

    status: "reference" | "waiting" | "init" | "tracking" | "degraded" | "lost".
    keypoints: (N, 3) float64 m world (raw), smoothed: (N, 3) causal moving average; empty before init.
    grasp_idx: (G,) int64 keypoint held by each gripper (-1: none). abs_mm / cd_mm: the paper's per-frame
    edge-length RMSE and keypoint-to-cloud distance (nan before init). n_points: segmented cloud size (voxels;
    while waiting to initialise a 1D or unknown object, the difference cloud's ``voxels_worth``).
    timings_ms: wall time of this frame's stages, ms: "arm" (arm mask render), "segment"
    (differencing or background segmentation + DBSCAN), "init" (classification, anchors, warm start,
    solve) on an initialisation frame, "anchors" (re-detection) and "solve" (Algorithm 1 + scoring)
    on a tracked frame, "total" (the whole ``process`` call). prepared: the frame's decimated depth and
    arm mask (``PreparedFrame``), for a caller that processes the frame again. tangled / repaired: the
    tracker's (``FrameResult``): a grid's tangled cells or a chain's folded keypoints left, a repair made.
    """

    status: str
    keypoints: np.ndarray
    smoothed: np.ndarray
    grasp_idx: np.ndarray
    abs_mm: float
    cd_mm: float
    n_points: int
    topology: Topology | None = None
    cloud: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), repr=False)
    note: str = ""
    timings_ms: dict[str, float] = field(default_factory=dict, repr=False)
    prepared: PreparedFrame | None = field(default=None, repr=False, compare=False)
    tangled: int = 0
    repaired: bool = False


_EMPTY = np.zeros((0, 3))


@dataclass(frozen=True)
class PreparedFrame:
    """What ``LivePipeline.process`` computes first from a frame, before any state is used: its decimated depth
    (h, w) float32 m, arm mask (h, w) bool (None without arm meshes) and colour (h, w, 3) uint8 (a strided view of
    the frame's; None without one, or for a cloth). An offline pass that tracks the frame again hands it back
    (``process(prepared=...)``) instead of decimating and rendering the arms again."""

    depth: np.ndarray
    arm: np.ndarray | None
    colour: np.ndarray | None = None


def object_samples(X: np.ndarray, topology: Topology, n: int = 6) -> np.ndarray:
    """Points (M, 3) m densely covering the tracked object: n samples along each edge of keypoints
    X (N, 3) m, and for a 2D grid n x n bilinear samples of each cell (the cloth between its edges)."""
    pts = edge_samples(X, topology.edges, n)
    if topology.grid_shape is None:
        return pts
    I, W = cell_samples(topology.grid_shape, max(2, n) - 1)
    return np.concatenate([pts, np.einsum("kj,kjc->kc", W, X[I])])


class LivePipeline:
    """Feed frames with :meth:`process`; K (3, 3) and T_world_cam (4, 4) are fixed for a sequence.

    Depth images are decimated by ``stride`` (``params.decimate_pixel_m``) before segmentation,
    arm masking and background modelling, so the per-frame cost does not grow with the camera
    resolution; anchors are detected with the full camera matrix.
    """

    def __init__(
        self,
        params: TrackingParams,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        kind: str | None = None,
        min_init_points: int = 150,
        reference_gap: int = 10,
        init_stable_frames: int = 6,
        init_max_growth: float = 0.05,
        init_grasp_patience: int = 90,
    ) -> None:
        """kind: "1d"/"2d" when the object's category is known (else classified from the cloud).

        min_init_points: a difference segmentation smaller than this (voxels; of a 1D or unknown object, voxels'
          worth of surface: ``voxels_worth``) waits for more motion.
        reference_gap: frames between the extra difference references kept from the recent past.
        init_stable_frames, init_max_growth: initialise only once the difference segmentation has
          grown by at most this fraction over this many frames (it is still uncovering the object
          while the arms start moving it; a partial cloud would give a partial topology).
        init_grasp_patience: an initialisation must put a keypoint at every closed gripper's TCP
          (within ``grasp_gate_m``: the object is held there); after this many such rejections a
          cloud that fails the check is accepted anyway (e.g. a poorly calibrated TCP), frames.
        """
        self.params = params
        self.K = np.asarray(K, np.float64)
        self.T = np.asarray(T_world_cam, np.float64)
        self.kind = kind
        self.min_init_points = min_init_points
        self.reference_gap = reference_gap
        self.init_stable_frames = init_stable_frames
        self.init_max_growth = init_max_growth
        self.init_grasp_patience = init_grasp_patience
        self.stride = decimation_stride(self.K, params.decimate_pixel_m)
        s = self.stride
        self.K_seg = decimated_intrinsics(self.K, s) if s > 1 else self.K
        self.seg_params = params if s == 1 else replace(
            params, lift_stride=1, arm_margin_px=-(-params.arm_margin_px // s),
            arm_render_stride=max(1, int(round(params.arm_render_stride / s))),
        )
        self.tracker = Tracker(params, self.K, self.T)
        self._cullable = OutwardCache()  # the arm meshes' back faces the arm mask may skip, per topology
        # the object's and the empty scene's colours, measured at a 1D object's initialisation (None without colour
        # frames): kept through reset and resume, so an offline pass's pipeline is given the forward pass's
        self.colour_model: ColourModel | None = None
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next frame becomes the reference D0."""
        self.tracker.reset()
        self._d0: np.ndarray | None = None
        self._c0: np.ndarray | None = None  # the reference's decimated colour, when frames have one
        self._support: tuple[np.ndarray, float] | None = None  # the table plane in D0 (normal, offset m)
        self._recent: deque[tuple[np.ndarray, np.ndarray | None]] = deque(maxlen=3)  # (depth, colour or None)
        self._since_recent = 0
        self._sizes: deque[int] = deque(maxlen=self.init_stable_frames + 1)
        self._grasp_rejections = 0
        # the previous decimated depths (newest last) a background update must agree with
        self._prev: deque[np.ndarray] = deque(
            maxlen=max(0, self.params.background_confirm_1d - 1, self.params.background_confirm_2d - 1)
        )
        self.background: np.ndarray | None = None  # (h, w) float32 m, decimated
        self._last_cloud: np.ndarray | None = None  # the last frame's segmented object (M, 3) m world
        self.init_failures = 0
        self.last_init_error = ""
        self._timings: dict[str, float] = {}

    @property
    def state(self) -> str:
        """``reference``, ``waiting`` or ``tracking``."""
        if self._d0 is None:
            return "reference"
        return "tracking" if self.tracker.initialised else "waiting"

    def decimate(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) depth, m -> (ceil(H / s), ceil(W / s)) float32 every ``stride``-th pixel (contiguous)."""
        if self.stride == 1:
            return np.array(depth, np.float32)  # a copy: references and background outlive the caller's buffer
        return np.ascontiguousarray(depth[:: self.stride, :: self.stride], np.float32)

    def arm_mask(
        self, depth: np.ndarray, arm_vertices: np.ndarray | None, arm_triangles: np.ndarray | None
    ) -> np.ndarray | None:
        """Arm pixels (h, w) bool of a decimated depth (h, w) m (arms rendered at their measured
        joints), or None without meshes."""
        if arm_vertices is None or arm_triangles is None or len(arm_triangles) == 0:
            return None
        p = self.seg_params
        return render_arm_mask(
            arm_vertices, arm_triangles, self.K_seg, self.T, depth.shape, p.arm_margin_px, depth, p.arm_margin_m,
            p.arm_render_stride, self._cullable((arm_vertices, arm_triangles)),
        )

    def prepare(
        self, depth: np.ndarray, arm_vertices: np.ndarray | None = None, arm_triangles: np.ndarray | None = None,
        depth_scale: float | None = None, colour: np.ndarray | None = None,
    ) -> PreparedFrame:
        """A frame's decimated depth, arm mask and colour (``PreparedFrame``) from its depth (H, W) float32 m, arm
        mesh (V, 3) m world + (F, 3) int and colour (H, W, 3) uint8 (registered to the depth; another size is left
        out): stateless, the first step of ``process``. With ``depth_scale`` (m per unit) depth is the recorded
        integer image, decimated before it is scaled (as ``RGBDFrame.depth_m`` scales it: the same float32 values
        without converting the whole image)."""
        if depth_scale is None:
            dec = self.decimate(depth)
        else:
            dec = np.ascontiguousarray(depth[:: self.stride, :: self.stride]).astype(np.float32) * np.float32(
                depth_scale
            )
        col = None  # a view: a cloth's colour is not read, a rope's at a few hundred pixels a frame
        if self.kind != "2d" and colour is not None and colour.ndim == 3 and colour.shape[:2] == depth.shape[:2]:
            col = colour[:: self.stride, :: self.stride, :3]
        return PreparedFrame(dec, self.arm_mask(dec, arm_vertices, arm_triangles), col)

    def process(
        self,
        depth: np.ndarray | None,
        arm_vertices: np.ndarray | None = None,
        arm_triangles: np.ndarray | None = None,
        tcp: np.ndarray | None = None,
        gripper_closed: np.ndarray | None = None,
        prepared: PreparedFrame | None = None,
        tcp_rot: np.ndarray | None = None,
        colour: np.ndarray | None = None,
    ) -> PipelineOutput:
        """One frame: depth (H, W) float32 m; both arms as one mesh (V, 3) m world + (F, 3) int;
        tcp (G, 3) m world, tcp_rot (G, 3, 3) (TCP frame to world; optional) and gripper_closed (G,) bool of the
        grippers (G = 2: left, right); colour (H, W, 3) uint8 RGB registered to the depth (optional: a 1D
        object's points lying low are then told from the table by it, ``tracking.colour``).
        prepared: this frame's ``PreparedFrame`` from an earlier ``prepare`` / output (the arm meshes are then
        not needed); depth may then be None unless the pipeline still has to initialise (it re-lifts the
        initial cloud from the full-resolution depth)."""
        t0 = time.perf_counter()
        if prepared is None:
            if depth is None:
                raise ValueError("LivePipeline.process: no depth and no prepared frame")
            prepared = self.prepare(depth, arm_vertices, arm_triangles, colour=colour)
        elif depth is None and self._d0 is not None and not self.tracker.initialised:
            raise ValueError("LivePipeline.process: initialising needs the full-resolution depth, not only a "
                             "prepared frame")
        full, depth, arm, col = depth, prepared.depth, prepared.arm, prepared.colour
        self._timings = {"arm": 1e3 * (time.perf_counter() - t0)}
        if self._d0 is None:
            self.set_reference(depth, col)
            out = self._empty("reference")
        elif not self.tracker.initialised:
            assert full is not None  # checked above
            out = self._try_initialise(depth, arm, tcp, gripper_closed, full, col)
        else:
            out = self._track(depth, arm, tcp, gripper_closed, tcp_rot, col)
        if self._prev.maxlen:
            self._prev.append(depth)
        self._timings["total"] = 1e3 * (time.perf_counter() - t0)
        return replace(out, timings_ms=self._timings, prepared=prepared)

    def segment_initial(self, refs: np.ndarray, depth: np.ndarray, arm: np.ndarray | None) -> Segmentation:
        """Difference segmentation of a decimated depth (h, w) m against references (R, h, w) m.

        A 2D object (``kind`` "2d", or classified so from its "appeared" cloud when unknown) is grown
        over the changed pixels depth-continuous with it (``segment_by_difference(grow=True)``): a
        cloth pulled back lies behind its old positions and differencing alone misses most of it.
        A 1D object gets its thin parts that did not move (``grow_attached_tubes``): a hanging end.
        The parts of a 2D object that did not move are added once it is initialised on (``_try_initialise``):
        before the object moved, noise alone would seed the whole surface.
        """
        p = self.seg_params
        if self.kind == "2d":
            return segment_by_difference(refs, depth, self.K_seg, self.T, p, arm, grow=True)
        seg = segment_by_difference(refs, depth, self.K_seg, self.T, p, arm)
        if len(seg.points) < self.params.min_object_points:
            return seg
        if self.kind is None and classify_object(seg.points, p).kind == "2d":
            return segment_by_difference(refs, depth, self.K_seg, self.T, p, arm, grow=True)
        return grow_attached_tubes(depth, seg, self.K_seg, self.T, p, arm, self._support)

    def reach_grippers(
        self, depth: np.ndarray, seg: Segmentation, arm: np.ndarray | None, held: np.ndarray | None
    ) -> Segmentation:
        """A 1D object's initial segmentation (of the decimated depth (h, w) m) grown again over its thin
        parts above the table (``grow_attached_tubes``, ``attach_reach_m`` a step, up to ``attach_iterations``
        steps) while a holding gripper's TCP (held (G, 3) m) is farther than ``grasp_gate_m`` from it: in a
        slow start only the middle of a rope moves, and its still ends hang up to the grippers. Kept only when
        it reaches a gripper the segmentation did not, or comes closer to one and stops within ``hand_hidden_m``
        of its TCP where the arm (arm: decimated mask) hides the rest of the way (``gaps_hidden``: the hand
        hides the end it holds). Then, whether the grippers were reached or not, it is grown until it stalls
        (nothing within ``grasp_gate_m`` of a TCP), a part of a pixel or more at a time: a still free end,
        e.g. a branch's tip on the table or hanging away from the camera."""
        if held is None or len(held) == 0 or len(seg.points) == 0 or self.kind == "2d" or seg.grown:
            return seg
        held = np.asarray(held, np.float64).reshape(-1, 3)
        return self._grow_free(depth, self._grow_to_grippers(depth, seg, arm, held), arm, held)

    def _grow_to_grippers(
        self, depth: np.ndarray, seg: Segmentation, arm: np.ndarray | None, held: np.ndarray
    ) -> Segmentation:
        """``reach_grippers``' growth towards the holding grippers' TCPs held (G, 3) m (seg when it is not kept)."""
        p = self.seg_params
        d0 = cKDTree(seg.points).query(held)[0]
        reached = d0 <= p.grasp_gate_m
        if reached.all():
            return seg
        # what grows near a gripper is the gripper: within grasp_gate_m of one the cloud reached already,
        # within attach_reach_m of the others (the end is then within grasp_gate_m: initialisation puts it at the TCP)
        gate = np.where(reached, p.grasp_gate_m, min(p.attach_reach_m, p.grasp_gate_m))
        out = seg
        for _ in range(p.attach_iterations):
            grown = grow_attached_tubes(depth, out, self.K_seg, self.T, p, arm, self._support)
            new = grown.points[len(out.points):]
            new = new[(np.linalg.norm(new[:, None, :] - held[None, :, :], axis=2) > gate).all(axis=1)]
            if len(new) == 0:
                break
            out = replace(out, points=np.concatenate([out.points, new]))
            if (cKDTree(out.points).query(held)[0] <= p.grasp_gate_m).all():
                break
        # a growth that stalls before reaching another gripper found something else (a surface patch, a gap),
        # unless it stops where that gripper's hand hides the rest of the way to its TCP
        d, i = cKDTree(out.points).query(held)
        now = d <= p.grasp_gate_m
        if now.sum() > reached.sum():
            return out
        if arm is not None and len(out.points) > len(seg.points):
            if self._hand_hides(out.points, held, arm, i, ~reached & (d < d0) & (d <= p.hand_hidden_m)).any():
                return out
        return seg

    def _hand_hides(
        self, points: np.ndarray, held: np.ndarray, arm: np.ndarray, i: np.ndarray, ask: np.ndarray
    ) -> np.ndarray:
        """(G,) bool: for the TCPs held (G, 3) m picked by ask (G,) bool, whether the arm's pixels (arm: decimated
        mask) cover the straight way to the TCP from its nearest point of points (N, 3) m, index i (G,)
        (``gaps_hidden``: the hand hides the end it holds); False for the others."""
        out = np.zeros(len(held), bool)
        if ask.any():
            out[ask] = gaps_hidden(points[i[ask]], held[ask], arm, self.K_seg, self.T, self.seg_params.voxel_m)
        return out

    def grasp_gates(self, cloud: np.ndarray, arm: np.ndarray | None, tcp: np.ndarray | None) -> np.ndarray | None:
        """How far (G,) m from each TCP tcp (G, 3) m the end of a 1D object (a cloth's corner) held there may be
        seen in the cloud (N, 3) m: ``grasp_gate_m``, or, where the straight way from the cloud's nearest point to
        the TCP is hidden (behind the arm: decimated mask; or outside the image: ``gaps_hidden``), that point's
        distance plus ``grasp_gate_m``: a hand seen across its fingers, or an arm in front of the rope or cloth
        it holds, hides the end whatever the length hidden. A 1D end's nearest point is asked only when it lies
        beyond ``grasp_gate_m``; a cloth's always: its contour's corner, where the hand hides it, may lie farther
        than its nearest seen point (cloth_medium_c408: 73 and 86 mm). None without TCPs, arm or cloud."""
        if tcp is None or arm is None or len(cloud) == 0:
            return None
        p = self.seg_params
        tcp = np.asarray(tcp, np.float64).reshape(-1, 3)
        d, i = cKDTree(cloud).query(tcp)
        ask = d > p.grasp_gate_m if self.kind != "2d" else np.ones(len(d), bool)
        return np.where(self._hand_hides(cloud, tcp, arm, i, ask), d + p.grasp_gate_m, p.grasp_gate_m)

    def _grow_free(
        self, depth: np.ndarray, seg: Segmentation, arm: np.ndarray | None, held: np.ndarray
    ) -> Segmentation:
        """``reach_grippers``' growth of the still free parts until it stalls, nothing within ``grasp_gate_m`` of
        the TCPs held (G, 3) m."""
        p = self.seg_params
        return complete_thin_parts(depth, seg, self.K_seg, self.T, p, arm, self._support, p.attach_iterations,
                                   (held, p.grasp_gate_m))

    def initial_cloud(
        self, refs: np.ndarray, depth: np.ndarray, seg: Segmentation, arm: np.ndarray | None,
        tcp: np.ndarray | None, closed: np.ndarray | None, full: np.ndarray,
    ) -> tuple[Segmentation, np.ndarray]:
        """The cloud (N, 3) m to initialise on, from the initial segmentation ``seg`` of the decimated depth
        (h, w) m against refs (R, h, w) m, once the object moved enough: a grown (2D) segmentation is
        completed with what did not move but stands above the table (a cloth's still hem: ``segment_by_
        difference(support=...)``), a 1D one grown to the closed grippers' TCPs (tcp (G, 3) m, closed (G,)
        bool: ``reach_grippers``), then re-lifted from the full-resolution depth (H, W) m (``refine``).
        Returns the (completed) decimated segmentation and the cloud."""
        if seg.grown:
            seg = segment_by_difference(refs, depth, self.K_seg, self.T, self.seg_params, arm, grow=True,
                                        support=self._support)
        if tcp is not None:
            held = np.asarray(tcp, np.float64).reshape(-1, 3)
            seg = self.reach_grippers(depth, seg, arm, held if closed is None else held[np.asarray(closed, bool)])
        return seg, self.refine(full, seg, arm, refs)

    def refine(self, depth: np.ndarray, seg: Segmentation, arm: np.ndarray | None, refs: np.ndarray) -> np.ndarray:
        """The initial object cloud (N, 3) m re-lifted from the full-resolution depth (H, W) m, a grown
        one re-grown against the decimated references refs (R, h, w) m, a 1D one's thin parts above
        the table grown again (``refine_object_cloud``; arm: decimated arm mask): initialisation runs
        on it, once."""
        if self.stride == 1:
            return seg.points
        return refine_object_cloud(
            np.asarray(depth, np.float32), seg.points, self.K, self.T, self.params, arm,
            refs=refs if seg.grown else None, support=self._support,
        )

    def resume(
        self, topology: Topology, keypoints: np.ndarray, grasp_idx: np.ndarray, background: np.ndarray
    ) -> None:
        """Start tracking from a known state instead of initialising: keypoints (N, 3) m world of
        ``topology``, grasp_idx (G,) int64 and a decimated background (h, w) float32 m (e.g. another
        pass's); the next ``process`` call tracks. Used by the offline passes (``tracking.offline``)."""
        self.reset()
        self.tracker.resume(topology, keypoints, grasp_idx)
        self.background = np.array(background, np.float32)
        self._d0 = self.background
        self._support = support_plane(self.background, self.K_seg, self.T, self.seg_params)

    def set_reference(self, depth: np.ndarray, colour: np.ndarray | None = None) -> None:
        """Make a decimated depth (h, w) m the reference D0 (and find the table plane in it: an
        object's parts that did not move stand above it), with its decimated colour (h, w, 3) uint8 if any;
        ``process`` does this on its first frame."""
        self._d0 = depth
        self._c0 = None if colour is None else np.array(colour)  # a copy: it outlives the caller's frame
        self._support = support_plane(depth, self.K_seg, self.T, self.seg_params)

    # ---------------------------------------------------------------- internals
    def _empty(self, status: str, n_points: int = 0, note: str = "") -> PipelineOutput:
        nan = float("nan")
        return PipelineOutput(status, _EMPTY, _EMPTY, np.zeros(0, np.int64), nan, nan, n_points, note=note)

    def _references(self) -> np.ndarray:
        assert self._d0 is not None
        refs = np.stack([self._d0, *(d for d, _ in self._recent)])
        return refs if self.kind == "2d" else far_where_no_return(refs, self.K_seg, self.seg_params)

    def _remember(self, depth: np.ndarray, colour: np.ndarray | None = None) -> None:
        self._since_recent += 1
        if self._since_recent >= self.reference_gap:
            self._recent.append((depth, None if colour is None else np.array(colour)))
            self._since_recent = 0

    def voxels_worth(self, points: np.ndarray) -> int:
        """The surface of a cloud (N, 3) m world in voxels (``voxel_m`` squared): each point counts for the area of
        a decimated pixel at its distance where that is wider than a voxel. A rope's points fall as the square of
        its distance until it is a pixel wide (a 9 mm rope: 277 voxels at 1 m, 68 at 2 m; a 0.95 m rope ~2 m
        away gave 50-130, never ``min_init_points``); the surface they stand for does not."""
        if len(points) == 0:
            return 0
        px = np.linalg.norm(points - self.T[:3, 3], axis=1) / self.K_seg[0, 0]
        return int((np.maximum(1.0, px / self.params.voxel_m) ** 2).sum())

    def _growing(self, n: int) -> bool:
        """Whether the difference cloud (n voxels now, a count: its surface's ``voxels_worth`` moves with the
        distances of the points that come and go) grew by more than ``init_max_growth`` lately."""
        self._sizes.append(n)
        if self.init_stable_frames <= 0:
            return False
        return len(self._sizes) < self._sizes.maxlen or n > (1.0 + self.init_max_growth) * self._sizes[0]

    def _try_initialise(
        self, depth: np.ndarray, arm: np.ndarray | None, tcp: np.ndarray | None, closed: np.ndarray | None,
        full: np.ndarray, colour: np.ndarray | None = None,
    ) -> PipelineOutput:
        refs = self._references()
        t0 = time.perf_counter()
        seg = self.segment_initial(refs, depth, arm)
        t1 = time.perf_counter()
        self._timings["segment"] = 1e3 * (t1 - t0)
        self._remember(depth, colour)
        # a sheet's moving part is never thin: its count early in its motion is what min_init_points was set for
        # (counted as surface, 35 of 87 test-bed cloths initialised 1-26 frames earlier, on a sheet still to move:
        # cloth_fast_c403's anchors 33 -> 92 mm, cloth_slow_g426's 10 -> 105)
        n = len(seg.points) if self.kind == "2d" else self.voxels_worth(seg.points)
        if self._growing(len(seg.points)) or n < self.min_init_points:
            return self._empty("waiting", n, "waiting for the arms to move the object")
        seg, cloud = self.initial_cloud(refs, depth, seg, arm, tcp, closed, full)
        try:
            ini, res = self.tracker.initialise(cloud, tcp=tcp, kind=self.kind, gripper_closed=closed,
                                               grasp_gate=self.grasp_gates(cloud, arm, tcp))
        except InitialisationError as e:
            self.init_failures += 1
            self.last_init_error = str(e)
            return self._empty("waiting", n, f"initialisation failed: {e}")
        finally:
            self._timings["init"] = 1e3 * (time.perf_counter() - t1)
        if tcp is not None and closed is not None:
            held = np.asarray(closed, bool)
            missing = held & (np.asarray(self.tracker.grasp_idx) < 0)
            if missing.any() and self._grasp_rejections < self.init_grasp_patience:
                self._grasp_rejections += 1
                self.tracker.reset()
                return self._empty("waiting", n, "waiting: the segmented object does not reach every closed gripper")
        bg = background_from_depths(refs)
        # where the object stood still in every reference the background is unknown, not the object: every
        # pixel whose background reading lies on the initialised cloud (a 1D object's full-resolution growth
        # found thin parts the decimated segmentation missed; a cloth's completion, its still hem)
        bg[unchanged_object_pixels(depth, bg, cloud, self.K_seg, self.T, self.seg_params, by_background=True)] = 0.0
        # the object's pixels behind the references (moving away) are object, not revealed background
        keep = behind_near_object(depth, bg, self.seg_params, cloud, self.K_seg, self.T, arm)
        self.background = update_background(bg, depth, self.seg_params, arm, keep=keep)
        self._sizes.clear()
        self._grasp_rejections = 0
        if self.kind != "2d" and colour is not None and self._c0 is not None and colour.shape == self._c0.shape:
            self.colour_model = measure_object(colour, self._c0, cloud, self.K_seg, self.T,
                                               self.params.colour_min_separation)
        self._last_cloud = np.asarray(cloud, np.float64)
        return self._output("init", res, seg.points)

    def _track(
        self, depth: np.ndarray, arm: np.ndarray | None, tcp: np.ndarray | None, closed: np.ndarray | None,
        tcp_rot: np.ndarray | None = None, colour: np.ndarray | None = None,
    ) -> PipelineOutput:
        assert self.background is not None
        t0 = time.perf_counter()
        topo, X = self.tracker.topology, self.tracker.keypoints
        assert topo is not None and X is not None
        samples = object_samples(X, topo)
        thr = change_threshold(self.background, self.seg_params)  # one per frame, for the three tests below
        behind = behind_near_object(depth, self.background, self.seg_params, samples, self.K_seg, self.T, arm, thr)
        if self._last_cloud is not None and len(self._last_cloud):  # and what continues the object last seen
            seen, _ = pixel_mask(self._last_cloud, self.K_seg, self.T, depth.shape)
            behind |= behind_continuing(depth, self.background, self.seg_params, seen | behind, self.K_seg, self.T,
                                        arm, self._support, thr)
        told = None  # a 1D object's low points: the object's colour or the table's
        if topo.kind == "1d" and colour is not None and self.colour_model is not None and \
                colour.shape[:2] == self.colour_model.reference.shape[:2]:
            told = partial(classify, colour=colour, model=self.colour_model, K=self.K_seg, T_world_cam=self.T,
                           radius_m=self.params.colour_radius_m)
        tips = free_tips(X, topo.edges, self.tracker.grasp_idx) if topo.kind == "1d" else None
        held = held_seeds(X, topo, self.tracker.grasp_idx)  # a grid's held corners, else None
        seg = segment_against_background(
            depth, self.background, self.K_seg, self.T, self.seg_params, arm, X, behind, self._support, samples, thr,
            flat=topo.kind == "2d", colour=told, tips=tips, held=held,
        )
        if topo.kind == "1d":
            seg = complete_thin_parts(depth, seg, self.K_seg, self.T, self.seg_params, arm, self._support)
        self._timings["segment"] = 1e3 * (time.perf_counter() - t0)
        topology = self.tracker.topology
        # keypoints out of sight have no cloud of their own: a rope's behind the arm, a cloth's behind whatever the
        # depth shows in front of them (the arm, or the cloth's own near layer where it folds or turns edge-on), or
        # just beside such a layer (within the reach of a hidden keypoint's projection) with open space behind
        hidden = None
        if topo.kind == "2d":
            hidden = hidden_behind(X, None, depth, self.K_seg, self.T, self.params.arm_margin_m,
                                   self.params.hidden_reach * float(np.median(topo.rest)))
        else:
            mask = arm if arm is not None else np.zeros(depth.shape, bool)  # what is out of the image only
            hidden = hidden_behind(X, mask, depth, self.K_seg, self.T, self.params.arm_margin_m)
        open_space = None
        if topo.kind == "2d":  # where a hidden cloth keypoint, which the camera would see there, cannot be moved
            open_space = partial(in_open_space, depth=depth, K=self.K_seg, T_world_cam=self.T,
                                 margin_m=self.params.arm_margin_m)
        behind_arm = None
        if topo.kind == "1d" and arm is not None:  # where a rope keypoint the camera would see cannot stay
            behind_arm = partial(behind_nearest_occluder, depth=depth, K=self.K_seg, T_world_cam=self.T, mask=arm,
                                 reach_m=self.params.hidden_reach * float(np.median(topo.rest)),
                                 margin_m=self.params.arm_margin_m)
        res = self.tracker.step(seg.points, tcp=tcp, gripper_closed=closed, hidden=hidden, tcp_rot=tcp_rot,
                                open_space=open_space, behind_arm=behind_arm)
        self._last_cloud = np.asarray(seg.points, np.float64)
        self._timings.update(self.tracker.last_timings_ms)
        p = self.params
        n = (p.background_confirm_2d if topo.kind == "2d" else p.background_confirm_1d) - 1
        prev = np.stack(list(self._prev)[-n:]) if self._prev and n > 0 else None
        self.background = update_background(
            self.background, depth, self.seg_params, arm, prev, behind, nearest=topo.kind != "2d", thr=thr
        )
        self._remember(depth, colour)
        if res.status == TrackStatus.LOST:
            # back to waiting: the recent frames (object elsewhere) become the references
            if self._recent:
                self.set_reference(*self._recent[0])
            else:
                self.set_reference(depth, colour)
            self._recent.clear()
            self._sizes.clear()
            out = self._output("lost", res, seg.points, grid=topo.kind == "2d")
            return PipelineOutput(**{**out.__dict__, "topology": topology})
        return self._output("tracking" if res.status == TrackStatus.OK else "degraded", res, seg.points)

    def _output(self, status: str, res: FrameResult, cloud: np.ndarray, grid: bool | None = None) -> PipelineOutput:
        note = ""
        if grid is None:
            grid = self.tracker.topology is None or self.tracker.topology.kind == "2d"
        if res.tangled:
            note = (f"grid tangled: {res.tangled} cells" if grid else f"chain folded: {res.tangled} keypoints") + (
                " after a repair" if res.repaired else "")
        elif res.repaired:
            note = "grid tangle repaired" if grid else "chain fold repaired"
        return PipelineOutput(
            status, res.keypoints, res.smoothed, np.asarray(res.grasp_idx, np.int64),
            float(res.edge_rmse_mm), float(res.chamfer_mm), int(res.n_points), self.tracker.topology, cloud, note,
            tangled=int(res.tangled), repaired=bool(res.repaired),
        )
