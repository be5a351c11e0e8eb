"""Draw tracked keypoints and edges on the colour frames of a paper-layout sequence: one PNG montage.

Usage: .venv/bin/python benchmarks/overlay.py SEQ [--pred SEQ/3d_keypoints.npz] [--frames 0,30,60 | --every 15]
       [--gt] [--cols 4] [--scale 0.5] --out overlay.png

SEQ is a folder in the paper's layout (``rgbd.npz``, ``calibration/transform_ee_cam_world.npz``), e.g. a test-bed
sequence; --pred a ``3d_keypoints.npz`` (``trackdeform track``'s output, mm, world = the left arm's base).
Keypoints are dots (the first keypoint larger), edges lines; a cloth grid's flipped cells (normal against the
grid's mean normal) are filled red. ``--gt`` also draws the test bed's true anchors (``gt.npz``, camera frame) as
white rings: for looking at a bad sequence, never for tracking. A tangled grid or a rope that stops short is
plain in such a picture and hidden in a mean.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from tdrecord.paper import paper_calibration, read_reference_npz  # noqa: E402
from tracking.geometry import project_points  # noqa: E402


def grid_shape(edges: np.ndarray, n: int) -> tuple[int, int] | None:
    """(rows, cols) of a row-major 4-neighbour grid with n nodes and these edges (E, 2), else None."""
    for cols in range(2, n):
        if n % cols == 0:
            rows = n // cols
            if len(edges) == rows * (cols - 1) + cols * (rows - 1) and {tuple(e) for e in edges.tolist()} >= {
                (0, 1), (0, cols)
            }:
                return rows, cols
    return None


def flipped_cells(X: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Cells (rows-1, cols-1) bool whose normal points against the grid's mean normal; X (rows*cols, 3)."""
    G = X.reshape(rows, cols, 3)
    n = np.cross(G[1:, 1:] - G[:-1, :-1], G[:-1, 1:] - G[1:, :-1])
    mean = n.reshape(-1, 3).sum(axis=0)
    return (n @ mean) < 0


def main(argv: list[str] | None = None) -> int:
    """Draw the chosen frames and write the montage."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("seq", type=Path)
    ap.add_argument("--pred", type=Path, default=None, help="3d_keypoints.npz (default SEQ/3d_keypoints.npz)")
    ap.add_argument("--frames", default=None, help="comma-separated frame indices")
    ap.add_argument("--every", type=int, default=15, help="every this many frames when --frames is not given")
    ap.add_argument("--gt", action="store_true", help="also draw the test bed's true anchors (gt.npz)")
    ap.add_argument("--cols", type=int, default=4)
    ap.add_argument("--scale", type=float, default=0.5, help="each frame scaled by this")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    pred = read_reference_npz(a.pred or a.seq / "3d_keypoints.npz")
    K, T_world_cam, _ = paper_calibration(a.seq, "left")
    with np.load(a.seq / "rgbd.npz") as z:
        colour = z["color"]
    T = min(len(colour), len(pred.keypoints))
    frames = [int(f) for f in a.frames.split(",")] if a.frames else list(range(0, T, a.every))
    gt = np.load(a.seq / "gt.npz") if a.gt and (a.seq / "gt.npz").exists() else None
    n = pred.keypoints.shape[1]
    grid = grid_shape(pred.edges, n)
    tiles = []
    for f in frames:
        img = np.ascontiguousarray(colour[f])
        X = pred.keypoints[f]
        uv, _ = project_points(np.nan_to_num(X, nan=0.0), K, T_world_cam)
        uv[~np.isfinite(X).all(axis=1)] = np.nan
        if grid is not None and np.isfinite(X).all():
            rows, cols = grid
            bad = flipped_cells(X, rows, cols)
            G = uv.reshape(rows, cols, 2)
            overlay = img.copy()
            for r, c in zip(*np.nonzero(bad), strict=True):
                quad = np.array([G[r, c], G[r, c + 1], G[r + 1, c + 1], G[r + 1, c]]).round().astype(np.int32)
                cv2.fillPoly(overlay, [quad], (0, 0, 255))
            img = cv2.addWeighted(overlay, 0.5, img, 0.5, 0)
        _draw_edges_and_points(img, uv, pred.edges, (0, 255, 255))
        if gt is not None:
            A = np.asarray(gt["anchors"][f], np.float64).reshape(-1, 3)
            z = A[:, 2:3]
            Kg = np.asarray(gt["K"], np.float64)
            auv = (A @ Kg.T)[:, :2] / z
            for p in auv:
                cv2.circle(img, tuple(np.round(p).astype(int)), 9, (255, 255, 255), 2, cv2.LINE_AA)
        cv2.putText(img, f"frame {f}", (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255), 3, cv2.LINE_AA)
        tiles.append(cv2.resize(img, None, fx=a.scale, fy=a.scale, interpolation=cv2.INTER_AREA))
    h, w = tiles[0].shape[:2]
    cols = min(a.cols, len(tiles))
    rows = -(-len(tiles) // cols)
    sheet = np.zeros((rows * h, cols * w, 3), np.uint8)
    for k, t in enumerate(tiles):
        sheet[(k // cols) * h : (k // cols + 1) * h, (k % cols) * w : (k % cols + 1) * w] = t
    a.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.out), sheet)
    print(f"{a.out}: {len(tiles)} frames of {a.seq.name}" + (f", grid {grid[0]}x{grid[1]}" if grid else ""))
    return 0


def _draw_edges_and_points(img: np.ndarray, uv: np.ndarray, edges: np.ndarray, colour: tuple[int, int, int]) -> None:
    """Edges and keypoints uv (N, 2) px (NaN: not drawn) on img (H, W, 3) BGR, in place; keypoint 0 larger."""
    ok = np.isfinite(uv).all(axis=1)
    for i, j in edges:
        if ok[i] and ok[j]:
            cv2.line(img, tuple(np.round(uv[i]).astype(int)), tuple(np.round(uv[j]).astype(int)), colour, 2,
                     cv2.LINE_AA)
    for k, p in enumerate(uv):
        if ok[k]:
            q = tuple(np.round(p).astype(int))
            cv2.circle(img, q, 7 if k == 0 else 5, (0, 0, 0), -1, cv2.LINE_AA)
            cv2.circle(img, q, 5 if k == 0 else 3, (0, 0, 255) if k == 0 else colour, -1, cv2.LINE_AA)


if __name__ == "__main__":
    sys.exit(main())
