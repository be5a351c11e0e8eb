"""Recorder throughput: 1280x720 RGB-D frames through the episode recorder at 30 Hz, real time.

Frames come from the mock renderer (default) or from a test-bed / paper-layout ``rgbd.npz``
(``--frames PATH``, colour BGR, depth uint16 mm); ``--pool`` frames are held in memory and played in a
loop, with arm states at ``--state-rate`` Hz beside them and 5 s episodes, as a session records them.
Prints MB/s to disk, the recorder's CPU per frame (its thread and its depth-encoding thread), MB per
episode, colour PSNR against the raw frames, whether depth reads back bit-exact, frames lost and how
long the 30 Hz loop waited on the recorder. Middle episodes are deleted once counted (``--keep``).

Run: .venv/bin/python benchmarks/recorder.py [--minutes 5] [--frames rgbd.npz] [--crf 18] ...
(prints figures; no assertions)
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestrator.config import ColorOutputConfig, DepthOutputConfig  # noqa: E402
from orchestrator.recorder import Recorder  # noqa: E402
from tdcommon.types import CameraIntrinsics, RGBDFrame  # noqa: E402
from tdrecord import read_episodes  # noqa: E402

FPS = 30.0


def mock_frames(n: int, width: int, height: int) -> tuple[list[np.ndarray], list[np.ndarray], CameraIntrinsics]:
    """``n`` consecutive frames of the simulated rope station (both arms moving)."""
    from render import mock_objects, station

    _, cam = station(mock_objects()["rope"], width, height)
    colors, depths = [], []
    for _ in range(n):
        f = cam.read()
        colors.append(f.color)
        depths.append(f.depth)
    return colors, depths, f.intrinsics


def file_frames(path: Path, n: int) -> tuple[list[np.ndarray], list[np.ndarray], CameraIntrinsics]:
    """The first ``n`` frames of an ``rgbd.npz`` (colour BGR -> RGB)."""
    with np.load(path) as z:
        c, d = z["color"], z["depth"]
        colors = [np.ascontiguousarray(x[..., ::-1]) for x in c[:n]]
        depths = [np.ascontiguousarray(x, dtype=np.uint16) for x in d[:n]]
    h, w = depths[0].shape
    return colors, depths, CameraIntrinsics.from_fov(w, h, 69.0)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of uint8 image ``a`` against ``b``."""
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=5.0, help="recorded time (default 5)")
    ap.add_argument("--frames", type=Path, help="an rgbd.npz (paper / test-bed layout) instead of the mock renderer")
    ap.add_argument("--pool", type=int, default=60, help="frames held in memory and looped (default 60)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--color", default="h264", choices=["h264", "jpeg", "raw"])
    ap.add_argument("--crf", type=int, default=ColorOutputConfig().crf)
    ap.add_argument("--preset", default=ColorOutputConfig().preset)
    ap.add_argument("--gop", type=int, default=ColorOutputConfig().gop)
    ap.add_argument("--jpeg-quality", type=int, default=ColorOutputConfig().jpeg_quality)
    ap.add_argument("--depth", default="png", choices=["png", "planes", "raw"])
    ap.add_argument("--compression", default="zstd", choices=["zstd", "lz4", "none"])
    ap.add_argument("--state-rate", type=float, default=250.0, help="arm-state samples per second (default 250)")
    ap.add_argument("--episode-seconds", type=float, default=5.0)
    ap.add_argument("--out", type=Path, help="folder for the episodes (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep every episode (default: first and last only)")
    args = ap.parse_args()

    t0 = time.perf_counter()
    colors, depths, intr = (file_frames(args.frames, args.pool) if args.frames
                            else mock_frames(args.pool, args.width, args.height))
    h, w = depths[0].shape
    src = str(args.frames) if args.frames else "mock renderer (rope)"
    print(f"{len(colors)} frames {w}x{h} from {src} in {time.perf_counter() - t0:.1f} s; "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    color_cfg = ColorOutputConfig(codec=args.color, crf=args.crf, preset=args.preset, gop=args.gop,
                                  jpeg_quality=args.jpeg_quality)
    depth_cfg = DepthOutputConfig(codec=args.depth)
    print(f"colour {color_cfg.model_dump()}  depth {depth_cfg.model_dump()}  MCAP chunks {args.compression}")

    out = args.out or Path(tempfile.mkdtemp(prefix="recorder-bench-"))
    out.mkdir(parents=True, exist_ok=True)
    rec = Recorder("cam0", args.compression, color=color_cfg, depth=depth_cfg)
    n_frames = int(round(args.minutes * 60.0 * FPS))
    per_episode = int(round(args.episode_seconds * FPS))
    state_every = 1.0 / args.state_rate
    tcp = {"left_tcp": np.eye(4), "right_tcp": np.eye(4)}
    sizes: dict[Path, int] = {}
    waits, late = [], 0
    wall0, cpu0 = time.perf_counter(), time.process_time()
    next_state = 0.0
    for k in range(n_frames):
        t_frame = k / FPS
        now = time.perf_counter() - wall0
        if now < t_frame:
            time.sleep(t_frame - now)
        elif now - t_frame > 1.0 / FPS:
            late += 1
        if k % per_episode == 0:
            if k:
                rec.close_episode({"complete": True})
            rec.open_episode(out / f"episode_{k // per_episode:06d}.mcap", {"object": "bench"})
        while next_state <= t_frame:
            arm = {"stamp": next_state, "q": [0.0] * 7, "dq": [0.0] * 7, "gripper_width": 0.05, "grasped": False}
            rec.arm_state({"stamp": next_state, "left": arm, "right": arm, "u": [0.0] * 12}, tcp)
            next_state += state_every
        i = k % len(colors)
        frame = RGBDFrame(colors[i], depths[i], 0.001, intr, t_frame, t_frame, k)
        t = time.perf_counter()
        rec.frame(frame, np.eye(4))
        waits.append(time.perf_counter() - t)
        for p in rec.finished[:-1]:  # the newest finished file is kept as the "last" one until the end
            if p not in sizes:
                sizes[p] = p.stat().st_size
                if not args.keep and len(sizes) > 1:
                    p.unlink()
    rec.close_episode({"complete": True})
    rec.stop(timeout=600)
    wall = time.perf_counter() - wall0
    cpu_proc = time.process_time() - cpu0
    for p in rec.finished:
        if p not in sizes:
            sizes[p] = p.stat().st_size
    recorded = n_frames / FPS
    total = sum(sizes.values())

    first, last = rec.finished[0], rec.finished[-1]
    ps, exact, read = [], True, 0
    for path in (first, last):
        seq = read_episodes(path)
        for f in seq.frames:
            i = f.frame_number % len(colors)
            ps.append(psnr(f.color, colors[i]))
            exact &= bool(np.array_equal(f.depth, depths[i]))
            read += 1
    from mcap.reader import make_reader

    stored = 0  # colour messages in the files still on disk (their summaries)
    for p in rec.finished:
        if p.exists():
            with open(p, "rb") as fh:
                summary = make_reader(fh).get_summary()
            stored += sum(n for cid, n in summary.statistics.channel_message_counts.items()
                          if summary.channels[cid].topic == "/cam/cam0/color")
    counted = rec.frames_written
    mbps = total / recorded / 1e6
    cores = rec.cpu_seconds / wall
    print(f"recorded {recorded:.0f} s of {n_frames} frames in {wall:.1f} s wall; {len(sizes)} episodes")
    print(f"disk          : {mbps:.2f} MB/s  ({total / len(sizes) / 1e6:.1f} MB per {args.episode_seconds:g} s "
          f"episode, "
          f"{total / n_frames / 1e3:.0f} kB per frame)")
    print(f"recorder CPU  : {rec.cpu_seconds / n_frames * 1e3:.1f} ms per frame = {cores:.2f} cores "
          f"(whole process {cpu_proc / wall:.2f} cores)")
    print(f"colour PSNR   : {np.mean(ps):.2f} dB mean, {np.min(ps):.2f} min over {read} frames read back")
    print(f"depth         : {'bit-exact' if exact else 'NOT bit-exact'} over those frames")
    lost = n_frames - counted
    print(f"frames lost   : {lost} (written {counted} of {n_frames}; kept files hold {stored}); recorder errors "
          f"{len(rec.errors)}")
    print(f"30 Hz loop    : waited on the recorder max {max(waits) * 1e3:.1f} ms, p99 "
          f"{np.percentile(waits, 99) * 1e3:.2f} ms; {late} ticks more than a frame late")
    ok = {"<= 20 MB/s": mbps <= 20.0, "<= 0.5 core": cores <= 0.5, "PSNR >= 40 dB": np.mean(ps) >= 40.0,
          "depth bit-exact": exact, "0 frames lost": lost == 0 and not rec.errors}
    print("targets       : " + ", ".join(f"{k} {'met' if v else 'MISSED'}" for k, v in ok.items()))
    if not args.out and not args.keep:
        shutil.rmtree(out)  # the episodes and the digests written beside them


if __name__ == "__main__":
    main()
