"""``trackdeform eval ablations|init-consistency|baselines INPUT...``: the paper's Tables I-III from recorded data.

An INPUT is anything ``tdrecord.read_sequence`` reads (an episode, a folder of episodes, a folder in the
paper's layout); a session folder counts as one capture per program run (its episodes grouped by their
metadata, tracked with one warm-started pipeline). Metrics are on raw keypoints over tracked frames
(status init / tracking / degraded), as ``trackdeform track`` and the benchmarks compute them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from orchestrator.config import DEFAULT_CONFIG
from orchestrator.progress import Progress

if TYPE_CHECKING:  # the tracker (open3d and the rest) loads when a command runs, not with the CLI
    from orchestrator.offline import Variant

TRACKED = ("init", "tracking", "degraded")
ABLATIONS: dict[str, dict[str, bool]] = {
    "full": {},
    "w/o anchors": {"use_anchors": False},
    "w/o edge projection": {"use_edge_projection": False},
    "w/o cloud projection": {"use_cloud_projection": False},
}


@dataclass
class Capture:
    """One recorded capture: a name, its category, keypoint count (or None) and a factory of its sequences."""

    name: str
    category: str | None
    n_keypoints: int | None
    sequences: Callable[[], Iterator[Any]]


@dataclass
class Scores:
    """Per-frame figures of one method on one capture."""

    abs_mm: list[float] = field(default_factory=list)
    cd_mm: list[float] = field(default_factory=list)
    gt_mm: list[float] = field(default_factory=list)
    frames: int = 0
    inits: int = 0
    ms: list[float] = field(default_factory=list)

    def add(self, out: Any, frame: Any) -> None:
        """Count one frame's pipeline output (and its GT error when the frame has ground truth)."""
        from tracking.metrics import surface_error_mm

        self.frames += 1
        self.ms.append(out.timings_ms.get("total", float("nan")))
        self.inits += out.status == "init"
        if out.status not in TRACKED or not len(out.keypoints) or not math.isfinite(out.cd_mm):
            return
        self.abs_mm.append(float(out.abs_mm))
        self.cd_mm.append(float(out.cd_mm))
        gt = frame.ground_truth
        if gt is not None and len(gt.centreline):
            polyline = gt.category != "cloth"
            self.gt_mm.append(surface_error_mm(out.keypoints, gt.centreline, gt.radius, polyline=polyline))

    def extend(self, other: Scores) -> None:
        """Pool another capture's frames into these."""
        self.abs_mm += other.abs_mm
        self.cd_mm += other.cd_mm
        self.gt_mm += other.gt_mm
        self.frames += other.frames
        self.inits += other.inits
        self.ms += other.ms

    def summary(self) -> dict[str, Any]:
        """Abs, E<5, CD, F<10 (tracking.metrics.sequence_summary), GT RMSE, frames, initialisations, ms/frame."""
        from tracking.metrics import sequence_summary

        out: dict[str, Any] = {"frames": self.frames, "tracked_frames": len(self.abs_mm), "initialisations": self.inits}
        if self.abs_mm:
            out.update(sequence_summary(np.asarray(self.abs_mm), np.asarray(self.cd_mm)))
        else:
            out.update({"Abs": float("nan"), "E<5": float("nan"), "CD": float("nan"), "F<10": float("nan")})
        out["GT"] = float(np.sqrt(np.mean(np.square(self.gt_mm)))) if self.gt_mm else None
        out["ms_per_frame_median"] = float(np.nanmedian(self.ms)) if self.ms else float("nan")
        return out


def captures(inputs: list[str], category: str | None, n_keypoints: int | None) -> list[Capture]:
    """The captures of the inputs: one per program run of a session folder, else one per input."""
    from orchestrator.report import group_runs
    from tdrecord import read_episode_metadata, read_episodes, read_sequence
    from tdrecord.episodes import episode_files

    out: list[Capture] = []
    for inp in inputs:
        path = Path(inp)
        files, _ = episode_files(path) if path.is_dir() else ([], [])
        if len(files) > 1 and not (path / "rgbd.npz").exists():
            for run in group_runs(files):
                meta = read_episode_metadata(run.episodes[0])
                out.append(Capture(f"{path.name}: {run.label}", category or meta.get("category"),
                                   n_keypoints or meta.get("n_keypoints"),
                                   lambda eps=tuple(run.episodes): (read_episodes(p) for p in eps)))
            continue
        seq = read_sequence(path)  # errors (missing, not a dataset) surface here, naming the path
        out.append(Capture(path.name, category or seq.metadata.get("category"),
                           n_keypoints or seq.metadata.get("n_keypoints"), lambda s=seq: iter([s])))
    return out


def _object_name(c: Capture) -> str:
    return c.category or "unknown"


def evaluate_variants(caps: list[Capture], config: Any, make: Callable[[Any], dict[str, Variant]],
                      max_frames: int | None, progress: Progress) -> dict[str, dict[str, Scores]]:
    """{category: {variant: pooled Scores}} of every capture tracked with every variant in lockstep."""
    from orchestrator.offline import track_variants
    from orchestrator.worker import tracking_params
    from tdcommon.objects import DIMENSION

    pooled: dict[str, dict[str, Scores]] = {}
    for n, cap in enumerate(caps):
        params = tracking_params(config.tracking, cap.category, cap.n_keypoints)
        variants = make(params)
        scores = {name: Scores() for name in variants}
        for i, frame, outs, _ in track_variants(cap.sequences(), variants, DIMENSION.get(cap.category or ""),
                                                max_frames):
            for name, out in outs.items():
                scores[name].add(out, frame)
            progress.update(f"[{n + 1}/{len(caps)}] {cap.name}: frame {i}")
        group = pooled.setdefault(_object_name(cap), {name: Scores() for name in variants})
        for name, s in scores.items():
            group[name].extend(s)
    progress.done()
    return pooled


def ablation_variants(params: Any) -> dict[str, Variant]:
    """The paper's Table II: the full method and each constraint switched off in the per-frame solve."""
    from orchestrator.offline import Variant

    return {name: Variant(params, replace(params, **off) if off else None) for name, off in ABLATIONS.items()}


def baseline_variants(params: Any, beta_m: float = 0.05, lam: float = 2.0) -> dict[str, Variant]:
    """The full method beside CPD and nearest-neighbour tracking, with the same segmentation and initialisation."""
    from orchestrator.offline import Variant
    from tracking.baselines import BaselineTracker

    return {
        "TrackDeform3D": Variant(params),
        "CPD": Variant(params, tracker=partial(BaselineTracker, method="cpd", cpd_beta_m=beta_m, cpd_lambda=lam)),
        "nearest neighbour": Variant(params, tracker=partial(BaselineTracker, method="nn")),
    }


def init_consistency(caps: list[Capture], config: Any, max_frames: int | None, progress: Progress) -> dict[str, Any]:
    """The paper's Table III: initialise each capture from scratch; per-keypoint spread over the captures
    (RMS distance to the mean position, and the largest distance), with Abs / CD / F<10 of the
    initialisation frames. Every capture must be of one category and keypoint count."""
    from orchestrator.offline import Variant, track_variants
    from orchestrator.worker import tracking_params
    from tdcommon.objects import DIMENSION
    from tracking.metrics import percent_below

    cats = {c.category for c in caps}
    if len(cats) != 1:
        raise ValueError(f"init-consistency compares captures of one object; got categories {sorted(map(str, cats))}")
    inits: list[np.ndarray] = []
    abs_mm, cd_mm, names, failed = [], [], [], []
    for n, cap in enumerate(caps):
        params = tracking_params(config.tracking, cap.category, cap.n_keypoints)
        found = None
        for i, _, outs, _ in track_variants(cap.sequences(), {"": Variant(params)}, DIMENSION.get(cap.category or ""),
                                            max_frames):
            progress.update(f"[{n + 1}/{len(caps)}] {cap.name}: frame {i}")
            if outs[""].status == "init":
                found = outs[""]
                break
        if found is None:
            failed.append(cap.name)
            continue
        if inits and len(found.keypoints) != len(inits[0]):
            raise ValueError(f"{cap.name}: {len(found.keypoints)} keypoints, the first capture has {len(inits[0])}")
        inits.append(np.asarray(found.keypoints))
        abs_mm.append(found.abs_mm)
        cd_mm.append(found.cd_mm)
        names.append(cap.name)
    progress.done()
    if len(inits) < 2:
        raise ValueError(f"init-consistency needs at least 2 initialised captures; got {len(inits)} "
                         f"(not initialised: {failed or 'none'})")
    P = np.stack(inits)  # (C, N, 3) m
    dev = np.linalg.norm(P - P.mean(axis=0), axis=2)  # (C, N)
    std = np.sqrt(np.mean(dev**2, axis=0))  # (N,)
    return {
        "object": cats.pop(), "captures": len(inits), "not_initialised": failed, "names": names,
        "spread_std_mm": float(1e3 * std.max()), "spread_std_median_mm": float(1e3 * np.median(std)),
        "spread_maxdev_mm": float(1e3 * dev.max()), "per_keypoint_std_mm": np.round(1e3 * std, 3).tolist(),
        "Abs": float(np.mean(abs_mm)), "CD": float(np.mean(cd_mm)), "F<10": percent_below(np.array(cd_mm), 10.0),
    }


def _table(rows: list[dict[str, Any]], cols: list[tuple[str, str, str]]) -> str:
    head = "  ".join(f"{t:>{max(len(t), 8)}}" if i else f"{t:<22}" for i, (t, _, _) in enumerate(cols))
    lines = [head, "-" * len(head)]
    for r in rows:
        cells = []
        for i, (t, k, fmt) in enumerate(cols):
            v = r.get(k)
            s = "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)
            cells.append(f"{s:>{max(len(t), 8)}}" if i else f"{s:<22}")
        lines.append("  ".join(cells))
    return "\n".join(lines)


TABLE = [("method", "method", "{}"), ("object", "object", "{}"), ("Abs mm", "Abs", "{:.2f}"),
         ("E<5 %", "E<5", "{:.1f}"), ("CD mm", "CD", "{:.2f}"), ("F<10 %", "F<10", "{:.1f}"), ("GT mm", "GT", "{:.2f}"),
         ("tracked", "tracked_frames", "{}"), ("frames", "frames", "{}"), ("inits", "initialisations", "{}"),
         ("ms/frame", "ms_per_frame_median", "{:.1f}")]


def cmd_eval(args: argparse.Namespace) -> int:
    """Run one evaluation and print its table (or JSON)."""
    from orchestrator.config import ConfigError, load_config
    from tdrecord import DatasetError

    try:
        config = load_config(args.config)
        caps = captures(args.inputs, args.category, args.keypoints)
        progress = Progress(enabled=not args.json)
        if args.what == "init-consistency":
            result = init_consistency(caps, config, args.max_frames, progress)
            if args.json:
                print(json.dumps(result))
            else:
                print(f"{result['object']}: {result['captures']} captures"
                      + (f" ({len(result['not_initialised'])} not initialised)" if result["not_initialised"] else ""))
                cols = [("object", "object", "{}"), ("spread mm", "spread_std_mm", "{:.2f}"),
                        ("median", "spread_std_median_mm", "{:.2f}"), ("max dev", "spread_maxdev_mm", "{:.2f}"),
                        ("Abs mm", "Abs", "{:.2f}"), ("CD mm", "CD", "{:.2f}"), ("F<10 %", "F<10", "{:.1f}")]
                print(_table([result], cols))
            return 0
        make = ablation_variants if args.what == "ablations" else partial(baseline_variants, beta_m=args.cpd_beta,
                                                                         lam=args.cpd_lambda)
        pooled = evaluate_variants(caps, config, make, args.max_frames, progress)
    except (ConfigError, DatasetError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    rows = [{"method": m, "object": obj, **s.summary()} for obj, group in pooled.items() for m, s in group.items()]
    if args.json:
        print(json.dumps({"evaluation": args.what, "captures": [c.name for c in caps], "rows": rows}))
    else:
        print(_table(rows, TABLE))
    return 0


def register(sub: Any) -> None:
    """Add ``eval`` to the main parser."""
    e = sub.add_parser("eval", help="the paper's tables on recorded data: ablations, init-consistency, baselines")
    e.add_argument("what", choices=["ablations", "init-consistency", "baselines"])
    e.add_argument("inputs", nargs="+", help="sessions (one capture per run), episodes or paper-layout folders")
    e.add_argument("--config", default=str(DEFAULT_CONFIG), help="tracking parameters from this config")
    e.add_argument("--category", choices=["dlo", "bdlo", "cloth"], help="object category (default: metadata)")
    e.add_argument("--keypoints", type=int, help="number of keypoints (1D) or total grid size (cloth)")
    e.add_argument("--max-frames", type=int, help="track at most this many frames of each capture")
    e.add_argument("--cpd-beta", type=float, default=0.05, help="CPD motion-coherence kernel width, m")
    e.add_argument("--cpd-lambda", type=float, default=2.0, help="CPD regularisation weight")
    e.add_argument("--json", action="store_true", help="print the table as JSON")
    e.set_defaults(func=cmd_eval)
