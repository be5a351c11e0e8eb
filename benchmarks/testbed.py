"""``trackdeform track`` on the independent test bed (``../shared/testbed``): generate, track, score, one table.

Usage: .venv/bin/python benchmarks/testbed.py [--cache DIR] [--testbed DIR] [--testbed-python PY]
       [--set dev|variants|all] [--only NAME[,NAME]] [--list] [--json] [--cores N] [--ablations] [--truth]

The test bed is a second simulated station (MuJoCo physics, its own renderer, stereo depth noise) with
its own scorer; see its README. This script

1. finds it (``--testbed``, else ``../shared/testbed`` beside the repository; absent: a message, exit 0);
2. finds its Python (``--testbed-python``, ``$TESTBED_PYTHON``, ``<cache>/venv`` or ``../tbvenv`` beside
   the repository), else creates ``<cache>/venv`` from its ``requirements.txt``;
3. generates the sequences that are not yet in ``<cache>/sequences`` (a ``make_sequence.py --jobs``
   call each; a sequence is a pure function of its arguments, so a cached one is reused);
4. runs ``trackdeform track`` on each as a lab would (rgbd.npz, arm poses, joint states, calibration and
   the object category; never the masks or ground truth), output in ``<cache>/tracks/<name>``;
5. scores ``3d_keypoints.npz`` with the test bed's ``score.py`` and prints one table, then the rows that miss one
   of issue 10's targets (``TARGETS``), each missed figure with its limit.

Columns: missing = frames with a missing keypoint (%); object / anchors / coverage / Abs / CD in mm,
E<5 and F<10 in % of all frames (the scorer's definitions); ms/frame = the tracker's median per-frame
time over the frames its forward pass tracked (``tracking_metrics.json``; not the frames before initialisation,
which only wait for motion), fill ms/frame = the same for the frames tracked backwards (or forwards after a loss)
from a tracked neighbour (the frames the forward pass left tangled and that are tracked again backwards are timed
apart: ``retrack_ms_per_frame_median`` in ``tracking_metrics.json``, beside the forward pass's time for the same
frames, ``retrack_forward_ms_per_frame_median``), wall ms/frame = the whole ``track`` command's wall time per
frame (start-up, reading the clip, both passes, writing: what a lab waits for), cpu ms/frame = the CPU time
(user + system, all its threads) the command used per frame, which a busy shared machine inflates less than
the wall time. ``--cores N`` runs each ``track`` command on N cores of this process's affinity mask (1: the
issue's one-core figures).

``--ablations`` tracks every sequence once per variant of the paper's Table II (``trackdeform eval
ablations``' variants: the full method, without anchors, without edge-length projection, without cloud
projection; each a copy of configs/mock.yaml with one switch off) and adds the mean over the sequences of
each variant: the scorer's ground-truth columns (object, anchors, coverage) beside the paper's Abs and CD,
which ``trackdeform eval`` cannot show on sequences without ground truth.

``--truth`` also scores the ground truth itself as a tracker's output (``truth_keypoints``: exact keypoints at
the tracker's spacing) and adds its CD and F<10: the scorer measures CD to the visible surface only, so keypoints
exactly on a part out of sight (a cloth's far side seen edge-on, a rope above the image) count against it, and on
some sequences exact keypoints miss the CD / F<10 targets.

The default set (``--set all``) is the five-sequence development set plus the variants below (camera
from the side and from above, rope lengths 0.8-1.0 m, radii 4-7 mm, colours, the three speeds, other
seeds; 110 sequences); generating it the first time takes ~2 h with two generators at once, 2-5 hours one at a
time (1-3.5 min a sequence on this 2-core machine), and ~15 GB; tracking and scoring it ~16 min here.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the repository, before this folder's tracking.py
from tracking.init import grid_topology, polyline_arc  # noqa: E402

REPO = Path(__file__).resolve().parent.parent

# The test bed's development set (make_sequence.py --all), by keyword set.
DEV: list[dict[str, Any]] = [
    dict(name="rope_medium", obj="rope", speed="medium", seconds=6, seed=1),
    dict(name="bdlo_medium", obj="bdlo", speed="medium", seconds=6, seed=2),
    dict(name="cloth_medium", obj="cloth", speed="medium", seconds=6, seed=3),
    dict(name="rope_fast", obj="rope", speed="fast", seconds=5, seed=4),
    dict(name="rope_samecolor_slow", obj="rope", speed="slow", seconds=6, seed=5, samecolor=True),
]
# Variants: other seeds, views, sizes, colours and speeds (camera = eye x,y,z, target x,y,z in the world, m).
SIDE = [1.05, 0.55, 0.55, 0.45, -0.45, 0.20]
ABOVE = [0.95, -0.45, 1.45, 0.45, -0.45, 0.10]
OBLIQUE = [1.35, -0.05, 0.85, 0.50, -0.45, 0.15]
FRONT_LOW = [1.25, -0.45, 0.60, 0.45, -0.45, 0.15]
OBLIQUE_RIGHT = [1.2, -0.95, 1.0, 0.45, -0.40, 0.15]
HIGH_FRONT = [1.6, -0.45, 1.1, 0.45, -0.45, 0.15]
VARIANTS: list[dict[str, Any]] = [
    dict(name="rope_side_long_thin", obj="rope", speed="medium", seconds=5, seed=11, camera=SIDE, length=1.0,
         radius=0.004, rgb=[0.15, 0.3, 0.85]),
    dict(name="rope_above_short_thick", obj="rope", speed="fast", seconds=5, seed=12, camera=ABOVE, length=0.8,
         radius=0.007, rgb=[0.9, 0.75, 0.1]),
    dict(name="rope_slow_r5", obj="rope", speed="slow", seconds=6, seed=13, length=0.85, radius=0.005,
         rgb=[0.1, 0.6, 0.2]),
    dict(name="bdlo_above_fast", obj="bdlo", speed="fast", seconds=5, seed=2, camera=ABOVE, branch_len=0.25),
    dict(name="bdlo_side_slow", obj="bdlo", speed="slow", seconds=6, seed=15, camera=SIDE, length=0.95,
         radius=0.005, rgb=[0.8, 0.2, 0.6]),
    dict(name="cloth_side_fast", obj="cloth", speed="fast", seconds=5, seed=16, camera=SIDE),
    dict(name="cloth_above_slow", obj="cloth", speed="slow", seconds=6, seed=17, camera=ABOVE),
    dict(name="cloth_medium_s41", obj="cloth", speed="medium", seconds=6, seed=41),
    dict(name="cloth_fast_cam2", obj="cloth", speed="fast", seconds=5, seed=42, camera=OBLIQUE),
    dict(name="bdlo_slow_s43", obj="bdlo", speed="slow", seconds=6, seed=43, length=0.85, radius=0.005,
         branch_len=0.22),
    dict(name="rope_medium_cam2", obj="rope", speed="medium", seconds=6, seed=44, camera=OBLIQUE, length=0.95,
         radius=0.0065, rgb=[0.7, 0.3, 0.1]),
    dict(name="rope_slow_front", obj="rope", speed="slow", seconds=5, seed=52, camera=FRONT_LOW, length=0.95,
         radius=0.0045, rgb=[0.85, 0.15, 0.15]),
    dict(name="bdlo_medium_obl2", obj="bdlo", speed="medium", seconds=5, seed=53, camera=OBLIQUE_RIGHT,
         branch_len=0.28),
    dict(name="bdlo_fast_s54", obj="bdlo", speed="fast", seconds=5, seed=54),
    dict(name="cloth_slow_s55", obj="cloth", speed="slow", seconds=5, seed=55),
    dict(name="cloth_medium_obl2", obj="cloth", speed="medium", seconds=5, seed=56, camera=OBLIQUE_RIGHT),
    dict(name="rope_fast_samecolor", obj="rope", speed="fast", seconds=5, seed=57, samecolor=True, length=0.85,
         radius=0.006),
    dict(name="rope_above_fast_s61", obj="rope", speed="fast", seconds=5, seed=61, camera=ABOVE, length=0.9,
         radius=0.005, rgb=[0.2, 0.2, 0.8]),
    dict(name="rope_medium_obl2_s62", obj="rope", speed="medium", seconds=5, seed=62, camera=OBLIQUE_RIGHT,
         length=0.85, radius=0.007, rgb=[0.9, 0.5, 0.1]),
    dict(name="rope_side_slow_s64", obj="rope", speed="slow", seconds=5, seed=64, camera=SIDE, radius=0.0055),
    dict(name="rope_slow_high_s81", obj="rope", speed="slow", seconds=5, seed=81, camera=HIGH_FRONT, length=0.95,
         radius=0.006, rgb=[0.6, 0.6, 0.1]),
    dict(name="rope_medium_side_s83", obj="rope", speed="medium", seconds=5, seed=83, camera=SIDE, length=0.85,
         radius=0.0045, rgb=[0.1, 0.5, 0.5]),
    dict(name="bdlo_medium_high_s84", obj="bdlo", speed="medium", seconds=5, seed=84, camera=HIGH_FRONT,
         branch_len=0.24, radius=0.006, rgb=[0.2, 0.6, 0.9]),
    dict(name="bdlo_slow_obl2_s85", obj="bdlo", speed="slow", seconds=5, seed=85, camera=OBLIQUE_RIGHT, length=0.9,
         branch_len=0.2),
    dict(name="rope_fast_obl2_s91", obj="rope", speed="fast", seconds=5, seed=91, camera=OBLIQUE_RIGHT, length=0.9,
         radius=0.005, rgb=[0.3, 0.7, 0.3]),
    dict(name="bdlo_medium_side_s92", obj="bdlo", speed="medium", seconds=5, seed=92, camera=SIDE, branch_len=0.22),
    dict(name="rope_slow_above_s93", obj="rope", speed="slow", seconds=5, seed=93, camera=ABOVE, length=0.85,
         radius=0.006, rgb=[0.8, 0.4, 0.4]),
    dict(name="bdlo_fast_obl_s94", obj="bdlo", speed="fast", seconds=5, seed=94, camera=OBLIQUE, length=0.95,
         branch_len=0.26, radius=0.0055),
    dict(name="rope_medium_high_s95", obj="rope", speed="medium", seconds=5, seed=95, camera=HIGH_FRONT, length=1.0,
         radius=0.0045),
    dict(name="rope_medium_front_s96", obj="rope", speed="medium", seconds=5, seed=96, camera=FRONT_LOW, length=0.8,
         radius=0.0065, rgb=[0.9, 0.9, 0.9]),
    dict(name="rope_fast_s101", obj="rope", speed="fast", seconds=5, seed=101, length=0.95, radius=0.0055,
         rgb=[0.9, 0.5, 0.1]),
    dict(name="bdlo_slow_s102", obj="bdlo", speed="slow", seconds=5, seed=102, branch_len=0.27),
    dict(name="cloth_fast_s103", obj="cloth", speed="fast", seconds=5, seed=103),
    dict(name="cloth_medium_s104", obj="cloth", speed="medium", seconds=5, seed=104),
    dict(name="rope_medium_samecolor_s105", obj="rope", speed="medium", seconds=5, seed=105, samecolor=True),
    dict(name="bdlo_medium_high_s106", obj="bdlo", speed="medium", seconds=5, seed=106, camera=HIGH_FRONT, length=0.85,
         branch_len=0.23),
    dict(name="cloth_slow_side_s111", obj="cloth", speed="slow", seconds=5, seed=111, camera=SIDE),
    dict(name="cloth_fast_high_s112", obj="cloth", speed="fast", seconds=5, seed=112, camera=HIGH_FRONT),
    dict(name="cloth_medium_front_s113", obj="cloth", speed="medium", seconds=5, seed=113, camera=FRONT_LOW),
    dict(name="cloth_medium_above_s114", obj="cloth", speed="medium", seconds=5, seed=114, camera=ABOVE),
    dict(name="cloth_fast_obl_s115", obj="cloth", speed="fast", seconds=5, seed=115, camera=OBLIQUE),
    dict(name="bdlo_slow_high_s121", obj="bdlo", speed="slow", seconds=5, seed=121, camera=HIGH_FRONT, length=0.9,
         branch_len=0.26),
    dict(name="bdlo_fast_above_s125", obj="bdlo", speed="fast", seconds=5, seed=125, camera=ABOVE, radius=0.006,
         branch_len=0.22, rgb=[0.7, 0.2, 0.2]),
    dict(name="bdlo_medium_front_s123", obj="bdlo", speed="medium", seconds=5, seed=123, camera=FRONT_LOW,
         length=0.85, branch_len=0.25),
    dict(name="rope_fast_high_s124", obj="rope", speed="fast", seconds=5, seed=124, camera=HIGH_FRONT, length=0.9,
         radius=0.0055, rgb=[0.5, 0.3, 0.7]),
    dict(name="rope_slow_obl_s127", obj="rope", speed="slow", seconds=5, seed=127, camera=OBLIQUE, length=0.85,
         radius=0.0045),
    dict(name="bdlo_fast_side_s130", obj="bdlo", speed="fast", seconds=5, seed=130, camera=SIDE,
         branch_len=0.24, rgb=[0.3, 0.3, 0.8]),
    dict(name="bdlo_medium_obl_s129", obj="bdlo", speed="medium", seconds=5, seed=129, camera=OBLIQUE,
         branch_len=0.2, radius=0.0055),
    dict(name="cloth_medium_s131", obj="cloth", speed="medium", seconds=5, seed=131,
         camera=[1.15, -0.75, 1.2, 0.45, -0.45, 0.15]),
    dict(name="cloth_slow_s132", obj="cloth", speed="slow", seconds=5, seed=132,
         camera=[1.0, 0.1, 0.9, 0.45, -0.45, 0.2]),
    dict(name="cloth_fast_s133", obj="cloth", speed="fast", seconds=5, seed=133,
         camera=[0.75, -0.45, 1.35, 0.45, -0.45, 0.1]),
    dict(name="cloth_medium_s134", obj="cloth", speed="medium", seconds=5, seed=134,
         camera=[1.5, -0.2, 1.0, 0.45, -0.45, 0.15], rgb=[0.8, 0.2, 0.2]),
    # sixteen more in one batch, scored once before any change they prompted (seeds 141-158)
    dict(name="rope_medium_u141", obj="rope", speed="medium", seconds=5, seed=141,
         camera=[1.4, 0.05, 0.95, 0.5, -0.45, 0.18], length=0.92, radius=0.0052, rgb=[0.2, 0.8, 0.8]),
    dict(name="rope_fast_u142", obj="rope", speed="fast", seconds=5, seed=142,
         camera=[1.3, -0.7, 0.75, 0.45, -0.45, 0.15], length=0.82, radius=0.0068, rgb=[0.6, 0.1, 0.6]),
    dict(name="rope_slow_u143", obj="rope", speed="slow", seconds=5, seed=143,
         camera=[1.25, -0.35, 1.3, 0.5, -0.45, 0.15], length=1.0, radius=0.004),
    dict(name="bdlo_fast_u144", obj="bdlo", speed="fast", seconds=5, seed=144,
         camera=[1.35, -0.85, 0.85, 0.45, -0.42, 0.15], branch_len=0.21),
    dict(name="bdlo_slow_u145", obj="bdlo", speed="slow", seconds=5, seed=145,
         length=0.9, radius=0.0065, rgb=[0.9, 0.9, 0.2]),
    dict(name="bdlo_medium_u146", obj="bdlo", speed="medium", seconds=5, seed=146,
         camera=[1.1, 0.25, 1.05, 0.45, -0.45, 0.18], branch_len=0.27),
    dict(name="cloth_medium_u147", obj="cloth", speed="medium", seconds=5, seed=147,
         camera=[1.5, -0.6, 0.9, 0.45, -0.45, 0.15]),
    dict(name="cloth_fast_u148", obj="cloth", speed="fast", seconds=5, seed=148, rgb=[0.2, 0.5, 0.8]),
    dict(name="rope_slow_above_u151", obj="rope", speed="slow", seconds=5, seed=151,
         camera=[0.9, -0.5, 1.5, 0.45, -0.45, 0.1], length=0.95, radius=0.006, rgb=[0.85, 0.3, 0.2]),
    dict(name="bdlo_medium_above_u152", obj="bdlo", speed="medium", seconds=5, seed=152,
         camera=[1.0, -0.35, 1.4, 0.45, -0.45, 0.1], radius=0.005, branch_len=0.23),
    dict(name="cloth_medium_above_u153", obj="cloth", speed="medium", seconds=5, seed=153,
         camera=[0.95, -0.55, 1.5, 0.45, -0.45, 0.1]),
    dict(name="rope_fast_side_u154", obj="rope", speed="fast", seconds=5, seed=154,
         camera=[1.1, 0.5, 0.6, 0.45, -0.45, 0.2], length=0.88, radius=0.005),
    dict(name="bdlo_slow_side_u155", obj="bdlo", speed="slow", seconds=5, seed=155,
         camera=[1.0, 0.6, 0.5, 0.45, -0.45, 0.2], branch_len=0.25, rgb=[0.2, 0.7, 0.3]),
    dict(name="cloth_fast_side_u156", obj="cloth", speed="fast", seconds=5, seed=156,
         camera=[1.05, 0.5, 0.6, 0.45, -0.45, 0.2]),
    dict(name="rope_medium_u157", obj="rope", speed="medium", seconds=5, seed=157,
         length=0.8, radius=0.0045, rgb=[0.95, 0.95, 0.95]),
    dict(name="bdlo_fast_u158", obj="bdlo", speed="fast", seconds=5, seed=158,
         camera=[1.5, -0.45, 0.8, 0.45, -0.45, 0.15], length=0.85, radius=0.006, branch_len=0.2),
    # seven more generated at the end of that session and scored once (seeds 161-168)
    dict(name="rope_medium_v161", obj="rope", speed="medium", seconds=5, seed=161,
         camera=[0.6, -1.5, 0.9, 0.5, -0.45, 0.2], length=0.9, radius=0.0055, rgb=[0.9, 0.2, 0.5]),
    dict(name="rope_slow_v163", obj="rope", speed="slow", seconds=5, seed=163,
         camera=[1.3, -0.9, 1.3, 0.45, -0.45, 0.1], length=0.85, radius=0.0065),
    dict(name="bdlo_medium_v164", obj="bdlo", speed="medium", seconds=5, seed=164,
         camera=[0.85, -0.3, 1.45, 0.45, -0.45, 0.1], branch_len=0.24, rgb=[0.1, 0.3, 0.9]),
    dict(name="rope_fast_v165", obj="rope", speed="fast", seconds=5, seed=165,
         camera=[1.2, 0.3, 0.7, 0.45, -0.45, 0.2], length=1.0, radius=0.005, rgb=[0.3, 0.3, 0.3]),
    dict(name="bdlo_slow_v166", obj="bdlo", speed="slow", seconds=5, seed=166,
         camera=[1.45, -0.7, 0.65, 0.45, -0.45, 0.2], length=0.95, branch_len=0.22),
    dict(name="cloth_medium_v167", obj="cloth", speed="medium", seconds=5, seed=167,
         camera=[1.6, -0.35, 0.85, 0.45, -0.45, 0.15], rgb=[0.9, 0.8, 0.2]),
    dict(name="bdlo_fast_v168", obj="bdlo", speed="fast", seconds=5, seed=168,
         camera=[1.2, -1.0, 1.2, 0.45, -0.4, 0.15], branch_len=0.28, radius=0.006),
    # seventeen more in two batches, scored before any change they prompted (seeds 171-198; 162 and 175 put a
    # waypoint out of the right arm's reach)
    dict(name="rope_medium_w171", obj="rope", speed="medium", seconds=5, seed=171,
         length=0.95, radius=0.0045, rgb=[0.2, 0.7, 0.3]),
    dict(name="rope_fast_w172", obj="rope", speed="fast", seconds=5, seed=172,
         camera=[1.4, -0.1, 0.9, 0.5, -0.45, 0.2], length=0.82, radius=0.007),
    dict(name="rope_slow_w173", obj="rope", speed="slow", seconds=5, seed=173, length=0.88, samecolor=True),
    dict(name="bdlo_medium_w174", obj="bdlo", speed="medium", seconds=5, seed=174, branch_len=0.2, radius=0.005),
    dict(name="bdlo_slow_w176", obj="bdlo", speed="slow", seconds=5, seed=176,
         camera=[1.55, -0.45, 0.95, 0.5, -0.45, 0.2], rgb=[0.8, 0.5, 0.1]),
    dict(name="cloth_medium_w177", obj="cloth", speed="medium", seconds=5, seed=177,
         camera=[1.45, -0.55, 0.8, 0.5, -0.45, 0.2]),
    dict(name="cloth_fast_w178", obj="cloth", speed="fast", seconds=5, seed=178,
         camera=[1.35, -0.2, 1.0, 0.5, -0.45, 0.2], rgb=[0.2, 0.5, 0.8]),
    dict(name="cloth_slow_w179", obj="cloth", speed="slow", seconds=5, seed=179),
    dict(name="bdlo_fast_w185", obj="bdlo", speed="fast", seconds=5, seed=185,
         camera=[1.3, -0.8, 1.0, 0.5, -0.45, 0.2], branch_len=0.26),
    dict(name="cloth_fast_x191", obj="cloth", speed="fast", seconds=5, seed=191),
    dict(name="cloth_medium_x192", obj="cloth", speed="medium", seconds=5, seed=192,
         camera=[1.4, -0.7, 0.95, 0.5, -0.45, 0.2]),
    dict(name="cloth_fast_x193", obj="cloth", speed="fast", seconds=5, seed=193,
         camera=[1.5, -0.1, 0.85, 0.5, -0.45, 0.2], rgb=[0.3, 0.7, 0.3]),
    dict(name="cloth_slow_x194", obj="cloth", speed="slow", seconds=5, seed=194,
         camera=[1.55, -0.35, 0.75, 0.5, -0.45, 0.22], rgb=[0.85, 0.85, 0.85]),
    dict(name="cloth_fast_x195", obj="cloth", speed="fast", seconds=5, seed=195,
         camera=[1.35, -0.6, 0.9, 0.5, -0.45, 0.2]),
    dict(name="cloth_medium_x196", obj="cloth", speed="medium", seconds=5, seed=196, rgb=[0.6, 0.2, 0.6]),
    dict(name="cloth_medium_x197", obj="cloth", speed="medium", seconds=5, seed=197,
         camera=[1.3, -0.45, 1.05, 0.5, -0.45, 0.2]),
    dict(name="cloth_fast_x198", obj="cloth", speed="fast", seconds=5, seed=198,
         camera=[1.45, -0.25, 0.95, 0.5, -0.45, 0.2]),
    # generated at the end of session 26 and only scored (every target met)
    dict(name="cloth_medium_y201", obj="cloth", speed="medium", seconds=5, seed=201,
         camera=[1.5, -0.6, 0.9, 0.5, -0.45, 0.2], rgb=[0.8, 0.3, 0.3]),
    dict(name="cloth_fast_y202", obj="cloth", speed="fast", seconds=5, seed=202,
         camera=[1.4, -0.3, 0.8, 0.5, -0.45, 0.2]),
    dict(name="cloth_slow_y203", obj="cloth", speed="slow", seconds=5, seed=203,
         camera=[1.55, -0.5, 1.0, 0.5, -0.45, 0.2], rgb=[0.3, 0.4, 0.8]),
    dict(name="rope_medium_y207", obj="rope", speed="medium", seconds=5, seed=207,
         camera=[1.45, -0.2, 0.95, 0.5, -0.45, 0.2], length=0.92, radius=0.006, rgb=[0.7, 0.2, 0.2]),
    dict(name="cloth_medium_y204", obj="cloth", speed="medium", seconds=5, seed=204,
         camera=[1.3, -0.55, 0.95, 0.5, -0.45, 0.2]),
    dict(name="cloth_fast_y205", obj="cloth", speed="fast", seconds=5, seed=205, rgb=[0.9, 0.6, 0.2]),
    dict(name="cloth_medium_y206", obj="cloth", speed="medium", seconds=5, seed=206,
         camera=[1.6, -0.45, 0.9, 0.5, -0.45, 0.2], rgb=[0.2, 0.6, 0.6]),
    dict(name="bdlo_medium_y208", obj="bdlo", speed="medium", seconds=5, seed=208,
         camera=[1.4, -0.65, 1.0, 0.5, -0.45, 0.2], branch_len=0.23, radius=0.0055),
    # generated at the start of session 28, at camera poses no row above uses, and only scored
    dict(name="rope_fast_z211", obj="rope", speed="fast", seconds=5, seed=211,
         camera=[1.3, 0.2, 1.2, 0.45, -0.45, 0.15], length=0.95, radius=0.004, rgb=[0.1, 0.6, 0.9]),
    dict(name="bdlo_slow_z212", obj="bdlo", speed="slow", seconds=5, seed=212,
         camera=[0.9, -1.2, 1.1, 0.45, -0.45, 0.15], branch_len=0.22, radius=0.0065, rgb=[0.8, 0.7, 0.1]),
    dict(name="cloth_medium_z213", obj="cloth", speed="medium", seconds=5, seed=213,
         camera=[1.7, -0.3, 0.75, 0.45, -0.45, 0.2], rgb=[0.7, 0.3, 0.7]),
    dict(name="rope_slow_z214", obj="rope", speed="slow", seconds=5, seed=214,
         camera=[1.4, -0.9, 0.6, 0.45, -0.45, 0.2], length=0.82, radius=0.0068),
    dict(name="cloth_fast_z216", obj="cloth", speed="fast", seconds=5, seed=216,
         camera=[1.2, -1.0, 1.2, 0.45, -0.45, 0.15], rgb=[0.3, 0.8, 0.4]),
    # generated after e7b01b1, at camera poses no row above uses, and only scored
    dict(name="rope_medium_q221", obj="rope", speed="medium", seconds=5, seed=221,
         camera=[1.25, -0.05, 0.9, 0.45, -0.45, 0.2], length=0.88, radius=0.005, rgb=[0.9, 0.9, 0.9]),
    dict(name="bdlo_fast_q225", obj="bdlo", speed="fast", seconds=5, seed=225,
         camera=[1.6, -0.75, 0.85, 0.5, -0.45, 0.2], branch_len=0.25, radius=0.005, rgb=[0.2, 0.3, 0.9]),
    dict(name="rope_slow_q223", obj="rope", speed="slow", seconds=5, seed=223,
         camera=[1.1, -0.6, 1.3, 0.5, -0.45, 0.15], length=1.0, radius=0.0045),
    dict(name="cloth_medium_q224", obj="cloth", speed="medium", seconds=5, seed=224,
         camera=[1.35, -0.15, 1.1, 0.5, -0.45, 0.2], rgb=[0.85, 0.85, 0.3]),
    # generated after 0ea060e, only scored (camera poses no other row uses)
    dict(name="rope_fast_r231", obj="rope", speed="fast", seconds=5, seed=231,
         camera=[1.45, -0.3, 0.75, 0.45, -0.45, 0.15], length=0.85, radius=0.006, rgb=[0.2, 0.7, 0.3]),
    dict(name="bdlo_medium_r232", obj="bdlo", speed="medium", seconds=5, seed=232,
         camera=[1.0, -0.85, 1.2, 0.45, -0.45, 0.15], branch_len=0.22, radius=0.0055, rgb=[0.9, 0.5, 0.1]),
    dict(name="cloth_fast_r233", obj="cloth", speed="fast", seconds=5, seed=233,
         camera=[1.5, -0.55, 0.95, 0.45, -0.45, 0.2]),
    dict(name="bdlo_slow_r234", obj="bdlo", speed="slow", seconds=5, seed=234,
         camera=[1.3, 0.1, 1.0, 0.5, -0.45, 0.15], radius=0.004),
    dict(name="cloth_slow_t241", obj="cloth", speed="slow", seconds=5, seed=241,
         camera=[1.15, 0.25, 1.05, 0.45, -0.45, 0.2], rgb=[0.3, 0.5, 0.8]),
    dict(name="rope_medium_t242", obj="rope", speed="medium", seconds=5, seed=242,
         camera=[1.5, -0.9, 0.8, 0.45, -0.4, 0.15], length=0.95, radius=0.0065, rgb=[0.75, 0.15, 0.15]),
    dict(name="bdlo_fast_t243", obj="bdlo", speed="fast", seconds=5, seed=243,
         camera=[1.4, -0.45, 1.3, 0.45, -0.45, 0.1], branch_len=0.28, radius=0.005),
    dict(name="rope_slow_t244", obj="rope", speed="slow", seconds=5, seed=244,
         camera=[0.9, -0.1, 1.25, 0.45, -0.45, 0.1], length=0.8, radius=0.004, rgb=[0.95, 0.6, 0.1]),
    # generated after 1e6bea3, at camera poses no other row uses, and scored before any change they prompted
    dict(name="rope_medium_k251", obj="rope", speed="medium", seconds=5, seed=251,
         camera=[1.2, -0.7, 1.4, 0.5, -0.45, 0.15], length=0.9, radius=0.005, rgb=[0.6, 0.1, 0.8]),
    dict(name="bdlo_slow_k252", obj="bdlo", speed="slow", seconds=5, seed=252,
         camera=[1.65, -0.2, 1.1, 0.45, -0.45, 0.15], branch_len=0.26, radius=0.006, rgb=[0.1, 0.7, 0.7]),
    dict(name="cloth_fast_k253", obj="cloth", speed="fast", seconds=5, seed=253,
         camera=[1.05, -0.3, 1.35, 0.45, -0.45, 0.15], rgb=[0.8, 0.3, 0.3]),
    dict(name="rope_fast_k254", obj="rope", speed="fast", seconds=5, seed=254,
         camera=[1.55, -1.0, 1.05, 0.45, -0.45, 0.15], length=0.85, radius=0.0065),
    dict(name="bdlo_medium_k255", obj="bdlo", speed="medium", seconds=5, seed=255,
         camera=[1.25, 0.3, 0.85, 0.45, -0.45, 0.2], branch_len=0.3, radius=0.0045, rgb=[0.9, 0.8, 0.2]),
    dict(name="cloth_medium_k256", obj="cloth", speed="medium", seconds=5, seed=256,
         camera=[1.6, -0.7, 1.25, 0.5, -0.45, 0.15], rgb=[0.5, 0.8, 0.9]),
    dict(name="rope_slow_k257", obj="rope", speed="slow", seconds=5, seed=257,
         camera=[0.95, -0.5, 1.4, 0.45, -0.45, 0.15], length=1.0, radius=0.0055, rgb=[0.2, 0.2, 0.9]),
    dict(name="bdlo_fast_k258", obj="bdlo", speed="fast", seconds=5, seed=258,
         camera=[1.45, -0.15, 0.7, 0.45, -0.45, 0.2], branch_len=0.24, radius=0.0055),
    dict(name="cloth_slow_k259", obj="cloth", speed="slow", seconds=5, seed=259,
         camera=[1.35, -1.1, 0.9, 0.45, -0.45, 0.2], rgb=[0.9, 0.9, 0.9]),
    # generated after 26a4152, at camera poses no other row uses, and only scored
    dict(name="rope_fast_m261", obj="rope", speed="fast", seconds=5, seed=261,
         camera=[1.1, -0.95, 1.15, 0.45, -0.45, 0.15], length=0.92, radius=0.0058, rgb=[0.85, 0.35, 0.6]),
    dict(name="bdlo_medium_m262", obj="bdlo", speed="medium", seconds=5, seed=262,
         camera=[1.5, 0.05, 1.2, 0.45, -0.45, 0.15], branch_len=0.27, radius=0.005, rgb=[0.3, 0.8, 0.3]),
    dict(name="cloth_medium_m263", obj="cloth", speed="medium", seconds=5, seed=263,
         camera=[1.45, -0.35, 1.3, 0.45, -0.45, 0.15], rgb=[0.95, 0.5, 0.2]),
    dict(name="rope_slow_m264", obj="rope", speed="slow", seconds=5, seed=264,
         camera=[1.7, -0.6, 0.95, 0.45, -0.45, 0.2], length=0.86, radius=0.0047),
    dict(name="bdlo_fast_m265", obj="bdlo", speed="fast", seconds=5, seed=265,
         camera=[1.05, -0.15, 1.05, 0.45, -0.45, 0.2], branch_len=0.25, radius=0.006, rgb=[0.6, 0.2, 0.9]),
    dict(name="cloth_fast_m266", obj="cloth", speed="fast", seconds=5, seed=266,
         camera=[1.25, -0.8, 1.05, 0.5, -0.45, 0.2], rgb=[0.4, 0.6, 0.95]),
    # generated after a35ac5f, at camera poses no other row uses, and scored before any change they prompted
    dict(name="rope_slow_n271", obj="rope", speed="slow", seconds=5, seed=271,
         camera=[1.35, -0.85, 1.0, 0.45, -0.45, 0.15], length=0.88, radius=0.0052, rgb=[0.1, 0.5, 0.9]),
    dict(name="bdlo_fast_n272", obj="bdlo", speed="fast", seconds=5, seed=272,
         camera=[1.2, 0.2, 1.3, 0.45, -0.45, 0.15], branch_len=0.23, radius=0.0048, rgb=[0.9, 0.2, 0.2]),
    dict(name="cloth_slow_n273", obj="cloth", speed="slow", seconds=5, seed=273,
         camera=[1.55, -0.15, 1.0, 0.45, -0.45, 0.2], rgb=[0.7, 0.7, 0.3]),
    dict(name="rope_medium_n274", obj="rope", speed="medium", seconds=5, seed=274,
         camera=[0.85, -0.8, 1.3, 0.45, -0.45, 0.15], length=0.97, radius=0.0068, rgb=[0.9, 0.9, 0.9]),
    dict(name="bdlo_slow_n275", obj="bdlo", speed="slow", seconds=5, seed=275,
         camera=[1.6, -0.4, 0.8, 0.45, -0.45, 0.2], branch_len=0.29, radius=0.0058, rgb=[0.2, 0.3, 0.2]),
    dict(name="cloth_medium_n276", obj="cloth", speed="medium", seconds=5, seed=276,
         camera=[1.15, -1.0, 1.15, 0.45, -0.45, 0.15], rgb=[0.6, 0.2, 0.5]),
    # generated at the start of session 34, at camera poses no other row uses, and scored before any change (seed
    # 285 put a waypoint out of the right arm's reach)
    dict(name="rope_fast_p281", obj="rope", speed="fast", seconds=5, seed=281,
         camera=[1.5, -0.75, 1.25, 0.45, -0.45, 0.15], length=0.84, radius=0.0062, rgb=[0.95, 0.75, 0.1]),
    dict(name="bdlo_medium_p282", obj="bdlo", speed="medium", seconds=5, seed=282,
         camera=[1.3, -0.5, 1.4, 0.45, -0.45, 0.15], branch_len=0.21, radius=0.0052, rgb=[0.8, 0.8, 0.8]),
    dict(name="cloth_fast_p283", obj="cloth", speed="fast", seconds=5, seed=283,
         camera=[1.45, -0.85, 1.1, 0.45, -0.45, 0.2], rgb=[0.2, 0.4, 0.7]),
    dict(name="rope_slow_p284", obj="rope", speed="slow", seconds=5, seed=284,
         camera=[1.0, -0.25, 1.35, 0.45, -0.45, 0.15], length=0.93, radius=0.0042, rgb=[0.5, 0.2, 0.1]),
    dict(name="bdlo_fast_p287", obj="bdlo", speed="fast", seconds=5, seed=287,
         camera=[1.55, 0.0, 0.95, 0.45, -0.45, 0.2], branch_len=0.26, radius=0.0062, rgb=[0.1, 0.6, 0.5]),
    dict(name="cloth_medium_p286", obj="cloth", speed="medium", seconds=5, seed=286,
         camera=[1.2, -0.25, 1.25, 0.45, -0.45, 0.15], rgb=[0.9, 0.9, 0.5]),
    # generated at the start of session 35, at camera poses no other row uses, and scored before any change
    dict(name="rope_medium_q291", obj="rope", speed="medium", seconds=5, seed=291,
         camera=[1.4, -0.1, 1.2, 0.45, -0.45, 0.15], length=0.95, radius=0.0066, rgb=[0.3, 0.9, 0.6]),
    dict(name="bdlo_slow_q292", obj="bdlo", speed="slow", seconds=5, seed=292,
         camera=[1.15, -0.7, 1.35, 0.45, -0.45, 0.15], branch_len=0.25, radius=0.0056, rgb=[0.9, 0.5, 0.1]),
    dict(name="cloth_slow_q293", obj="cloth", speed="slow", seconds=5, seed=293,
         camera=[1.4, -0.6, 1.05, 0.45, -0.45, 0.2], rgb=[0.3, 0.7, 0.3]),
    dict(name="rope_fast_q294", obj="rope", speed="fast", seconds=5, seed=294,
         camera=[1.25, -1.05, 0.95, 0.45, -0.45, 0.2], length=0.81, radius=0.0045, rgb=[0.7, 0.1, 0.1]),
    dict(name="bdlo_medium_q295", obj="bdlo", speed="medium", seconds=5, seed=295,
         camera=[1.6, -0.05, 1.15, 0.45, -0.45, 0.15], branch_len=0.28, radius=0.0065),
    dict(name="cloth_fast_q296", obj="cloth", speed="fast", seconds=5, seed=296,
         camera=[1.3, 0.0, 1.2, 0.45, -0.45, 0.15], rgb=[0.5, 0.5, 0.8]),
    # generated at the start of session 36, at camera poses no other row uses, and scored before any change
    dict(name="rope_slow_j301", obj="rope", speed="slow", seconds=5, seed=301,
         camera=[1.2, -0.55, 1.4, 0.45, -0.45, 0.15], length=0.89, radius=0.0061, rgb=[0.6, 0.4, 0.9]),
    dict(name="bdlo_fast_j302", obj="bdlo", speed="fast", seconds=5, seed=302,
         camera=[1.4, -0.9, 1.15, 0.45, -0.45, 0.15], branch_len=0.22, radius=0.0059, rgb=[0.2, 0.5, 0.9]),
    dict(name="cloth_medium_j303", obj="cloth", speed="medium", seconds=5, seed=303,
         camera=[1.05, -0.6, 1.3, 0.45, -0.45, 0.15], rgb=[0.8, 0.6, 0.4]),
    dict(name="rope_medium_j304", obj="rope", speed="medium", seconds=5, seed=304,
         camera=[1.65, -0.3, 1.15, 0.45, -0.45, 0.15], length=0.83, radius=0.0049, rgb=[0.9, 0.6, 0.6]),
    dict(name="bdlo_slow_j305", obj="bdlo", speed="slow", seconds=5, seed=305,
         camera=[1.3, 0.15, 1.05, 0.45, -0.45, 0.2], branch_len=0.3, radius=0.0054, rgb=[0.4, 0.4, 0.9]),
    dict(name="cloth_slow_j306", obj="cloth", speed="slow", seconds=5, seed=306,
         camera=[1.5, -0.45, 1.35, 0.45, -0.45, 0.15], rgb=[0.9, 0.3, 0.6]),
    # generated in session 39, at camera poses no other row uses, and scored before any change (seeds 315, 317,
    # 319 and 321 put a waypoint of the fast branched-rope program out of the right arm's reach)
    dict(name="rope_fast_g311", obj="rope", speed="fast", seconds=5, seed=311,
         camera=[1.35, -0.35, 1.0, 0.45, -0.45, 0.2], length=0.86, radius=0.0052, rgb=[0.95, 0.75, 0.2]),
    dict(name="bdlo_medium_g312", obj="bdlo", speed="medium", seconds=5, seed=312,
         camera=[1.1, -0.3, 1.45, 0.45, -0.45, 0.15], branch_len=0.24, radius=0.0058, rgb=[0.7, 0.3, 0.7]),
    dict(name="cloth_slow_g313", obj="cloth", speed="slow", seconds=5, seed=313,
         camera=[1.55, -0.75, 1.2, 0.45, -0.45, 0.15], rgb=[0.4, 0.6, 0.9]),
    dict(name="rope_slow_g314", obj="rope", speed="slow", seconds=5, seed=314,
         camera=[1.25, 0.3, 1.2, 0.45, -0.45, 0.15], length=0.97, radius=0.0068, rgb=[0.2, 0.8, 0.8]),
    dict(name="bdlo_fast_g323", obj="bdlo", speed="fast", seconds=5, seed=323,
         camera=[1.5, -0.6, 0.95, 0.45, -0.45, 0.2], branch_len=0.27, radius=0.0047, rgb=[0.95, 0.95, 0.95]),
    dict(name="cloth_medium_g316", obj="cloth", speed="medium", seconds=5, seed=316,
         camera=[1.3, -0.2, 1.4, 0.45, -0.45, 0.15], rgb=[0.85, 0.4, 0.3]),
    # generated in session 40, at camera poses no other row uses, and scored before any change
    dict(name="rope_medium_h331", obj="rope", speed="medium", seconds=5, seed=331,
         camera=[1.0, -0.15, 1.25, 0.45, -0.45, 0.15], length=0.92, radius=0.0044, rgb=[0.3, 0.9, 0.4]),
    dict(name="bdlo_slow_h332", obj="bdlo", speed="slow", seconds=5, seed=332,
         camera=[1.6, -0.1, 1.3, 0.45, -0.45, 0.15], branch_len=0.25, radius=0.0065, rgb=[0.9, 0.5, 0.1]),
    dict(name="cloth_fast_h333", obj="cloth", speed="fast", seconds=5, seed=333,
         camera=[1.2, -0.8, 1.05, 0.45, -0.45, 0.2], rgb=[0.3, 0.7, 0.5]),
    dict(name="rope_fast_h334", obj="rope", speed="fast", seconds=5, seed=334,
         camera=[1.45, 0.05, 1.5, 0.45, -0.45, 0.15], length=0.81, radius=0.0063, rgb=[0.8, 0.2, 0.2]),
    dict(name="bdlo_medium_h335", obj="bdlo", speed="medium", seconds=5, seed=335,
         camera=[1.15, -0.45, 0.95, 0.45, -0.45, 0.2], branch_len=0.2, radius=0.005, rgb=[0.5, 0.9, 0.9]),
    dict(name="cloth_slow_h336", obj="cloth", speed="slow", seconds=5, seed=336,
         camera=[1.7, -0.6, 1.4, 0.45, -0.45, 0.15], rgb=[0.6, 0.6, 0.2]),
    # generated in session 41, at camera poses no other row uses, and scored before any change (seed 342 put a
    # waypoint of the fast branched-rope program out of the right arm's reach)
    dict(name="rope_slow_e341", obj="rope", speed="slow", seconds=5, seed=341,
         camera=[1.4, -0.55, 1.15, 0.45, -0.45, 0.2], length=0.88, radius=0.0047, rgb=[0.9, 0.9, 0.3]),
    dict(name="bdlo_fast_e347", obj="bdlo", speed="fast", seconds=5, seed=347,
         camera=[1.25, 0.1, 1.35, 0.45, -0.45, 0.15], branch_len=0.23, radius=0.006, rgb=[0.2, 0.5, 0.9]),
    dict(name="cloth_medium_e343", obj="cloth", speed="medium", seconds=5, seed=343,
         camera=[1.45, -0.4, 1.1, 0.45, -0.45, 0.2], rgb=[0.9, 0.6, 0.3]),
    dict(name="rope_medium_e344", obj="rope", speed="medium", seconds=5, seed=344,
         camera=[1.65, -0.35, 1.2, 0.45, -0.45, 0.15], length=0.99, radius=0.0057, rgb=[0.6, 0.2, 0.8]),
    dict(name="bdlo_slow_e345", obj="bdlo", speed="slow", seconds=5, seed=345,
         camera=[1.05, -0.55, 1.15, 0.45, -0.45, 0.2], branch_len=0.29, radius=0.0043, rgb=[0.9, 0.3, 0.3]),
    dict(name="cloth_fast_e346", obj="cloth", speed="fast", seconds=5, seed=346,
         camera=[1.35, -0.1, 1.2, 0.45, -0.45, 0.2], rgb=[0.3, 0.4, 0.8]),
    # generated in session 42, at camera poses no other row uses, and scored before any change
    dict(name="rope_fast_f351", obj="rope", speed="fast", seconds=5, seed=351,
         camera=[1.55, 0.2, 1.1, 0.45, -0.45, 0.2], length=0.86, radius=0.0055, rgb=[0.2, 0.8, 0.9]),
    dict(name="bdlo_medium_f352", obj="bdlo", speed="medium", seconds=5, seed=352,
         camera=[1.1, -0.75, 1.4, 0.45, -0.45, 0.15], branch_len=0.26, radius=0.0052, rgb=[0.9, 0.9, 0.2]),
    dict(name="cloth_slow_f353", obj="cloth", speed="slow", seconds=5, seed=353,
         camera=[1.3, -0.3, 1.55, 0.45, -0.45, 0.15], rgb=[0.8, 0.3, 0.6]),
    dict(name="rope_slow_f354", obj="rope", speed="slow", seconds=5, seed=354,
         camera=[0.95, -0.35, 1.05, 0.45, -0.45, 0.2], length=0.94, radius=0.0068, rgb=[0.9, 0.4, 0.1]),
    dict(name="bdlo_fast_f355", obj="bdlo", speed="fast", seconds=5, seed=355,
         camera=[1.75, -0.25, 1.05, 0.45, -0.45, 0.2], branch_len=0.21, radius=0.0045, rgb=[0.4, 0.9, 0.3]),
    dict(name="cloth_medium_f356", obj="cloth", speed="medium", seconds=5, seed=356,
         camera=[1.2, 0.3, 1.2, 0.45, -0.45, 0.2], rgb=[0.2, 0.6, 0.9]),
    # generated in session 42 after c6b8147, at camera poses no other row uses, and scored before any change
    dict(name="bdlo_slow_f361", obj="bdlo", speed="slow", seconds=5, seed=361,
         camera=[1.5, -0.7, 1.25, 0.45, -0.45, 0.2], branch_len=0.24, radius=0.0058, rgb=[0.8, 0.2, 0.6]),
    dict(name="rope_medium_f362", obj="rope", speed="medium", seconds=5, seed=362,
         camera=[1.15, 0.15, 1.5, 0.45, -0.45, 0.15], length=0.83, radius=0.0042, rgb=[0.3, 0.3, 0.9]),
    dict(name="cloth_fast_f363", obj="cloth", speed="fast", seconds=5, seed=363,
         camera=[1.6, -0.15, 1.35, 0.45, -0.45, 0.15], rgb=[0.9, 0.8, 0.3]),
    dict(name="bdlo_medium_f364", obj="bdlo", speed="medium", seconds=5, seed=364,
         camera=[1.0, -0.2, 1.3, 0.45, -0.45, 0.15], branch_len=0.2, radius=0.0066, rgb=[0.3, 0.8, 0.8]),
    dict(name="rope_fast_f365", obj="rope", speed="fast", seconds=5, seed=365,
         camera=[1.3, -0.6, 1.0, 0.45, -0.45, 0.2], length=0.96, radius=0.0061, rgb=[0.9, 0.5, 0.5]),
    dict(name="cloth_medium_f366", obj="cloth", speed="medium", seconds=5, seed=366,
         camera=[1.45, 0.05, 1.05, 0.45, -0.45, 0.2], rgb=[0.5, 0.3, 0.8]),
    # generated in session 44, at camera poses no other row uses, and scored before any change
    dict(name="rope_medium_b371", obj="rope", speed="medium", seconds=5, seed=371,
         camera=[1.35, -0.45, 1.45, 0.45, -0.45, 0.2], length=0.91, radius=0.0049, rgb=[0.9, 0.2, 0.3]),
    dict(name="bdlo_fast_b372", obj="bdlo", speed="fast", seconds=5, seed=372,
         camera=[1.05, 0.25, 1.15, 0.45, -0.45, 0.2], branch_len=0.23, radius=0.0061, rgb=[0.2, 0.5, 0.9]),
    dict(name="cloth_fast_b373", obj="cloth", speed="fast", seconds=5, seed=373,
         camera=[1.25, -0.55, 1.3, 0.45, -0.45, 0.15], rgb=[0.3, 0.8, 0.4]),
    dict(name="rope_fast_b374", obj="rope", speed="fast", seconds=5, seed=374,
         camera=[1.65, 0.1, 1.3, 0.45, -0.45, 0.2], length=0.85, radius=0.0064, rgb=[0.6, 0.2, 0.8]),
    dict(name="bdlo_medium_b375", obj="bdlo", speed="medium", seconds=5, seed=375,
         camera=[1.4, -0.85, 1.1, 0.45, -0.45, 0.2], branch_len=0.27, radius=0.0047, rgb=[0.9, 0.6, 0.1]),
    dict(name="cloth_slow_b376", obj="cloth", speed="slow", seconds=5, seed=376,
         camera=[1.0, -0.05, 1.45, 0.45, -0.45, 0.15], rgb=[0.9, 0.3, 0.3]),
    # generated in session 44 after 11eb8de, at camera poses no other row uses, and scored before any change
    dict(name="cloth_medium_b381", obj="cloth", speed="medium", seconds=5, seed=381,
         camera=[1.5, -0.95, 1.25, 0.45, -0.45, 0.2], rgb=[0.95, 0.95, 0.95]),
    dict(name="rope_slow_b382", obj="rope", speed="slow", seconds=5, seed=382,
         camera=[1.2, -0.3, 0.9, 0.45, -0.45, 0.25], length=0.98, radius=0.0058, rgb=[0.1, 0.6, 0.2]),
    dict(name="bdlo_medium_b383", obj="bdlo", speed="medium", seconds=5, seed=383,
         camera=[1.6, 0.0, 1.5, 0.45, -0.45, 0.15], branch_len=0.25, radius=0.0053, rgb=[0.8, 0.1, 0.1]),
    dict(name="cloth_fast_b384", obj="cloth", speed="fast", seconds=5, seed=384,
         camera=[1.1, -0.8, 1.0, 0.45, -0.45, 0.2], rgb=[0.2, 0.3, 0.7]),
    dict(name="rope_medium_b385", obj="rope", speed="medium", seconds=5, seed=385,
         camera=[1.45, -0.15, 1.15, 0.45, -0.45, 0.2], length=0.82, radius=0.0045, rgb=[0.9, 0.8, 0.1]),
    dict(name="bdlo_fast_b388", obj="bdlo", speed="fast", seconds=5, seed=388,
         camera=[1.3, 0.35, 1.35, 0.45, -0.45, 0.15], branch_len=0.22, radius=0.0068, rgb=[0.5, 0.2, 0.9]),
    # generated in session 45, at camera poses no other row uses, and scored before any change
    dict(name="cloth_medium_b391", obj="cloth", speed="medium", seconds=5, seed=391,
         camera=[1.2, -0.65, 1.4, 0.45, -0.45, 0.15], rgb=[0.6, 0.6, 0.2]),
    dict(name="rope_fast_b392", obj="rope", speed="fast", seconds=5, seed=392,
         camera=[1.55, -0.3, 1.05, 0.45, -0.45, 0.2], length=0.88, radius=0.0055, rgb=[0.2, 0.7, 0.7]),
    dict(name="bdlo_slow_b393", obj="bdlo", speed="slow", seconds=5, seed=393,
         camera=[1.15, 0.05, 1.25, 0.45, -0.45, 0.2], branch_len=0.26, radius=0.006, rgb=[0.7, 0.4, 0.2]),
    dict(name="cloth_slow_b394", obj="cloth", speed="slow", seconds=5, seed=394,
         camera=[1.4, -0.25, 1.5, 0.45, -0.45, 0.15], rgb=[0.3, 0.6, 0.9]),
    dict(name="rope_medium_b395", obj="rope", speed="medium", seconds=5, seed=395,
         camera=[1.05, -0.55, 1.2, 0.45, -0.45, 0.2], length=0.94, radius=0.0068, rgb=[0.95, 0.45, 0.1]),
    dict(name="cloth_fast_b396", obj="cloth", speed="fast", seconds=5, seed=396,
         camera=[1.35, 0.2, 1.2, 0.45, -0.45, 0.2], rgb=[0.8, 0.5, 0.7]),
    # cloths generated in sessions 45 (seeds 397-400) and 46 (401-406), at camera poses no other row uses, and
    # scored before any change; 401 and 403 look past the near arm, which hides the cloth for part of the clip
    dict(name="cloth_fast_c397", obj="cloth", speed="fast", seconds=5, seed=397,
         camera=[1.3, -0.35, 1.2, 0.45, -0.45, 0.2]),
    dict(name="cloth_medium_c398", obj="cloth", speed="medium", seconds=5, seed=398,
         camera=[1.5, -0.6, 1.35, 0.45, -0.45, 0.15]),
    dict(name="cloth_slow_c399", obj="cloth", speed="slow", seconds=5, seed=399,
         camera=[1.1, -0.25, 1.35, 0.45, -0.45, 0.15]),
    dict(name="cloth_fast_c400", obj="cloth", speed="fast", seconds=5, seed=400,
         camera=[1.45, 0.1, 1.45, 0.45, -0.45, 0.15]),
    dict(name="cloth_fast_c401", obj="cloth", speed="fast", seconds=5, seed=401,
         camera=[0.55, -1.45, 1.05, 0.5, -0.45, 0.25]),
    dict(name="cloth_medium_c402", obj="cloth", speed="medium", seconds=5, seed=402,
         camera=[1.45, 0.15, 1.0, 0.5, -0.45, 0.25]),
    dict(name="cloth_fast_c403", obj="cloth", speed="fast", seconds=5, seed=403,
         camera=[1.05, -1.2, 1.45, 0.5, -0.45, 0.2]),
    dict(name="cloth_slow_c404", obj="cloth", speed="slow", seconds=5, seed=404,
         camera=[1.55, -0.7, 0.85, 0.5, -0.45, 0.3]),
    dict(name="cloth_fast_c405", obj="cloth", speed="fast", seconds=5, seed=405,
         camera=[0.95, -0.35, 1.65, 0.5, -0.45, 0.2]),
    dict(name="cloth_medium_c406", obj="cloth", speed="medium", seconds=5, seed=406,
         camera=[1.25, -1.05, 0.95, 0.5, -0.45, 0.25]),
    dict(name="cloth_fast_c407", obj="cloth", speed="fast", seconds=5, seed=407,
         camera=[0.2, -1.3, 1.3, 0.5, -0.4, 0.25], rgb=[0.2, 0.6, 0.9]),
    dict(name="cloth_medium_c408", obj="cloth", speed="medium", seconds=5, seed=408,
         camera=[1.3, -0.9, 1.55, 0.5, -0.45, 0.25], rgb=[0.9, 0.5, 0.2]),
    # generated in session 49, at camera poses no other row uses, and scored before any change (seeds 412, 417
    # and 419 put a waypoint out of the right arm's reach)
    dict(name="rope_medium_d411", obj="rope", speed="medium", seconds=5, seed=411,
         camera=[1.6, -0.85, 1.1, 0.45, -0.45, 0.2], length=0.87, radius=0.0052, rgb=[0.9, 0.3, 0.5]),
    dict(name="bdlo_fast_d418", obj="bdlo", speed="fast", seconds=5, seed=418,
         camera=[1.0, -0.1, 1.5, 0.45, -0.45, 0.15], branch_len=0.27, radius=0.0057, rgb=[0.2, 0.5, 0.9]),
    dict(name="cloth_fast_d413", obj="cloth", speed="fast", seconds=5, seed=413,
         camera=[1.7, -0.4, 1.25, 0.45, -0.45, 0.2], rgb=[0.3, 0.7, 0.3]),
    dict(name="rope_slow_d414", obj="rope", speed="slow", seconds=5, seed=414,
         camera=[1.25, 0.3, 1.05, 0.45, -0.45, 0.2], length=0.93, radius=0.0047, rgb=[0.95, 0.85, 0.2]),
    dict(name="bdlo_medium_d415", obj="bdlo", speed="medium", seconds=5, seed=415,
         camera=[1.15, -0.95, 1.35, 0.45, -0.45, 0.2], branch_len=0.24, radius=0.0064, rgb=[0.6, 0.3, 0.8]),
    dict(name="cloth_medium_d416", obj="cloth", speed="medium", seconds=5, seed=416,
         camera=[1.4, -0.05, 1.6, 0.45, -0.45, 0.15], rgb=[0.9, 0.9, 0.9]),
    dict(name="rope_medium_g421", obj="rope", speed="medium", seconds=5, seed=421,
         camera=[1.55, 0.2, 1.55, 0.45, -0.45, 0.15], length=0.87, radius=0.0052, rgb=[0.9, 0.3, 0.2]),
    dict(name="bdlo_medium_g422", obj="bdlo", speed="medium", seconds=5, seed=422,
         camera=[1.5, -0.2, 1.7, 0.45, -0.45, 0.15], branch_len=0.28, radius=0.0061, rgb=[0.2, 0.7, 0.8]),
    dict(name="cloth_medium_g423", obj="cloth", speed="medium", seconds=5, seed=423,
         camera=[1.65, -0.7, 1.6, 0.45, -0.45, 0.15], rgb=[0.8, 0.6, 0.2]),
    dict(name="cloth_fast_g424", obj="cloth", speed="fast", seconds=5, seed=424,
         camera=[1.2, 0.35, 1.7, 0.45, -0.45, 0.15], rgb=[0.3, 0.4, 0.9]),
    dict(name="rope_fast_g425", obj="rope", speed="fast", seconds=5, seed=425,
         camera=[1.75, -0.35, 1.4, 0.45, -0.45, 0.15], length=0.95, radius=0.0044, rgb=[0.3, 0.8, 0.3]),
    dict(name="cloth_slow_g426", obj="cloth", speed="slow", seconds=5, seed=426,
         camera=[1.3, -1.1, 1.65, 0.45, -0.45, 0.15], rgb=[0.9, 0.4, 0.6]),
    dict(name="rope_slow_g431", obj="rope", speed="slow", seconds=5, seed=431,
         camera=[1.7, -0.9, 1.5, 0.45, -0.45, 0.15], length=1.0, radius=0.004, rgb=[0.95, 0.6, 0.1]),
    dict(name="rope_medium_g433", obj="rope", speed="medium", seconds=5, seed=433,
         camera=[0.9, -0.5, 2.0, 0.45, -0.45, 0.15], length=0.82, radius=0.0068, rgb=[0.2, 0.3, 0.9]),
    dict(name="bdlo_slow_g434", obj="bdlo", speed="slow", seconds=5, seed=434,
         camera=[1.8, -0.15, 1.35, 0.45, -0.45, 0.15], branch_len=0.3, radius=0.0055, rgb=[0.9, 0.9, 0.3]),
]
SETS = {"dev": DEV, "variants": VARIANTS, "all": DEV + VARIANTS}
CATEGORY = {"rope": "dlo", "bdlo": "bdlo", "cloth": "cloth"}
# Issue 10's targets per object: (scorer key, column, at most (True) or at least (False), limit); a rope's or
# branch's coverage limit is its radius + 3 mm (None here, from gt.npz).
_LINE = [("nan_frame_fraction", "missing", True, 0.0), ("gt_object_rmse_mm", "object", True, 2.0),
         ("anchor_err_mm", "anchors", True, 8.0), ("coverage_mm", "coverage", True, None),
         ("Abs_mm", "Abs", True, 3.0), ("E<5_pct", "E<5", False, 90.0), ("CD_mm", "CD", True, 5.0),
         ("F<10_pct", "F<10", False, 95.0)]
TARGETS: dict[str, list[tuple[str, str, bool, float | None]]] = {
    "rope": _LINE, "bdlo": _LINE,
    "cloth": [("nan_frame_fraction", "missing", True, 0.0), ("gt_object_rmse_mm", "object", True, 3.0),
              ("anchor_err_mm", "anchors", True, 12.0), ("coverage_mm", "coverage", True, 6.0),
              ("Abs_mm", "Abs", True, 3.0), ("E<5_pct", "E<5", False, 85.0), ("CD_mm", "CD", True, 5.0),
              ("F<10_pct", "F<10", False, 95.0)],
}
COLUMNS = [  # (header, scorer key or None, scale, format)
    ("missing %", "nan_frame_fraction", 100.0, "{:.0f}"),
    ("object mm", "gt_object_rmse_mm", 1.0, "{:.2f}"),
    ("anchors mm", "anchor_err_mm", 1.0, "{:.1f}"),
    ("coverage mm", "coverage_mm", 1.0, "{:.1f}"),
    ("Abs mm", "Abs_mm", 1.0, "{:.2f}"),
    ("E<5 %", "E<5_pct", 1.0, "{:.1f}"),
    ("CD mm", "CD_mm", 1.0, "{:.2f}"),
    ("F<10 %", "F<10_pct", 1.0, "{:.1f}"),
    ("ms/frame", "tracked_ms_per_frame_median", 1.0, "{:.1f}"),
    ("fill ms/frame", "fill_ms_per_frame_median", 1.0, "{:.1f}"),
    ("wall ms/frame", "wall_ms_per_frame", 1.0, "{:.0f}"),
    ("cpu ms/frame", "cpu_ms_per_frame", 1.0, "{:.0f}"),
]
TRUTH_COLUMNS = [  # --truth: the ground truth scored as a tracker's output (``truth_keypoints``)
    ("truth CD mm", "truth_CD_mm", 1.0, "{:.2f}"),
    ("truth F<10 %", "truth_F<10_pct", 1.0, "{:.1f}"),
]


def find_testbed(arg: str | None) -> Path | None:
    """The test bed folder: ``--testbed`` or ``../shared/testbed`` beside the repository; None when absent."""
    d = Path(arg) if arg else REPO.parent / "shared" / "testbed"
    if not arg and not d.is_dir():
        d = REPO.parent.parent / "shared" / "testbed"  # a git worktree one level deeper than the clone
    return d if (d / "make_sequence.py").is_file() and (d / "score.py").is_file() else None


def find_python(arg: str | None, cache: Path, testbed: Path) -> Path:
    """The test bed's interpreter; creates ``<cache>/venv`` from its requirements when none is found."""
    for cand in (arg, os.environ.get("TESTBED_PYTHON")):
        if cand:
            if not Path(cand).is_file():
                sys.exit(f"error: test bed python {cand} does not exist")
            return Path(cand)
    for venv in (cache / "venv", REPO.parent / "tbvenv", REPO / ".tbvenv"):
        if (venv / "bin" / "python").is_file():
            return venv / "bin" / "python"
    venv = cache / "venv"
    print(f"creating the test bed's virtualenv {venv} (pip install -r {testbed / 'requirements.txt'})",
          file=sys.stderr)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "-r", str(testbed / "requirements.txt")], check=True)
    return venv / "bin" / "python"


def generated(seq: Path) -> bool:
    """Whether a sequence folder is complete (the generator writes meta.json last)."""
    return (seq / "meta.json").is_file() and (seq / "rgbd.npz").is_file() and (seq / "gt.npz").is_file()


def generate(py: Path, testbed: Path, jobs: list[dict[str, Any]], out: Path) -> dict[str, str]:
    """Generate the sequences of ``jobs`` not yet in ``out``, one ``make_sequence.py --jobs`` call each (a
    job the generator rejects, e.g. a waypoint out of reach, does not stop the others); name -> error."""
    todo = [j for j in jobs if not generated(out / j["name"])]
    errors: dict[str, str] = {}
    out.mkdir(parents=True, exist_ok=True)
    for k, job in enumerate(todo):
        print(f"generating {job['name']} ({k + 1}/{len(todo)}, ~1-4 min) in {out}", file=sys.stderr, flush=True)
        spec = out / f"{job['name']}.job.json"
        spec.write_text(json.dumps([job], indent=1))
        r = subprocess.run([str(py), str(testbed / "make_sequence.py"), "--jobs", str(spec), "--out", str(out)],
                           capture_output=True, text=True)
        if r.returncode != 0 or not generated(out / job["name"]):
            errors[job["name"]] = "generation failed: " + ((r.stderr.strip().splitlines() or ["?"])[-1])
    return errors


def _children_cpu_s() -> float:
    """User + system CPU time of the finished child processes so far, s."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def track(seq: Path, job: dict[str, Any], out: Path, cores: int | None = None,
          config: Path | None = None) -> dict[str, Any]:
    """Run ``trackdeform track`` on one sequence (on ``cores`` cores of ours, or all; tracking parameters from
    ``config``, or the default); its metrics plus the command's wall and CPU time per frame."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(":")}
    cmd = [sys.executable, "-m", "orchestrator.cli", "track", str(seq), "--out", str(out),
           "--category", CATEGORY[job["obj"]], "--json"] + (["--config", str(config)] if config else [])
    mask = sorted(os.sched_getaffinity(0))[:cores] if cores else None

    def pin() -> None:  # in the child, before it runs the command
        if mask:
            os.sched_setaffinity(0, mask)

    cpu0, t0 = _children_cpu_s(), time.monotonic()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=REPO,
                       preexec_fn=pin if mask else None)
    wall, cpu = time.monotonic() - t0, _children_cpu_s() - cpu0
    if r.returncode != 0:
        return {"error": (r.stderr.strip().splitlines() or ["track failed"])[-1].removeprefix("error: ")}
    m = json.loads(r.stdout.strip().splitlines()[-1])
    frames = max(1, int(m.get("frames", 1)))
    m["wall_ms_per_frame"] = 1e3 * wall / frames
    m["cpu_ms_per_frame"] = 1e3 * cpu / frames
    return m


def score(py: Path, testbed: Path, pred: Path, seq: Path) -> dict[str, Any]:
    """The test bed scorer's JSON for one prediction."""
    r = subprocess.run([str(py), str(testbed / "score.py"), str(pred), str(seq), "--json"], capture_output=True,
                       text=True)
    if not r.stdout.strip():
        return {"error": (r.stderr.strip().splitlines() or ["score failed"])[-1]}
    return json.loads(r.stdout.strip().splitlines()[-1])


def slug(variant: str) -> str:
    """A variant's name as a file or folder name ("w/o anchors" -> "wo_anchors")."""
    return variant.replace("/", "").replace(" ", "_")


def ablation_configs(folder: Path) -> dict[str, Path | None]:
    """Variant name -> config file with that ablation switch off (None: the default config, the full method)."""
    import yaml

    if sys.path[0] != str(REPO):  # the project before this folder (benchmarks/tracking.py is not the package)
        sys.path.insert(0, str(REPO))
    from orchestrator.cli_eval import ABLATIONS

    folder.mkdir(parents=True, exist_ok=True)
    base = yaml.safe_load((REPO / "configs" / "mock.yaml").read_text())
    out: dict[str, Path | None] = {}
    for name, off in ABLATIONS.items():
        if not off:
            out[name] = None
            continue
        data = json.loads(json.dumps(base))
        data.setdefault("tracking", {}).update(off)
        path = folder / f"{slug(name)}.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        out[name] = path
    return out


def means(rows: list[tuple[str, dict[str, Any]]], variants: list[str]) -> list[tuple[str, dict[str, Any]]]:
    """One row per variant: the mean of every column over the sequences it scored (rows named 'seq · variant')."""
    out = []
    for v in variants:
        got = [r for n, r in rows if n.endswith(f" · {v}") and "error" not in r]
        if not got:
            continue
        avg = {}
        for _, key, _, _ in COLUMNS:
            vals = [float(r[key]) for r in got if r.get(key) is not None]
            avg[key] = sum(vals) / len(vals) if vals else None
        out.append((f"mean of {len(got)} · {v}", avg))
    return out


def truth_keypoints(gt: Path, like: Path | None = None) -> dict[str, np.ndarray]:
    """The test bed's ground truth as a tracker's output (``3d_keypoints.npz``'s arrays: full (T, N, 3) mm camera
    frame, edge_connection (E, 2), reference_lengths (E,) mm): a cloth's true mid-surface at an n x n grid of its
    samples, a rope's or branch's true centreline moved its radius towards the camera (the visible ridge, where
    keypoints on the cloud lie) at the arc spacing of the tracker's output ``like`` (its median reference length;
    n its grid's side; without one 6 x 6 and 45 mm). Scored, it shows what exact keypoints get: the CD / F<10
    targets count keypoints out of sight (a cloth's far side seen edge-on, a rope above the image), so some
    sequences miss them even so."""
    g = np.load(gt)
    ref = None
    if like is not None and like.is_file():
        with np.load(like) as p:
            ref = np.asarray(p["reference_lengths"], np.float64) / 1000.0
            n_pred = int(np.asarray(p["full"]).shape[1])
    if str(g["object_type"]) == "cloth":
        surf = np.asarray(g["surface"], np.float64)  # (T, R, C, 3) m
        n = int(round(np.sqrt(n_pred))) if ref is not None else 6
        rows = np.round(np.linspace(0, surf.shape[1] - 1, n)).astype(int)
        cols = np.round(np.linspace(0, surf.shape[2] - 1, n)).astype(int)
        full = surf[:, rows][:, :, cols].reshape(len(surf), n * n, 3)
        edges = grid_topology(n, n, 0.0, 0.0)[0]
    else:
        c = np.asarray(g["centerline"], np.float64)  # (T, M, 3) m
        c = c - float(g["radius_m"]) * c / np.linalg.norm(c, axis=2, keepdims=True)  # the ridge seen from the camera
        bid = np.asarray(g["branch_id"]) if "branch_id" in g else np.zeros(c.shape[1], int)
        step = float(np.median(ref)) if ref is not None and len(ref) else 0.045
        parts, pairs, start = [], [], 0
        for b in np.unique(bid):
            k = np.flatnonzero(bid == b)
            arc = polyline_arc(c[0, k])
            m = max(2, int(round(arc[-1] / step)) + 1)
            at = np.interp(np.linspace(0.0, arc[-1], m), arc, np.arange(len(k)))  # fractional samples, by arc
            i0 = np.minimum(at.astype(int), len(k) - 2)
            w = (at - i0)[None, :, None]
            parts.append((1.0 - w) * c[:, k[i0]] + w * c[:, k[i0 + 1]])
            pairs += [(start + i, start + i + 1) for i in range(m - 1)]
            start += m
        full = np.concatenate(parts, axis=1)
        edges = np.array(pairs, np.int64)
    rest = np.linalg.norm(full[0, edges[:, 0]] - full[0, edges[:, 1]], axis=1)
    return {"full": 1000.0 * full, "edge_connection": edges, "reference_lengths": 1000.0 * rest}


def missed(obj: str, r: dict[str, Any], radius_mm: float | None) -> list[str]:
    """The targets (issue 10) a scored row r misses, as "column value (limit)"; obj is rope, bdlo or cloth, radius_mm
    the rope's (for its coverage limit). A missed CD or F<10 that the ground truth misses too (``--truth``) is
    marked "(truth too)"."""
    out = []
    for key, name, at_most, limit in TARGETS[obj]:
        if limit is None:
            if radius_mm is None:
                continue
            limit = radius_mm + 3.0
        v = r.get(key)
        if v is None:
            continue
        v = 100.0 * float(v) if key == "nan_frame_fraction" else float(v)
        if (v > limit) if at_most else (v < limit):
            t = r.get("truth_" + key)
            truth = t is not None and ((float(t) > limit) if at_most else (float(t) < limit))
            out.append(f"{name} {v:.2f} ({'<=' if at_most else '>='} {limit:g})" + (" (truth too)" if truth else ""))
    return out


def miss_lines(jobs: list[dict[str, Any]], rows: dict[str, dict[str, Any]], seqs: Path) -> list[str]:
    """One line per job whose row misses a target (``missed``; a rope's coverage limit from its ``gt.npz`` in
    ``seqs``); a row without figures (never initialised, generation failed) misses every target and says why."""
    out = []
    for j in jobs:
        r = rows.get(j["name"], {})
        if "error" in r or not r:
            out.append(f"  {j['name']}: {r.get('error') or 'no result'}")
            continue
        gt = seqs / j["name"] / "gt.npz"
        radius = None
        if j["obj"] != "cloth" and gt.is_file():
            with np.load(gt) as g:
                radius = 1000.0 * float(g["radius_m"])
        m = missed(j["obj"], r, radius)
        if m:
            out.append(f"  {j['name']}: " + ", ".join(m))
    return out


def table(rows: list[tuple[str, dict[str, Any]]], truth: bool = False) -> str:
    """Markdown table of the scored sequences (with truth: the ground truth's own CD and F<10 too)."""
    columns = COLUMNS + TRUTH_COLUMNS if truth else COLUMNS
    head = "| sequence | " + " | ".join(c[0] for c in columns) + " |"
    lines = [head, "|" + "---|" * (len(columns) + 1)]
    for name, r in rows:
        if "error" in r:
            lines.append(f"| {name} | error: {r['error']} |")
            continue
        cells = []
        for _, key, scale, fmt in columns:
            v = r.get(key)
            cells.append("n/a" if v is None else fmt.format(scale * float(v)))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Generate (cached), track and score the chosen test-bed sequences; print the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", default=str(REPO / "runs" / "testbed"), help="sequences, venv and outputs go here")
    ap.add_argument("--testbed", help="the test bed folder (default ../shared/testbed beside the repository)")
    ap.add_argument("--testbed-python", help="the test bed's python (default: a venv found or created)")
    ap.add_argument("--set", choices=sorted(SETS), default="all", help="development set, variants or both")
    ap.add_argument("--only", action="append", help="only these sequences (comma-separated names, repeatable)")
    ap.add_argument("--list", action="store_true", help="list the sequences and exit")
    ap.add_argument("--json", action="store_true", help="also print every row's figures as one JSON line")
    ap.add_argument("--cores", type=int, help="run each track command on this many of our cores (default: all)")
    ap.add_argument("--truth", action="store_true",
                    help="also score the ground truth as a tracker's output (truth CD, truth F<10 columns)")
    ap.add_argument("--ablations", action="store_true",
                    help="track each sequence once per Table II variant (full, w/o anchors / edge / cloud projection)")
    a = ap.parse_args(argv)
    jobs = SETS[a.set] if not a.only else SETS["all"]
    if a.only:
        names = {n for o in a.only for n in o.split(",") if n}
        unknown = names - {j["name"] for j in jobs}
        if unknown:
            print(f"error: unknown sequence(s) {', '.join(sorted(unknown))}; --list shows them", file=sys.stderr)
            return 2
        jobs = [j for j in jobs if j["name"] in names]
    if a.list:
        for j in jobs:
            print(json.dumps(j))
        return 0
    testbed = find_testbed(a.testbed)
    if testbed is None:
        where = a.testbed or (REPO.parent / "shared" / "testbed")
        print(f"skipped: no test bed at {where} (make_sequence.py and score.py); pass --testbed DIR")
        return 0
    cache = Path(a.cache).resolve()
    cache.mkdir(parents=True, exist_ok=True)
    py = find_python(a.testbed_python, cache, testbed)
    seqs = cache / "sequences"
    failed = generate(py, testbed, jobs, seqs)
    variants = ablation_configs(cache / "ablations") if a.ablations else {"": None}
    rows: list[tuple[str, dict[str, Any]]] = []
    for j in jobs:
        name = j["name"]
        for variant, config in variants.items():
            label = f"{name} · {variant}" if variant else name
            if name in failed:
                rows.append((label, {"error": failed[name]}))
                continue
            out = cache / "tracks" / slug(variant) / name
            print(f"tracking {label} ...", file=sys.stderr, flush=True)
            m = track(seqs / name, j, out, a.cores, config)
            r = m if "error" in m else {**score(py, testbed, out / "3d_keypoints.npz", seqs / name), **m}
            if a.truth and not variant:
                truth = out / "truth_keypoints.npz"
                np.savez(truth, **truth_keypoints(seqs / name / "gt.npz", out / "3d_keypoints.npz"))
                t = score(py, testbed, truth, seqs / name)
                r = {**r, "truth_CD_mm": t.get("CD_mm"), "truth_F<10_pct": t.get("F<10_pct")}
            rows.append((label, r))
    if a.ablations:
        rows += means(rows, list(variants))
    print(table(rows, truth=a.truth))
    if not a.ablations:  # an ablation run's rows are per variant
        misses = miss_lines(jobs, dict(rows), seqs)
        print(f"\nrows missing a target (issue 10): {len(misses)} of {len(jobs)}" + (":" if misses else ""))
        print("\n".join(misses))
    if a.json:
        keys = ("error", *(c[1] for c in (COLUMNS + TRUTH_COLUMNS if a.truth else COLUMNS)))
        print(json.dumps({n: {k: r.get(k) for k in keys} for n, r in rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
