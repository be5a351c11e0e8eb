"""The folder layout of the paper's published code (``rgbd.npz``, per-arm pose files, calibration) and its
reference output ``3d_keypoints.npz``.

Millimetres appear only in these files, as the paper's code expects them; what is read is converted to SI.
"""

from __future__ import annotations

import itertools
import math
import struct
import zipfile
import zlib
from collections.abc import Collection, Iterable, Iterator
from pathlib import Path
from typing import IO, Any, Literal, NamedTuple

import numpy as np

from tdcommon.transforms import invert_transform, matrix_to_pose7, pose7_to_matrix
from tdcommon.types import CameraIntrinsics, RGBDFrame
from tdrecord.codecs import INFLATE
from tdrecord.sequence import (
    DEPTH_SCALE_MM,
    DatasetError,
    DepthImage,
    FrameSource,
    Sequence,
    check_rigid,
    read_ahead,
)

RGBD_FILE = "rgbd.npz"
POSE_FILES = {"left": "left_arm_poses.npz", "right": "right_arm_poses.npz"}
CALIBRATION_FILE = "calibration/transform_ee_cam_world.npz"
JOINT_FILE = "joint_states.npz"
REFERENCE_FILE = "3d_keypoints.npz"


class ReferenceKeypoints(NamedTuple):
    """Keypoints (T, N, 3) m, edges (E, 2) int64 and rest lengths (E,) m, as read from ``3d_keypoints.npz``."""

    keypoints: np.ndarray
    edges: np.ndarray
    rest_lengths: np.ndarray


def _read_npy_header(fp: IO[bytes], where: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fp)
        if version == (1, 0):
            return fmt.read_array_header_1_0(fp)
        return fmt.read_array_header_2_0(fp)
    except ValueError as e:
        raise DatasetError(f"{where}: not a .npy array ({e})") from e


class _Member:
    """A stored or deflated zip member read as a stream, inflated with ISA-L (``tdrecord.codecs.INFLATE``: ~2.5x
    zlib's speed on a test-bed depth array, the same bytes), one block in memory at a time; ``read()`` to its end
    compares the member's CRC-32 and raises ``zipfile.BadZipFile`` on a mismatch, ``zlib.error`` on data that does
    not inflate and ``EOFError`` on a file cut short, as ``zipfile``'s own stream does."""

    _BLOCK = 1 << 22

    def __init__(self, path: Path, info: zipfile.ZipInfo) -> None:
        self._info = info
        self._f = open(path, "rb")  # noqa: SIM115 - closed by close() / the context manager
        self._f.seek(info.header_offset)
        head = self._f.read(30)
        if len(head) != 30 or head[:4] != b"PK\x03\x04":
            self._f.close()
            raise zipfile.BadZipFile(f"bad local file header for {info.filename!r}")
        name_len, extra_len = struct.unpack("<HH", head[26:30])
        self._f.seek(info.header_offset + 30 + name_len + extra_len)
        self._left = info.compress_size
        self._inflate = INFLATE.decompressobj(-15) if info.compress_type == zipfile.ZIP_DEFLATED else None
        self._crc = 0
        self._chunk, self._pos = b"", 0
        self._done = False

    def _more(self) -> bool:
        """Inflate the next block (at most ``_BLOCK`` bytes out: a colour array inflates 12x, and bounded blocks
        stay in the cache, twice as fast); False at the member's end (its CRC checked there). Once the input is
        all read, the inflater is given nothing until its stream ends: it may still hold output (ISA-L does)."""
        if self._done:
            return False
        inflate = self._inflate
        if inflate is not None and inflate.unconsumed_tail:
            raw = inflate.unconsumed_tail
        else:
            raw = self._f.read(min(self._BLOCK, self._left)) if self._left > 0 else b""
            if self._left > 0 and not raw:
                raise EOFError(f"{self._info.filename!r} ends {self._left} bytes early")
            self._left -= len(raw)
        try:
            out = raw if inflate is None else inflate.decompress(raw, self._BLOCK)
        except INFLATE.error as e:
            raise zlib.error(str(e)) from None
        end = self._left == 0 if inflate is None else inflate.eof
        if not end and not raw and not out:
            raise EOFError(f"{self._info.filename!r}: its compressed data ends before the end-of-stream marker")
        self._crc = INFLATE.crc32(out, self._crc)
        self._chunk, self._pos = out, 0
        if end:
            self._done = True
            if self._crc != self._info.CRC:
                raise zipfile.BadZipFile(f"Bad CRC-32 for file {self._info.filename!r}")
        return True

    def drain(self) -> None:
        """Inflate to the member's end without keeping what it inflates (a CRC check)."""
        while self._more():
            pass

    def read(self, n: int = -1) -> bytes:
        """Up to n bytes (all that is left when n < 0); fewer only at the member's end."""
        parts = []
        need = n if n >= 0 else math.inf
        while need > 0:
            if self._pos == len(self._chunk) and not self._more():
                break
            take = self._chunk[self._pos : self._pos + need] if need < math.inf else self._chunk[self._pos :]
            self._pos += len(take)
            need -= len(take)
            parts.append(take)
        return parts[0] if len(parts) == 1 else b"".join(parts)

    def close(self) -> None:
        """Close the file."""
        self._f.close()

    def __enter__(self) -> _Member:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open_member(zf: zipfile.ZipFile, path: Path, name: str) -> IO[bytes] | _Member:
    """Member ``name`` of the open archive zf (of file path) as a stream: ``_Member`` when stored or deflated and
    not encrypted, else zipfile's own."""
    info = zf.getinfo(name)
    if info.compress_type in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED) and not info.flag_bits & 0x1:
        return _Member(path, info)
    return zf.open(info)


def verify_npz(path: Path, skip: Collection[str] = (), structure_only: bool = False) -> None:
    """Check an .npz before use: a zip archive whose every member (but those named in ``skip``, e.g.
    ``"depth.npy"``) passes its CRC check; ``structure_only``: only that it opens as a zip (its central
    directory, at the file's end, is intact: catches truncation without decompressing anything).

    Raises DatasetError naming the file (and the first bad member); the full check decompresses every member
    checked once, one block in memory at a time.
    """
    try:
        with zipfile.ZipFile(path) as zf:
            if structure_only:
                return
            for info in zf.infolist():
                if info.filename in skip:
                    continue
                try:
                    with _open_member(zf, path, info.filename) as fp:
                        if isinstance(fp, _Member):
                            fp.drain()
                        else:
                            while fp.read(1 << 22):
                                pass
                except (zipfile.BadZipFile, zlib.error) as e:
                    raise DatasetError(f"{path}: corrupt .npz: member {info.filename!r} fails its CRC check "
                                       f"({type(e).__name__}: {e})") from None
    except zipfile.BadZipFile as e:
        raise DatasetError(f"{path}: not a valid .npz (zip) file ({e})") from None
    except (OSError, EOFError, zlib.error) as e:
        raise DatasetError(f"{path}: corrupt .npz ({type(e).__name__}: {e})") from None


def paper_layout_files(folder: Path) -> list[Path]:
    """The .npz files of a paper-layout folder that exist (rgbd, poses, calibration, joint states)."""
    names = [RGBD_FILE, *POSE_FILES.values(), CALIBRATION_FILE, JOINT_FILE]
    return [folder / n for n in names if (folder / n).is_file()]


def npz_member_header(path: Path, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of array ``key`` in an .npz, read from its header only."""
    with zipfile.ZipFile(path) as zf:
        names = [n.removesuffix(".npy") for n in zf.namelist()]
        if key not in names:
            raise DatasetError(f"{path}: no array '{key}' (has: {sorted(names)})")
        with zf.open(f"{key}.npy") as fp:
            shape, _, dtype = _read_npy_header(fp, f"{path}:{key}")
    return shape, dtype


def _iter_npz_rows(path: Path, key: str, start: int = 0) -> Iterator[np.ndarray]:
    """The rows ``arr[start], arr[start + 1], ...`` of array ``key`` in an .npz, streamed (one row in memory).

    A stream read to its end has checked the member's CRC: a mismatch, or deflate data that does not decode,
    raises DatasetError naming the file and member.
    """
    try:
        with zipfile.ZipFile(path) as zf, _open_member(zf, path, f"{key}.npy") as fp:
            shape, fortran, dtype = _read_npy_header(fp, f"{path}:{key}")
            if fortran:  # rare: no row streaming possible
                with np.load(path) as z:
                    arr = z[key]
                yield from (np.array(r) for r in arr[start:])
                return
            n = math.prod(shape[1:]) * dtype.itemsize
            for i in range(shape[0]):
                buf = fp.read(n)
                if len(buf) != n:
                    raise DatasetError(f"{path}: array '{key}' is truncated at row {i} of {shape[0]}")
                if i >= start:
                    yield np.frombuffer(buf, dtype=dtype).reshape(shape[1:])
            fp.read()  # to the member's end, where zipfile compares its CRC
    except zipfile.BadZipFile as e:
        raise DatasetError(f"{path}: corrupt .npz: member '{key}.npy' ({e})") from None
    except zlib.error as e:
        raise DatasetError(f"{path}: corrupt .npz: member '{key}.npy' does not decompress ({e})") from None


def _require_file(folder: Path, name: str) -> Path:
    p = folder / name
    if not p.is_file():
        raise FileNotFoundError(f"{p}: missing (the paper's layout needs {name} in {folder})")
    return p


def _read_npz_array(path: Path, key: str, shape: tuple[int | None, ...]) -> np.ndarray:
    with np.load(path) as z:
        if key not in z.files:
            raise DatasetError(f"{path}: no array '{key}' (has: {sorted(z.files)})")
        a = np.asarray(z[key])
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join("T" if s is None else str(s) for s in shape) + ")"
        raise DatasetError(f"{path}: array '{key}' has shape {a.shape}, expected {want}")
    return a


def _read_pose_file(path: Path) -> np.ndarray:
    """(T, 7) [x, y, z, qw, qx, qy, qz] from ``arr_0 ... arr_{T-1}``."""
    with np.load(path) as z:
        files = set(z.files)
        n = len(files)
        missing = [f"arr_{i}" for i in range(n) if f"arr_{i}" not in files]
        if missing:
            extra = sorted(files - {f"arr_{i}" for i in range(n)})
            raise DatasetError(
                f"{path}: expected arrays arr_0 ... arr_{n - 1}; missing {missing[0]} (unexpected: {extra})"
            )
        rows = [np.asarray(z[f"arr_{i}"], dtype=np.float64) for i in range(n)]
    bad = next((i for i, r in enumerate(rows) if r.shape != (7,)), None)
    if bad is not None:
        raise DatasetError(f"{path}: arr_{bad} has shape {rows[bad].shape}, expected (7,) [x, y, z, qw, qx, qy, qz]")
    return np.stack(rows) if rows else np.zeros((0, 7))


def paper_calibration(folder: Path, world: str) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(K, T_world_cam, T_world_base) from ``calibration/transform_ee_cam_world.npz``."""
    cal = _require_file(folder, CALIBRATION_FILE)
    K = _read_npz_array(cal, "K", (3, 3)).astype(np.float64)
    T_cam_base = {a: check_rigid(_read_npz_array(cal, f"T_{a}_base2cam", (4, 4)), f"{cal}: T_{a}_base2cam")
                  for a in ("left", "right")}
    if world == "camera":
        T_world_cam = np.eye(4)
    elif world in T_cam_base:
        T_world_cam = invert_transform(T_cam_base[world])
    else:
        raise ValueError(f"world must be 'left', 'right' or 'camera', not {world!r}")
    return K, T_world_cam, {a: T_world_cam @ T for a, T in T_cam_base.items()}


def read_paper_layout(
    folder: str | Path,
    *,
    world: Literal["left", "right", "camera"] = "left",
    fps: float = 30.0,
    align: Literal["strict", "end"] = "strict",
) -> Sequence:
    """A folder in the layout of the paper's published code as a Sequence (frames streamed lazily).

    Files: ``rgbd.npz`` (``color`` (T, H, W, 3) uint8 BGR, ``depth`` (T, H, W) uint16 mm);
    ``left_arm_poses.npz`` / ``right_arm_poses.npz`` (``arr_0 ... arr_{T-1}``: [x, y, z, qw, qx, qy, qz],
    m, TCP in that robot's base frame); ``calibration/transform_ee_cam_world.npz`` (``T_left_base2cam``,
    ``T_right_base2cam`` (4, 4), ``K`` (3, 3)); optional ``joint_states.npz`` (``left``, ``right`` (T, 7) rad).

    Frame convention: the paper's code computes TCP positions in the camera as
    ``(T_left_base2cam @ T_base_tcp)[:3, 3]``, so ``T_<arm>_base2cam`` maps base coordinates to camera
    coordinates (it is the base pose in the camera frame, ``T_cam_base``). The world frame is the left
    robot's base (``world="left"``, default): ``T_world_cam = inv(T_left_base2cam)``,
    ``T_world_base["right"] = inv(T_left_base2cam) @ T_right_base2cam``, and TCP poses are
    ``T_world_base[arm] @ pose``. ``world="right"`` / ``"camera"`` use the right base / camera instead.
    The files carry no stamps: frame k is stamped ``k / fps`` s. Frame counts must agree
    (``align="end"`` keeps the last common frames instead, as the published scripts do).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    rgbd = _require_file(folder, RGBD_FILE)
    cshape, cdtype = npz_member_header(rgbd, "color")
    dshape, ddtype = npz_member_header(rgbd, "depth")
    if len(cshape) != 4 or cshape[3] != 3 or cdtype != np.uint8:
        raise DatasetError(f"{rgbd}: array 'color' is {cdtype} {cshape}, expected uint8 (T, H, W, 3) BGR")
    if len(dshape) != 3 or dshape != cshape[:3] or ddtype.kind != "u" or ddtype.itemsize != 2:
        raise DatasetError(f"{rgbd}: array 'depth' is {ddtype} {dshape}, expected uint16 {cshape[:3]} (mm)")
    T_rgb, H, W = cshape[:3]
    K, T_world_cam, T_world_base = paper_calibration(folder, world)
    poses = {a: _read_pose_file(_require_file(folder, f)) for a, f in POSE_FILES.items()}
    joints: dict[str, np.ndarray] = {}
    if (folder / JOINT_FILE).is_file():
        joints = {a: _read_npz_array(folder / JOINT_FILE, a, (None, 7)).astype(np.float64) for a in ("left", "right")}
    counts = {RGBD_FILE: T_rgb, **{POSE_FILES[a]: len(p) for a, p in poses.items()},
              **{f"{JOINT_FILE}:{a}": len(q) for a, q in joints.items()}}
    T = min(counts.values())
    if align == "strict":
        bad = {k: v for k, v in counts.items() if v != T_rgb}
        if bad:
            name, n = next(iter(bad.items()))
            raise DatasetError(
                f"{folder / name.split(':')[0]}: {n} rows but {RGBD_FILE} has {T_rgb} frames "
                f"(counts: {counts}); pass align='end' to keep the last {T} of each"
            )
    skip = T_rgb - T

    def tail(a: np.ndarray) -> np.ndarray:
        return a[len(a) - T:]

    tcp = {a: T_world_base[a] @ pose7_to_matrix(tail(p)) for a, p in poses.items()}
    intr = CameraIntrinsics.from_K(K, W, H)

    def frames(start: int) -> Iterator[RGBDFrame]:
        rows = zip(_iter_npz_rows(rgbd, "color", skip + start), _iter_npz_rows(rgbd, "depth", skip + start),
                   strict=True)
        for k, (bgr, depth) in enumerate(rows, start=start):
            t = k / fps
            yield RGBDFrame(
                color=np.ascontiguousarray(bgr[..., ::-1]), depth=depth.astype(np.uint16),
                depth_scale=DEPTH_SCALE_MM, intrinsics=intr, device_stamp=t, host_stamp=t, frame_number=k,
            )

    def depth_rows(start: int, colour: bool) -> Iterator[DepthImage]:  # the colour where tracking reads it
        depths = _iter_npz_rows(rgbd, "depth", skip + start)
        colours = _iter_npz_rows(rgbd, "color", skip + start) if colour else itertools.repeat(None)
        for k, (depth, bgr) in enumerate(zip(depths, colours, strict=colour), start=start):
            yield DepthImage(depth=depth.astype(np.uint16, copy=False), depth_scale=DEPTH_SCALE_MM, frame_number=k,
                             color=None if bgr is None else bgr[..., ::-1])  # an RGB view: a few pixels are read

    def depth_frames(start: int, colour: bool = True) -> Iterator[DepthImage]:  # decompressed a few frames ahead
        return read_ahead(lambda: depth_rows(start, colour))

    return Sequence(
        frames=FrameSource(frames, T, depth_frames),
        T_world_cam=T_world_cam,
        K=K,
        width=W,
        height=H,
        q_left=tail(joints["left"]) if joints else None,
        q_right=tail(joints["right"]) if joints else None,
        tcp_left=tcp["left"],
        tcp_right=tcp["right"],
        T_world_base=T_world_base,
        metadata={"layout": "paper", "fps": fps, "world_frame": f"{world} robot base" if world != "camera"
                  else "camera", "frame_counts": counts, "skipped_leading_frames": skip},
        source=folder,
        stamps=np.arange(T) / fps,
        frame_numbers=np.arange(T, dtype=np.int64),
    )


def _npy_header_dict(shape: tuple[int, ...], dtype: np.dtype) -> dict[str, Any]:
    return {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False, "shape": shape}


def write_paper_layout(
    folder: str | Path,
    frames: Iterable[RGBDFrame],
    *,
    T_world_cam: np.ndarray,
    T_world_base: dict[str, np.ndarray],
    tcp_left: np.ndarray,
    tcp_right: np.ndarray,
    q_left: np.ndarray | None = None,
    q_right: np.ndarray | None = None,
    K: np.ndarray | None = None,
    compress: bool = False,
) -> Path:
    """Write ``folder`` in the paper's layout (see :func:`read_paper_layout`); returns the folder.

    frames: re-iterable (a list or a FrameSource; read twice, one frame in memory at a time), RGB colour.
    tcp_left / tcp_right: (T, 4, 4) world frame; T_world_base: {"left", "right"} -> (4, 4); q: (T, 7) rad.
    K defaults to the first frame's intrinsics. Reading it back expresses everything in the left base frame.
    """
    folder = Path(folder)
    try:
        T = len(frames)  # type: ignore[arg-type]
    except TypeError:
        frames = list(frames)
        T = len(frames)
    if T == 0:
        raise ValueError("write_paper_layout: no frames")
    tcp = {"left": np.asarray(tcp_left, dtype=np.float64), "right": np.asarray(tcp_right, dtype=np.float64)}
    for a, arr in tcp.items():
        if arr.shape != (T, 4, 4):
            raise ValueError(f"write_paper_layout: tcp_{a} has shape {arr.shape}, expected ({T}, 4, 4)")
    (folder / CALIBRATION_FILE).parent.mkdir(parents=True, exist_ok=True)
    first = next(iter(frames))
    H, W = first.depth.shape
    K = first.intrinsics.K if K is None else np.asarray(K, dtype=np.float64)
    members = {
        "color": ((T, H, W, 3), np.uint8, lambda f: np.ascontiguousarray(f.color[..., ::-1], dtype=np.uint8)),
        "depth": ((T, H, W), np.dtype("<u2"), RGBDFrame.depth_mm),
    }
    mode = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    tmp = folder / (RGBD_FILE + ".part")
    with zipfile.ZipFile(tmp, "w", compression=mode, allowZip64=True) as zf:
        for key, (shape, dtype, convert) in members.items():
            n = 0
            with zf.open(f"{key}.npy", "w", force_zip64=True) as fp:
                np.lib.format.write_array_header_1_0(fp, _npy_header_dict(shape, dtype))
                for f in frames:
                    if f.depth.shape != (H, W):
                        raise ValueError(f"write_paper_layout: frame {f.frame_number} is {f.depth.shape}, not {(H, W)}")
                    fp.write(np.ascontiguousarray(convert(f), dtype=dtype).tobytes())
                    n += 1
            if n != T:
                raise ValueError(f"write_paper_layout: frames yielded {n} frames, len() said {T}")
    tmp.replace(folder / RGBD_FILE)
    T_cam_world = invert_transform(T_world_cam)
    bases = {a: np.asarray(T_world_base[a], dtype=np.float64) for a in ("left", "right")}
    for a, name in POSE_FILES.items():
        pose = matrix_to_pose7(invert_transform(bases[a]) @ tcp[a])
        np.savez(folder / name, *pose)
    np.savez(folder / CALIBRATION_FILE, K=K, T_left_base2cam=T_cam_world @ bases["left"],
             T_right_base2cam=T_cam_world @ bases["right"])
    if q_left is not None and q_right is not None:
        np.savez(folder / JOINT_FILE, left=np.asarray(q_left, dtype=np.float64),
                 right=np.asarray(q_right, dtype=np.float64))
    return folder


def _reference_path(path: str | Path) -> Path:
    path = Path(path)
    return path / REFERENCE_FILE if path.is_dir() else path


def write_reference_npz(path: str | Path, keypoints: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray) -> Path:
    """Write ``3d_keypoints.npz`` as the paper's code does: ``full`` (T, N, 3) mm, ``edge_connection`` (E, 2),
    ``reference_lengths`` (E,) mm. keypoints: (T, N, 3) m (NaN allowed); rest_lengths: (E,) m.
    A folder ``path`` gets ``3d_keypoints.npz`` inside; returns the file written.
    """
    X = np.asarray(keypoints, dtype=np.float64)
    E = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    d = np.asarray(rest_lengths, dtype=np.float64).reshape(-1)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"write_reference_npz: keypoints have shape {X.shape}, expected (T, N, 3)")
    if len(d) != len(E):
        raise ValueError(f"write_reference_npz: {len(E)} edges but {len(d)} rest lengths")
    if len(E) and (E.min() < 0 or E.max() >= X.shape[1]):
        raise ValueError(f"write_reference_npz: edge index out of range for {X.shape[1]} keypoints")
    out = _reference_path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as f:  # a file object: numpy must not append .npz to the name
        np.savez(f, full=X * 1000.0, edge_connection=E, reference_lengths=d * 1000.0)
    return out


def read_reference_npz(path: str | Path) -> ReferenceKeypoints:
    """Read ``3d_keypoints.npz`` (or a folder holding it) back in metres: (T, N, 3), (E, 2), (E,)."""
    p = _reference_path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: missing")
    with np.load(p) as z:
        missing = [k for k in ("full", "edge_connection", "reference_lengths") if k not in z.files]
        if missing:
            raise DatasetError(f"{p}: no array '{missing[0]}' (has: {sorted(z.files)})")
        X = np.asarray(z["full"], dtype=np.float64)
        E = np.asarray(z["edge_connection"]).astype(np.int64)
        d = np.asarray(z["reference_lengths"], dtype=np.float64).reshape(-1)
    if X.ndim == 2:
        X = X[None]
    if X.ndim != 3 or X.shape[2] != 3:
        raise DatasetError(f"{p}: 'full' has shape {X.shape}, expected (T, N, 3)")
    if E.size == 0:
        E = E.reshape(0, 2)
    if E.ndim != 2 or E.shape[1] != 2 or len(E) != len(d):
        raise DatasetError(
            f"{p}: 'edge_connection' {E.shape} and 'reference_lengths' {d.shape} do not match (E, 2) / (E,)"
        )
    return ReferenceKeypoints(X / 1000.0, E, d / 1000.0)
