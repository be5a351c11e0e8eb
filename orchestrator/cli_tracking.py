"""Tracking commands: ``worker`` (live, zenoh), ``watch`` (print live keypoints), ``track`` (offline)."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from orchestrator.config import DEFAULT_CONFIG


def cmd_worker(args: argparse.Namespace) -> int:
    """Run the tracking worker (same as ``python -m orchestrator.worker``)."""
    from orchestrator.worker import main as worker_main

    argv = [args.config] + [x for e in (args.connect or []) for x in ("--connect", e)]
    if args.max_frames:
        argv += ["--max-frames", str(args.max_frames)]
    if args.verbose:
        argv.append("-v")
    return worker_main(argv)


def format_keypoints_line(msg: dict[str, Any]) -> str:
    """One human line per keypoint message."""
    n = len(msg.get("keypoints", []))
    g = msg.get("grasp_indices", {})
    abs_mm, cd_mm = msg.get("abs_mm"), msg.get("cd_mm")
    fig = "" if abs_mm is None else f" Abs {abs_mm:5.2f} mm CD {cd_mm:5.2f} mm"
    return (f"frame {msg.get('frame_number'):7d}  {msg.get('object', '')}/{msg.get('category', '')}  "
            f"{msg.get('status', ''):9s} N={n:3d}{fig}  grasp L={g.get('left', -1)} R={g.get('right', -1)}")


def cmd_watch(args: argparse.Namespace) -> int:
    """Print live keypoint messages as they arrive (Ctrl-C to stop)."""
    from orchestrator.bus import local_endpoints, open_client
    from orchestrator.config import load_config
    from tdcommon.wire import decode_json

    config = load_config(args.config)
    endpoints = args.connect or config.bus.connect or local_endpoints(config.bus.listen)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    deadline = (time.monotonic() + args.seconds) if args.seconds else None
    try:  # the session may still be starting: keep trying to reach it (for --seconds, or until Ctrl-C)
        bus = open_client(config.bus, args.station or config.station.name, endpoints,
                          args.seconds if args.seconds else 365 * 86400.0)
    except RuntimeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        sub = bus.subscribe(bus.key("keypoints"), ring=64)
        print(f"watching {bus.key('keypoints')} via {endpoints}", file=sys.stderr)
        seen = 0
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            s = sub.try_recv()
            if s is None:
                time.sleep(0.005)
                continue
            msg = decode_json(s.payload.to_bytes())
            print(json.dumps(msg) if args.json else format_keypoints_line(msg), flush=True)
            seen += 1
            if args.count and seen >= args.count:
                break
    finally:
        bus.close()
    return 0


def _arm_geometry(seq: Any, i: int, arms: Any) -> tuple[Any, Any, Any, Any, Any]:
    """Arm meshes, TCPs, closed flags and TCP orientations for frame ``i`` of a dataset (whole arms, or hands at
    the TCPs). Where the opening is not recorded, the fingers are rendered closed as well as open: closed on a
    rope or a cloth's corner, they hide what they hold, and their pads are not the object."""
    from tdcommon.robot import hand_mesh

    closed = None
    if seq.grasped_left is not None and seq.grasped_right is not None:
        closed = np.array([bool(seq.grasped_left[i]), bool(seq.grasped_right[i])])
    widths = [getattr(seq, f"gripper_width_{a}", None) for a in ("left", "right")]
    width = [float(w[i]) if w is not None and np.isfinite(w[i]) else 0.08 for w in widths]
    if arms is not None and seq.q_left is not None and seq.q_right is not None:
        state = {
            a: {"q": q[i], "gripper_width": width[j], "grasped": bool(closed[j]) if closed is not None else False}
            for j, (a, q) in enumerate((("left", seq.q_left), ("right", seq.q_right)))
        }
        V, F, tcp, c, rot = arms.from_state(state)
        # an opening that was not recorded: the fingers are masked closed as well as open (the default width)
        extra = [arms.kin[a].finger_meshes(q[i], 0.0) for a, q, w in
                 (("left", seq.q_left, widths[0]), ("right", seq.q_right, widths[1]))
                 if w is None or not np.isfinite(w[i])]
        if extra:
            from tdcommon.meshes import merge_meshes

            V, F = merge_meshes([(V, F), *extra])
        return V, F, tcp, (c if closed is not None else None), rot
    if seq.tcp_left is not None and seq.tcp_right is not None:
        vl, fl = hand_mesh(seq.tcp_left[i], width[0])
        vr, fr = hand_mesh(seq.tcp_right[i], width[1])
        tcp = np.stack([seq.tcp_left[i][:3, 3], seq.tcp_right[i][:3, 3]])
        rot = np.stack([seq.tcp_left[i][:3, :3], seq.tcp_right[i][:3, :3]])
        return np.concatenate([vl, vr]), np.concatenate([fl, fr + len(vl)]), tcp, closed, rot
    return None, None, None, None, None


class _Background:
    """Run ``job`` in a daemon thread; ``raise_if_failed`` re-raises its exception, ``wait`` returns it."""

    def __init__(self, job: Callable[[], None]) -> None:
        self.error: Exception | None = None
        self._thread = threading.Thread(target=self._run, args=(job,), name="verify", daemon=True)
        self._thread.start()

    def _run(self, job: Callable[[], None]) -> None:
        from tdrecord.sequence import lower_thread_priority

        # off the critical path (the depth reader is on it: it keeps the normal priority), so on a busy
        # machine the tracking thread comes first
        lower_thread_priority()
        try:
            job()
        except Exception as e:  # noqa: BLE001 - reported by the thread that waits
            self.error = e

    def raise_if_failed(self) -> None:
        """Raise the job's exception if it has failed already."""
        if self.error is not None:
            raise self.error

    def wait(self) -> Exception | None:
        """Wait for the job; its exception or None."""
        self._thread.join()
        return self.error


class _Pending(NamedTuple):
    """A frame the forward pass left without keypoints, as compact as exact: the decimated depth in its
    recorded units (uint16, converted as ``depth_m`` converts the full image, so the float32 values are the
    ones the forward pass used), its arm mask bit-packed, the TCPs (G, 3) m, closed flags (G,) bool and TCP
    orientations (G, 3, 3), and the decimated colour (h, w, 3) uint8 (None without)."""

    depth: np.ndarray
    scale: float
    arm_bits: np.ndarray | None
    shape: tuple[int, int]
    tcp: np.ndarray | None
    closed: np.ndarray | None
    tcp_rot: np.ndarray | None
    colour: np.ndarray | None = None

    @staticmethod
    def keep(prepared: Any, depth: np.ndarray, scale: float, stride: int, tcp: np.ndarray | None,
             closed: np.ndarray | None, tcp_rot: np.ndarray | None) -> _Pending:
        arm = None if prepared.arm is None else np.packbits(prepared.arm, axis=None)
        dec = np.ascontiguousarray(depth[::stride, ::stride])
        colour = None if prepared.colour is None else np.ascontiguousarray(prepared.colour)  # not the whole frame
        p = _Pending(dec, scale, arm, prepared.depth.shape, tcp, closed, tcp_rot, colour)
        if dec.dtype.kind not in "ui" or dec.shape != p.shape or not np.array_equal(p.prepared().depth,
                                                                                  prepared.depth):
            p = p._replace(depth=prepared.depth.copy(), scale=1.0)  # not so exact: keep the float32 image
        return p

    def prepared(self) -> Any:
        from tracking.pipeline import PreparedFrame

        if self.depth.dtype == np.float32:
            depth = self.depth
        else:
            depth = self.depth.astype(np.float32) * np.float32(self.scale)
        arm = None
        if self.arm_bits is not None:
            n = self.shape[0] * self.shape[1]
            arm = np.unpackbits(self.arm_bits, count=n).astype(bool).reshape(self.shape)
        return PreparedFrame(depth, arm, self.colour)



def stage_medians(stages: list[dict[str, float]]) -> dict[str, float]:
    """Median time of each pipeline stage (``PipelineOutput.timings_ms``: arm, segment, anchors, solve, ...,
    total) over the frames that ran it, ms, from one dict per frame."""
    names = sorted({k for st in stages for k in st})
    return {k: round(float(np.median([st[k] for st in stages if k in st])), 3) for k in names}


def _renumbering(topology: Any, new: Any, X: np.ndarray, last: np.ndarray, span_tol: float) -> np.ndarray | None:
    """The order (N,) int64 that puts a re-initialised track's keypoints X (N, 3) m (topology ``new``) in the
    clip's numbering (``topology``): the identity or the chains' reversal, whichever keeps the edges and lies
    nearer the last keypoints (N, 3) m. None when the edges differ (another split of the keypoints among the
    branches) or the rest lengths add up to more than span_tol (a fraction) away from the clip's (a cloth seen
    edge-on gives a grid squeezed into its strip): the clip's topology cannot hold these keypoints, and the
    frames are filled from its own track."""
    def edge_set(e: np.ndarray) -> set[tuple[int, ...]]:
        return {tuple(sorted(p)) for p in np.asarray(e).tolist()}

    edges = edge_set(topology.edges)
    if edge_set(new.edges) != edges or abs(float(np.sum(new.rest)) / float(np.sum(topology.rest)) - 1.0) > span_tol:
        return None
    N = len(X)
    best, cost = None, np.inf
    for perm in (np.arange(N), np.arange(N)[::-1]):
        if edge_set(perm[np.asarray(topology.edges)]) != edges:
            continue
        c = float(np.linalg.norm(X[perm] - last, axis=1).sum()) if len(last) == N else 0.0
        if c < cost:
            best, cost = perm, c
    return best


# A clip never initialised is tracked again from this fraction of its largest moving part (``track_sequence``):
# below 1 so the stability test (no growth over ``init_stable_frames``) can pass near that part's frame.
INIT_RETRY_FRACTION = 0.8


def track_sequence(
    seq: Any, params: Any, kind: str | None, progress: bool = True, on_frame: Callable[[int], None] | None = None,
    min_init_points: int | None = None,
) -> dict[str, Any]:
    """Run the pipeline over every frame, then fill the frames left without keypoints (before initialisation,
    after a loss) by tracking from their tracked neighbour (``tracking.offline.fill_missing``), and track a run
    of frames left tangled again backwards from the good frame after it, switching to that solution from where
    the two meet when it is better (``tracking.offline.retrack_tangled``; metrics ``retracked_frames``,
    ``retracked_kept``). A chain lengthened within ``params.grow_retrack_frames`` of initialisation has the
    frames up to it tracked again backwards with the longer chain (``tracking.offline.retrack_grown``; metric
    ``grow_retracked``: [initialisation frame, growth frame, 1 if kept] or []); returns raw
    keypoints (T, N, 3) m (NaN only where no frame was ever tracked), grasp indices (T entries (G,) int64
    or None), topology, metrics. The frames without keypoints, those left tangled and the first
    ``params.grow_retrack_frames`` after initialisation are kept in memory for the second pass as the forward
    pass prepared them (decimated uint16 depth and bit-packed arm mask, ~120 kB each at 1280x720
    whatever the clip's length), with their TCPs. on_frame(i) is called after the forward pass's frame i.
    A clip whose moving part never reached the pipeline's ``min_init_points`` (an object mostly hidden, or
    only one end of it moving) is tracked again with that threshold lowered to ``INIT_RETRY_FRACTION`` of the
    largest difference segmentation seen, so it initialises near the frame that showed the most of it
    (metrics ``init_retry_min_points``; min_init_points: that threshold, None for the pipeline's default)."""
    from orchestrator.worker import ArmModel
    from tdrecord.sequence import iter_depth
    from tracking.metrics import sequence_summary, surface_error_mm
    from tracking.offline import FrameInput, fill_missing, retrack_grown, retrack_tangled
    from tracking.pipeline import LivePipeline

    arms = ArmModel(seq.T_world_base) if seq.T_world_base is not None else None
    pipe = LivePipeline(params, seq.K, seq.T_world_cam, kind)
    if min_init_points is not None:
        pipe.min_init_points = min_init_points
    T = len(seq)
    largest = 0  # the largest difference segmentation while waiting, voxels
    raw: list[np.ndarray | None] = []
    grasp: list[np.ndarray | None] = []
    pending: dict[int, _Pending] = {}  # the frames without keypoints or left tangled, for the second pass
    tangled_at: dict[int, tuple[int, float]] = {}  # forward frames left tangled: (tangled, Abs mm)
    statuses: list[str] = []
    tangles = [0, 0]  # forward-pass frames left with a tangled grid / folded chain, frames repaired
    abs_mm, cd_mm, gt_mm, ms = [], [], [], []
    stages: list[dict[str, float]] = []  # each forward frame's LivePipeline.timings_ms (arm: its prepare)
    topology = None
    last = np.zeros((0, 3))  # the last frame's keypoints in the clip's numbering
    first: int | None = None  # the first frame with keypoints (initialisation)
    grown: int | None = None  # the last frame within params.grow_retrack_frames of it that lengthened a chain
    rest_seen = np.zeros(0)  # the rest lengths after the frame before
    t_start = time.monotonic()
    for i, frame in enumerate(iter_depth(seq.frames, colour=kind != "2d")):  # a cloth's tracking reads no colour
        V, F, tcp, closed, rot = _arm_geometry(seq, i, arms)
        full = None if pipe.state == "tracking" else frame.depth_m()  # only initialising needs the whole image
        t0 = time.perf_counter()
        if full is None:  # decimate the recorded image, then scale it (the float32 values decimate() gives)
            prepared = pipe.prepare(frame.depth, V, F, depth_scale=frame.depth_scale, colour=frame.color)
            t_arm = time.perf_counter()
            out = pipe.process(None, tcp=tcp, gripper_closed=closed, prepared=prepared, tcp_rot=rot)
        else:
            t_arm = None
            out = pipe.process(full, V, F, tcp, closed, tcp_rot=rot, colour=frame.color)
        ms.append((time.perf_counter() - t0) * 1e3)
        stages.append({**out.timings_ms, "total": ms[-1]} if t_arm is None else
                      {**out.timings_ms, "arm": (t_arm - t0) * 1e3, "total": ms[-1]})
        statuses.append(out.status)
        if out.status == "waiting":
            largest = max(largest, out.n_points)
        tangles[0] += out.tangled > 0
        tangles[1] += out.repaired and not out.tangled
        if len(out.keypoints) and topology is None:
            topology = out.topology
        kp, g = out.keypoints, out.grasp_idx
        same = topology is not None and len(kp) == topology.n_keypoints
        if same and out.topology is not topology:  # re-initialised after a loss: keypoints numbered anew
            perm = _renumbering(topology, out.topology, kp, last, params.relift_span_tol)
            same = perm is not None
            if perm is not None:
                kp, g = kp[perm], np.where(g >= 0, np.argsort(perm)[np.maximum(g, 0)], -1)
        if same:
            last = kp
            if first is None:
                first, rest_seen = i, topology.rest.copy()
            elif i - first <= params.grow_retrack_frames and not np.array_equal(rest_seen, topology.rest):
                grown, rest_seen = i, topology.rest.copy()  # a chain lengthened (Tracker._grow, in place)
        early = first is not None and i - first <= params.grow_retrack_frames  # tracked again if a chain grows
        raw.append(kp if same else None)
        grasp.append(g if same else None)
        if not same or out.tangled or early:  # tracked (again) in the second pass; a tangled frame keeps the better
            pending[i] = _Pending.keep(out.prepared, frame.depth, frame.depth_scale, pipe.stride, tcp, closed, rot)
        if same and out.tangled:
            tangled_at[i] = (int(out.tangled), float(out.abs_mm))
        if same and out.status != "lost":
            abs_mm.append(out.abs_mm)
            cd_mm.append(out.cd_mm)
            gt = frame.ground_truth
            if gt is not None and len(gt.centreline):
                gt_mm.append(surface_error_mm(out.keypoints, gt.centreline, gt.radius, polyline=gt.category != "cloth"))
        if on_frame is not None:
            on_frame(i)
        if progress and (i % 30 == 0 or i == T - 1):
            print(f"\rtracking frame {i + 1}/{T}  {out.status:9s} {np.mean(ms[-30:]):6.1f} ms/frame", end="",
                  file=sys.stderr, flush=True)
    if progress:
        print(f"\r{T} frames in {time.monotonic() - t_start:.1f} s" + " " * 30, file=sys.stderr)
    if topology is None:
        retry = max(params.min_object_points, int(INIT_RETRY_FRACTION * largest))
        if min_init_points is None and retry < pipe.min_init_points:
            if progress:
                print(f"never initialised (the largest moving part: {largest} voxels < {pipe.min_init_points}); "
                      f"tracking again, initialising from {retry} voxels", file=sys.stderr)
            result = track_sequence(seq, params, kind, progress, on_frame, min_init_points=retry)
            result["metrics"]["init_retry_min_points"] = retry
            return result
        raise RuntimeError(
            f"the object was never initialised in {T} frames (last note: {pipe.last_init_error or 'no motion seen'})"
        )

    def frame_input(i: int) -> FrameInput:
        p = pending[i]  # a frame tracked again after a chain grew may be tracked a third time if left tangled
        return FrameInput(None, tcp=p.tcp, closed=p.closed, prepared=p.prepared(), tcp_rot=p.tcp_rot)

    assert pipe.background is not None  # set at initialisation

    def make_pipeline() -> LivePipeline:
        p = LivePipeline(params, seq.K, seq.T_world_cam, kind)
        p.colour_model = pipe.colour_model  # measured at the forward pass's initialisation
        return p

    took = False
    if grown is not None and first is not None:  # the frames up to a chain's growth, again with the longer chain
        filled, took = retrack_grown(raw, grasp, first, grown, tangled_at, topology, pipe.background,
                                     make_pipeline, frame_input)
        if took:
            for i in range(first, grown + 1):
                tangled_at.pop(i, None)
    else:
        filled = fill_missing(raw, grasp, topology, pipe.background, make_pipeline, frame_input)  # asks missing
    second, again, kept = retrack_tangled(raw, grasp, tangled_at, [i for i, q in filled.quality.items() if q[0]],
                                          topology, pipe.background, make_pipeline, frame_input)
    pending.clear()
    N = topology.n_keypoints
    full = np.stack([r if r is not None else np.full((N, 3), np.nan) for r in raw])
    metrics: dict[str, Any] = {"frames": T, "tracked_frames": len(abs_mm)}
    metrics.update(sequence_summary(np.array(abs_mm), np.array(cd_mm)))
    metrics["ms_per_frame_median"] = float(np.median(ms))
    tracked_ms = [t for t, st in zip(ms, statuses, strict=True) if st in ("tracking", "degraded", "lost")]
    if tracked_ms:  # the frames the forward pass tracked (not waiting for motion, nor initialising)
        metrics["tracked_ms_per_frame_median"] = float(np.median(tracked_ms))
    metrics["backward_frames"], metrics["forward_filled_frames"] = filled.backward, filled.forward
    metrics["grow_retracked"] = [] if grown is None or first is None else [first, grown, int(took)]
    metrics["retracked_frames"], metrics["retracked_kept"] = again, kept  # tangled, tracked backwards again
    if filled.ms:  # the frames without keypoints: before initialisation (backwards), after a loss
        metrics["fill_ms_per_frame_median"] = float(np.median(filled.ms))
    if second.ms:  # the tangled frames tracked again, and what the forward pass took for the same frames
        metrics["retrack_ms_per_frame_median"] = float(np.median(second.ms))
        metrics["retrack_forward_ms_per_frame_median"] = float(np.median([ms[i] for i in second.frames]))
    metrics["stage_ms_median"] = {"forward": stage_medians(stages), "fill": stage_medians(filled.stages),
                                  "retrack": stage_medians(second.stages)}
    metrics["statuses"] = {s: statuses.count(s) for s in sorted(set(statuses))}
    metrics["tangled_frames"], metrics["repaired_frames"] = tangles  # a grid's tangles, a chain's folds
    if gt_mm:
        metrics["gt_rmse_mm"] = float(np.sqrt(np.mean(np.square(gt_mm))))
    return {"raw": full, "grasp": grasp, "topology": topology, "metrics": metrics}


def cmd_track(args: argparse.Namespace) -> int:
    """Track a recorded sequence offline and write ``3d_keypoints.npz`` like the paper's code."""
    from orchestrator.config import load_config
    from orchestrator.worker import tracking_params
    from tdcommon.objects import DIMENSION
    from tdrecord import DatasetError, read_sequence, verify_sequence_files, write_reference_npz
    from tracking.offline import gaps
    from tracking.tangle import clip_tangles
    from tracking.tracker import final_keypoints

    try:
        verify_sequence_files(args.input, structure_only=True)  # a truncated npz is refused before reading it
        seq = read_sequence(args.input)
    except (DatasetError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        print(f"error: {args.input}: cannot be read ({type(e).__name__}: {e})", file=sys.stderr)
        return 2
    category = args.category or seq.metadata.get("category")
    config = load_config(args.config)
    params = tracking_params(config.tracking, category, args.keypoints or seq.metadata.get("n_keypoints"))
    # The CRCs of what tracking does not stream (colour, poses, calibration) are checked beside it; the depth
    # stream checks its own. A corrupt file stops the run at the next frame and nothing is written.
    check = _Background(lambda: verify_sequence_files(args.input, except_streamed=True))
    try:
        result = track_sequence(seq, params, DIMENSION.get(category or ""), progress=not args.json,
                                on_frame=lambda _i: check.raise_if_failed())
    except Exception as e:
        if (bad := check.wait()) is not None:
            print(f"error: {bad}", file=sys.stderr)
            return 2
        if isinstance(e, RuntimeError):
            print(f"error: {args.input}: {e}", file=sys.stderr)
            return 1
        if isinstance(e, DatasetError):
            print(f"error: {e}", file=sys.stderr)
            return 2
        if isinstance(e, (OSError, EOFError, zipfile.BadZipFile, zlib.error)):  # damage found mid-file
            print(f"error: {args.input}: unreadable part ({type(e).__name__}: {e})", file=sys.stderr)
            return 2
        raise
    if (bad := check.wait()) is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    raw, topo = result["raw"], result["topology"]
    final = final_keypoints(raw, topo, params)
    tangled = clip_tangles(final, topo, params.fold_cos)  # flagged, not passed on as good frames
    out = Path(args.out) if args.out else Path(args.input if Path(args.input).is_dir() else Path(args.input).parent)
    out.mkdir(parents=True, exist_ok=True)
    write_reference_npz(out / "3d_keypoints.npz", final, topo.edges, topo.reference_lengths)
    np.savez_compressed(out / "3d_keypoints_raw.npz", raw=raw, edges=topo.edges, rest=topo.rest,
                        anchors=topo.anchor_idx, tangled=tangled)
    metrics = {**result["metrics"], "output_tangled_frames": int((tangled > 0).sum()),
               "output_tangled_runs": [[a, b - 1] for a, b in gaps(tangled == 0)], "category": category,
               "output": str(out / "3d_keypoints.npz")}
    (out / "tracking_metrics.json").write_text(json.dumps(metrics, indent=2))
    if args.json:
        print(json.dumps(metrics))
    else:
        for k, v in metrics.items():
            print(f"{k:22s} {v:.2f}" if isinstance(v, float) else f"{k:22s} {v}")
    return 0


def register(sub: Any) -> None:
    """Add the tracking subcommands to the main parser."""
    w = sub.add_parser("worker", help="run the live tracking worker (zenoh in, keypoints out)")
    w.add_argument("config", help="station config (the session's)")
    w.add_argument("--connect", action="append", help="zenoh endpoint of the daemon or router (repeatable)")
    w.add_argument("--max-frames", type=int)
    w.set_defaults(func=cmd_worker)

    wa = sub.add_parser("watch", help="print live keypoints from the bus")
    wa.add_argument("--config", default=str(DEFAULT_CONFIG))
    wa.add_argument("--connect", action="append", help="zenoh endpoint (default: the config's listen endpoints)")
    wa.add_argument("--station", help="station name (default: the config's)")
    wa.add_argument("--json", action="store_true", help="print each message as JSON")
    wa.add_argument("--count", type=int, help="stop after this many messages")
    wa.add_argument("--seconds", type=float, help="stop after this long")
    wa.set_defaults(func=cmd_watch)

    t = sub.add_parser("track", help="track keypoints offline in episodes or a paper-layout folder")
    t.add_argument("input", help="episode .mcap, folder of episodes, or folder with rgbd.npz (paper layout)")
    t.add_argument("--out", help="output folder (default: beside the input)")
    t.add_argument("--category", choices=["dlo", "bdlo", "cloth"], help="object category (default: metadata)")
    t.add_argument("--keypoints", type=int, help="number of keypoints (1D) or total grid size (cloth)")
    t.add_argument("--config", default=str(DEFAULT_CONFIG), help="tracking parameters from this config")
    t.add_argument("--json", action="store_true", help="print the metrics as JSON")
    t.set_defaults(func=cmd_track)
