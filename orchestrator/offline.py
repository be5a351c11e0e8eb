"""Offline tracking of recorded sequences frame by frame, for the report, ``trackdeform eval`` and re-tracking.

One :class:`tracking.pipeline.LivePipeline` runs across every sequence given (the episodes of one program
run), so the warm start carries from one episode to the next as it does live. A sequence is decoded one
frame at a time: nothing but the current frame is held in memory.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from tdcommon.types import RGBDFrame
from tracking.params import TrackingParams
from tracking.pipeline import LivePipeline, PipelineOutput
from tracking.tracker import Tracker

TrackerFactory = Callable[[TrackingParams, np.ndarray, np.ndarray], Tracker]


@dataclass(frozen=True)
class Variant:
    """One way of tracking a sequence: initialisation params, optional per-frame (ablated) params, tracker."""

    params: TrackingParams
    tracking_params: TrackingParams | None = None
    tracker: TrackerFactory | None = None


@dataclass(frozen=True)
class TrackedFrame:
    """One frame of an offline run: its index in the whole run, the frame, the pipeline's output, and the
    sequence it came from (calibration, metadata)."""

    index: int
    frame: RGBDFrame
    out: PipelineOutput
    sequence: Any


def track_frames(
    sequences: Iterable[Any],
    params: TrackingParams,
    kind: str | None,
    *,
    tracking_params: TrackingParams | None = None,
    tracker: TrackerFactory | None = None,
) -> Iterator[TrackedFrame]:
    """Track every frame of ``sequences`` (``tdrecord.Sequence``, same camera) with one pipeline.

    params: initialisation (and segmentation) parameters. tracking_params: if given, the tracker's
    per-frame solve uses these instead (an ablation switches a constraint off after the same
    initialisation). tracker: builds the pipeline's tracker from (params, K, T_world_cam) (a baseline
    tracker subclassing :class:`tracking.tracker.Tracker` keeps the same initialisation). kind: "1d"/"2d".
    """
    for index, frame, outs, seq in track_variants(sequences, {"": Variant(params, tracking_params, tracker)}, kind):
        yield TrackedFrame(index, frame, outs[""], seq)


def track_variants(
    sequences: Iterable[Any], variants: dict[str, Variant], kind: str | None, max_frames: int | None = None
) -> Iterator[tuple[int, RGBDFrame, dict[str, PipelineOutput], Any]]:
    """Track the frames of ``sequences`` with several variants in lockstep (each frame decoded once and its
    arm geometry built once) -> (index in the run, frame, {variant: output}, sequence) per frame; at most
    ``max_frames`` frames."""
    from orchestrator.cli_tracking import _arm_geometry
    from orchestrator.worker import ArmModel

    pipes: dict[str, LivePipeline] = {}
    K0 = T0 = None
    i = 0
    for seq in sequences:
        if not pipes:
            K0, T0 = seq.K, seq.T_world_cam
            for name, v in variants.items():
                pipe = pipes[name] = LivePipeline(v.params, seq.K, seq.T_world_cam, kind)
                if v.tracker is not None:
                    pipe.tracker = v.tracker(v.params, pipe.K, pipe.T)
        elif not (np.allclose(seq.K, K0) and np.allclose(seq.T_world_cam, T0, atol=1e-9)):
            raise ValueError(f"{seq.source}: calibration differs from the run's first episode; track it separately")
        arms = ArmModel(seq.T_world_base) if seq.T_world_base is not None else None
        for j, frame in enumerate(seq.frames):
            if max_frames is not None and i >= max_frames:
                return
            V, F, tcp, closed, rot = _arm_geometry(seq, j, arms)
            depth = frame.depth_m()
            outs = {}
            for name, v in variants.items():
                pipe = pipes[name]
                if v.tracking_params is not None:  # (re-)initialisation with the full method, the solve ablated
                    pipe.tracker.params = v.tracking_params if pipe.tracker.initialised else v.params
                outs[name] = pipe.process(depth, V, F, tcp, closed, tcp_rot=rot, colour=frame.color)
            yield i, frame, outs, seq
            i += 1
