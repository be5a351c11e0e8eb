"""Per-frame timings and quality of the tracking pipeline on synthetic depth sequences (no assertions).

Usage: .venv/bin/python benchmarks/tracking_synthetic.py [--width 1280 --height 720 --frames 40]
Rendering is not timed. Timed per frame: arm mask (raycast), segmentation against the background,
tracker step (anchor re-detection + solve + scoring). Initialisation is timed once per sequence.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdcommon.meshes import box_mesh, sheet_mesh, tube_mesh  # noqa: E402
from tracking import synthetic as S  # noqa: E402
from tracking.metrics import anchor_error_mm, sequence_summary, surface_error_mm  # noqa: E402
from tracking.params import TrackingParams  # noqa: E402
from tracking.segmentation import background_from_depths, render_arm_mask, segment_against_background  # noqa: E402
from tracking.tracker import Tracker, TrackStatus, smooth_symmetric  # noqa: E402


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rope_frames(n: int):
    for k in range(n):
        c = S.rope_centreline(0.12 * k)
        yield [tube_mesh(c, 0.006)], c, 0.006, c[[0, -1]], True


def yrope_frames(n: int):
    base = S.y_rope_branches()
    for k in range(n):
        R = _rot_z(0.03 * k)
        br = [b @ R.T + np.array([0.002 * k, 0.0, 0.0]) for b in base]
        anchors = np.array([br[0][0]] + [b[-1] for b in br])
        yield [tube_mesh(b, 0.006) for b in br], np.concatenate(br), 0.006, anchors, False


def cloth_frames(n: int):
    for k in range(n):
        cs = S.cloth_surface(wave=0.25 * k, height=0.12 + 0.002 * k)
        yield [sheet_mesh(cs)], cs.reshape(-1, 3), 0.0, cs[[0, 0, -1, -1], [0, -1, 0, -1]], False


def run(name: str, frames, K, T, shape, params: TrackingParams, rng: np.random.Generator) -> None:
    H, W = shape
    arm = box_mesh((0.42, 0.2, 0.2), (0.04, 0.04, 0.2))
    table = S.table_mesh()
    bg = background_from_depths(np.stack([S.render_depth([table, arm], K, T, shape, rng=rng) for _ in range(3)]))
    data = [(S.render_depth([table, arm, *m], K, T, shape, rng=rng), c, r, a, pl) for m, c, r, a, pl in frames]
    tr = Tracker(params, K, T)
    t_arm, t_seg, t_trk, abs_mm, cd_mm, gt, anc, raw = [], [], [], [], [], [], [], []
    t_init = float("nan")
    bad = 0
    for k, (depth, cl, radius, anchors, polyline) in enumerate(data):
        t0 = time.perf_counter()
        am = render_arm_mask(arm[0], arm[1], K, T, shape, params.arm_margin_px, depth, params.arm_margin_m)
        t1 = time.perf_counter()
        seg = segment_against_background(depth, bg, K, T, params, am, tr.keypoints)
        t2 = time.perf_counter()
        if k == 0:
            _, r = tr.initialise(seg.points)
            t_init = time.perf_counter() - t2
        else:
            r = tr.step(seg.points)
            t3 = time.perf_counter()
            t_arm.append(t1 - t0)
            t_seg.append(t2 - t1)
            t_trk.append(t3 - t2)
        bad += r.status != TrackStatus.OK
        abs_mm.append(r.edge_rmse_mm)
        cd_mm.append(r.chamfer_mm)
        gt.append(surface_error_mm(r.keypoints, cl, radius, polyline=polyline))
        topo = tr.topology
        if topo is not None:
            kinds = topo.anchor_kind
            sel = topo.anchor_idx if topo.kind == "1d" else topo.anchor_idx[kinds == 3]
            anc.append(anchor_error_mm(r.keypoints[sel], anchors))
        raw.append(r.keypoints)
    ms = 1e3 * np.array([t_arm, t_seg, t_trk])
    tot = ms.sum(axis=0)
    s = sequence_summary(np.array(abs_mm), np.array(cd_mm))
    smooth = smooth_symmetric(np.stack(raw), params.symmetric_window)
    jitter_raw = np.mean(np.linalg.norm(np.diff(np.stack(raw), 2, axis=0), axis=2)) * 1e3
    jitter_s = np.mean(np.linalg.norm(np.diff(smooth, 2, axis=0), axis=2)) * 1e3
    topo = tr.topology
    print(
        f"{name:7s} N={len(raw[-1]):3d} E={len(topo.edges) if topo else 0:3d} pts={len(seg.points):5d} | "
        f"init {1e3 * t_init:6.1f} ms | per frame median: arm {np.median(ms[0]):5.1f} seg {np.median(ms[1]):5.1f} "
        f"track {np.median(ms[2]):5.1f} total {np.median(tot):5.1f} ms (p90 {np.percentile(tot, 90):5.1f}) | "
        f"Abs {s['Abs']:.2f} mm E<5 {s['E<5']:.0f}% CD {s['CD']:.2f} mm F<10 {s['F<10']:.0f}% | "
        f"GT {np.mean(gt):.2f} mm anchors {np.nanmean(anc):.1f} mm | not-OK frames {bad} | "
        f"accel jitter raw {jitter_raw:.2f} -> smoothed {jitter_s:.2f} mm/frame^2"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--paper-projection", action="store_true", help="nearest-point cloud projection (surface_k=1)")
    ap.add_argument("--voxel", type=float, default=TrackingParams.voxel_m, help="voxel size, m")
    ap.add_argument("--stride", type=int, default=TrackingParams.lift_stride, help="pixel lift stride")
    ap.add_argument("--only", choices=["rope", "Y-rope", "cloth"], default=None)
    a = ap.parse_args()
    params = TrackingParams(surface_k=1 if a.paper_projection else 8, voxel_m=a.voxel, lift_stride=a.stride)
    K, T = S.default_camera(a.width, a.height)
    shape = (a.height, a.width)
    print(
        f"{a.width}x{a.height}, {a.frames} frames per sequence, surface_k={params.surface_k}, "
        f"voxel {params.voxel_m * 1e3:.1f} mm, lift stride {params.lift_stride}"
    )
    rng = np.random.default_rng(0)
    for name, gen in (("rope", rope_frames), ("Y-rope", yrope_frames), ("cloth", cloth_frames)):
        if a.only in (None, name):
            run(name, gen(a.frames), K, T, shape, params, rng)


if __name__ == "__main__":
    main()
