"""Image codecs of episode files, shared by the recorder (encoders) and the episode reader (decoders).

Colour (H, W, 3) uint8 RGB is stored as one of:

- ``h264``: ``foxglove.CompressedVideo`` format ``h264`` through PyAV's libx264: Annex B, one access
  unit per message, no B-frames, no lookahead (``tune=zerolatency``: one packet out per frame in),
  full-range 4:2:0, a keyframe (IDR with SPS/PPS in front) at the first frame of every encoder and
  every ``gop`` frames. A new encoder per episode makes each file decode on its own.
- ``jpeg``: ``foxglove.CompressedImage`` format ``jpeg`` (OpenCV).
- ``raw``: ``foxglove.RawImage`` ``rgb8``.

Depth (H, W) uint16 millimetres (0 = no data) is stored lossless as one of:

- ``png``: ``foxglove.CompressedImage`` format ``png``, 16-bit greyscale, every row with PNG's Sub
  filter and the deflate stream Huffman-coded only by zlib-ng (about 6 ms a 1280×720 frame; LZ77 matching
  finds nothing in depth noise, and OpenCV's PNG writer costs 4x as much for the same size). Any PNG reader
  gives the exact values back.
- ``planes``: ``trackdeform.CompressedDepth`` (the fields of ``foxglove.CompressedImage``, format ``planes``):
  each sample minus its left neighbour (the first column: minus the one above), zigzag-mapped, and the high
  and the low bytes of those residuals zstd-compressed as two planes (:func:`encode_planes`). About 20 %
  smaller than the PNG on stereo depth noise, whose two bytes a sample PNG codes with one Huffman table;
  Foxglove opens the channel but does not draw it as an image.
- ``raw``: ``foxglove.RawImage`` ``16UC1`` (little-endian).

PyAV, zlib and OpenCV release the GIL while they work, so encoders of one frame can run on threads.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Literal

import numpy as np
import zstandard

try:  # zlib-ng: same API and output format as zlib, about twice as fast for the same size (and to inflate)
    from zlib_ng import zlib_ng as ZLIB
except ImportError:  # pragma: no cover - a plain zlib gives the same files, only slower
    ZLIB = zlib  # type: ignore[assignment]
try:  # ISA-L: zlib's streaming API, inflates a test-bed depth array ~1.7x faster than zlib-ng (the same bytes)
    from isal import isal_zlib as INFLATE
except ImportError:  # pragma: no cover - zlib-ng inflates the same streams, only slower
    INFLATE = ZLIB  # type: ignore[assignment]

ColorCodec = Literal["h264", "jpeg", "raw"]
DepthCodec = Literal["png", "planes", "raw"]
H264_PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium")

SCHEMA_VIDEO = "foxglove.CompressedVideo"
SCHEMA_COMPRESSED = "foxglove.CompressedImage"
SCHEMA_RAW = "foxglove.RawImage"
SCHEMA_DEPTH = "trackdeform.CompressedDepth"  # wire-identical to foxglove.CompressedImage; format "planes"

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_FILTER_SUB = 1
_PLANES_MAGIC = b"TDP1"
_PLANES_HEADER = struct.Struct("<4sIII")  # magic, width, height, bytes of the compressed high plane


class CodecError(ValueError):
    """An image that cannot be encoded or decoded as asked; the message says which and why."""


@dataclass(frozen=True)
class EncodedImage:
    """One encoded image: the Foxglove schema it goes in, its ``format`` / ``encoding`` and the bytes.

    For ``foxglove.RawImage`` ``fmt`` is the encoding (``rgb8`` / ``16UC1``) and ``step`` the row bytes.
    ``keyframe`` is True for images that decode without earlier ones (all but H.264 delta frames).
    """

    schema: str
    fmt: str
    data: bytes
    width: int
    height: int
    keyframe: bool = True
    step: int = 0


# ---------------------------------------------------------------------------------------------- depth
def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(payload, zlib.crc32(kind)))


def encode_png16(depth: np.ndarray, level: int = 1) -> bytes:
    """(H, W) uint16 -> a 16-bit greyscale PNG (Sub filter on every row, Huffman-only deflate)."""
    d = np.asarray(depth)
    if d.ndim != 2 or d.dtype != np.uint16 or d.size == 0:
        raise CodecError(f"PNG depth: expected a non-empty (H, W) uint16 array, got {d.dtype} {d.shape}")
    h, w = d.shape
    b = np.ascontiguousarray(d, dtype=">u2").view(np.uint8).reshape(h, 2 * w)
    rows = np.empty((h, 2 * w + 1), dtype=np.uint8)
    rows[:, 0] = _PNG_FILTER_SUB
    rows[:, 1:3] = b[:, :2]
    np.subtract(b[:, 2:], b[:, :-2], out=rows[:, 3:])  # uint8 arithmetic wraps mod 256, as PNG's Sub filter
    comp = ZLIB.compressobj(level, ZLIB.DEFLATED, 15, 9, ZLIB.Z_HUFFMAN_ONLY)
    idat = comp.compress(rows) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)  # 16-bit greyscale, deflate, adaptive filters, no interlace
    return _PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")


def decode_png(data: bytes, where: str = "PNG") -> np.ndarray:
    """A PNG -> (H, W) uint16 / uint8 or (H, W, 3|4) uint8 array as stored (colour in RGB order)."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CodecError(f"{where}: not a decodable PNG ({len(data)} bytes)")
    if img.ndim == 3:
        img = np.ascontiguousarray(img[..., ::-1])
    return img


def encode_planes(depth: np.ndarray, level: int = 1) -> bytes:
    """(H, W) uint16 -> the ``planes`` bytes: header, then the zstd high-byte plane and the zstd low-byte plane.

    Residuals are taken modulo 2**16 (every value round-trips), zigzag-mapped so small negative ones stay
    small: the high plane is almost all zeros and costs next to nothing, the low plane carries the noise.
    """
    d = np.asarray(depth)
    if d.ndim != 2 or d.dtype != np.uint16 or d.size == 0:
        raise CodecError(f"planes depth: expected a non-empty (H, W) uint16 array, got {d.dtype} {d.shape}")
    h, w = d.shape
    r = np.empty((h, w), dtype=np.uint16)
    np.subtract(d[:, 1:], d[:, :-1], out=r[:, 1:])  # uint16 arithmetic wraps mod 2**16
    np.subtract(d[1:, 0], d[:-1, 0], out=r[1:, 0])
    r[0, 0] = d[0, 0]
    sr = r.view(np.int16)
    z = ((sr << 1) ^ (sr >> 15)).view(np.uint16)
    c = zstandard.ZstdCompressor(level=level)
    hi = c.compress((z >> 8).astype(np.uint8).tobytes())
    lo = c.compress(z.astype(np.uint8).tobytes())  # astype keeps the low byte
    return _PLANES_HEADER.pack(_PLANES_MAGIC, w, h, len(hi)) + hi + lo


def decode_planes(data: bytes, where: str = "planes depth") -> np.ndarray:
    """The ``planes`` bytes -> (H, W) uint16, exactly as encoded; CodecError naming ``where`` if they are not."""
    n = _PLANES_HEADER.size
    if len(data) < n:
        raise CodecError(f"{where}: {len(data)} bytes is shorter than the planes header")
    magic, w, h, n_hi = _PLANES_HEADER.unpack_from(data)
    if magic != _PLANES_MAGIC or not 0 < w * h <= 1 << 28 or n + n_hi > len(data):
        raise CodecError(f"{where}: not planes depth data (magic {magic!r}, {w}x{h}, high plane {n_hi} bytes)")
    dz = zstandard.ZstdDecompressor()
    try:
        hi = dz.decompress(data[n:n + n_hi], max_output_size=w * h)
        lo = dz.decompress(data[n + n_hi:], max_output_size=w * h)
    except zstandard.ZstdError as e:
        raise CodecError(f"{where}: a planes depth plane does not decompress ({e})") from e
    if len(hi) != w * h or len(lo) != w * h:
        raise CodecError(f"{where}: planes of {len(hi)} / {len(lo)} bytes for a {w}x{h} image")
    z = (np.frombuffer(hi, np.uint8).astype(np.uint16) << 8 | np.frombuffer(lo, np.uint8)).reshape(h, w)
    r = (z >> 1) ^ (np.uint16(0) - (z & 1))  # un-zigzag, mod 2**16
    r[:, 0] = np.cumsum(r[:, 0], dtype=np.uint16)
    return np.cumsum(r, axis=1, dtype=np.uint16)


class DepthEncoder:
    """Lossless depth: (H, W) uint16 mm -> EncodedImage (``png``, ``planes`` or ``raw``)."""

    def __init__(self, codec: DepthCodec = "png") -> None:
        if codec not in ("png", "planes", "raw"):
            raise CodecError(f"depth codec must be 'png', 'planes' or 'raw', not {codec!r}")
        self.codec = codec

    def encode(self, depth_mm: np.ndarray) -> EncodedImage:
        """Encode one depth image (uint16 mm, 0 = no data)."""
        h, w = depth_mm.shape
        if self.codec == "png":
            return EncodedImage(SCHEMA_COMPRESSED, "png", encode_png16(depth_mm), w, h)
        if self.codec == "planes":
            return EncodedImage(SCHEMA_DEPTH, "planes", encode_planes(depth_mm), w, h)
        data = np.ascontiguousarray(depth_mm, dtype="<u2").tobytes()
        return EncodedImage(SCHEMA_RAW, "16UC1", data, w, h, step=2 * w)


# ---------------------------------------------------------------------------------------------- colour
class ColorEncoder:
    """Colour (H, W, 3) uint8 RGB -> EncodedImage; one instance per episode (H.264 keeps state).

    crf: H.264 constant rate factor (0 lossless ... 51; lower is better); preset: libx264 speed preset;
    gop: frames between H.264 keyframes; jpeg_quality: 1-100 for ``jpeg``.
    """

    def __init__(self, codec: ColorCodec = "h264", *, crf: int = 18, preset: str = "ultrafast", gop: int = 30,
                 jpeg_quality: int = 90, fps: float = 30.0) -> None:
        if codec not in ("h264", "jpeg", "raw"):
            raise CodecError(f"colour codec must be 'h264', 'jpeg' or 'raw', not {codec!r}")
        if codec == "h264" and preset not in H264_PRESETS:
            raise CodecError(f"H.264 preset must be one of {H264_PRESETS}, not {preset!r}")
        self.codec = codec
        self.crf, self.preset, self.gop, self.jpeg_quality, self.fps = int(crf), preset, int(gop), jpeg_quality, fps
        self._ctx: Any = None
        self._size: tuple[int, int] | None = None
        self._n = 0

    def _open(self, w: int, h: int) -> None:
        import av

        if w % 2 or h % 2:
            raise CodecError(f"H.264 4:2:0 needs an even image size, got {w}x{h}: use colour codec 'jpeg'")
        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height, ctx.pix_fmt = w, h, "yuvj420p"  # full range: 0-255 kept, ~0.5 dB PSNR
        ctx.time_base = Fraction(1, 1000)
        ctx.framerate = Fraction(self.fps).limit_denominator(1001)
        ctx.gop_size = self.gop
        ctx.max_b_frames = 0
        ctx.thread_count = 1  # the recorder encodes depth beside it; one thread keeps the CPU per frame lowest
        ctx.options = {
            "preset": self.preset, "crf": str(self.crf), "tune": "zerolatency",
            # SPS/PPS before every IDR (each keyframe decodes alone); fixed GOP, no scene-cut keyframes
            "x264-params": f"repeat-headers=1:keyint={self.gop}:min-keyint={self.gop}:scenecut=0:bframes=0",
        }
        ctx.open()
        self._ctx, self._size = ctx, (w, h)

    def encode(self, rgb: np.ndarray) -> EncodedImage:
        """Encode one colour image; the first H.264 frame of an encoder is always a keyframe."""
        import cv2

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise CodecError(f"colour: expected (H, W, 3) uint8 RGB, got {rgb.dtype} {rgb.shape}")
        h, w = rgb.shape[:2]
        if self.codec == "raw":
            return EncodedImage(SCHEMA_RAW, "rgb8", np.ascontiguousarray(rgb).tobytes(), w, h, step=3 * w)
        if self.codec == "jpeg":
            ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                                   [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality)])
            if not ok:
                raise CodecError(f"colour: JPEG encoding of a {w}x{h} image failed")
            return EncodedImage(SCHEMA_COMPRESSED, "jpeg", buf.tobytes(), w, h)
        import av

        if self._ctx is None:
            self._open(w, h)
        elif self._size != (w, h):
            raise CodecError(f"colour: image size changed from {self._size} to {(w, h)} inside one H.264 stream")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24").reformat(format="yuvj420p")
        frame.pts = int(round(self._n * 1000.0 / self.fps))
        self._n += 1
        packets = self._ctx.encode(frame)
        if len(packets) != 1:  # zerolatency: one access unit per frame, never delayed
            raise CodecError(f"colour: libx264 gave {len(packets)} packets for frame {self._n - 1}, expected 1")
        p = packets[0]
        return EncodedImage(SCHEMA_VIDEO, "h264", bytes(p), w, h, keyframe=bool(p.is_keyframe))

    def close(self) -> None:
        """Flush and free the encoder (nothing is pending with zerolatency)."""
        if self._ctx is not None:
            try:
                self._ctx.encode(None)
            except Exception:  # noqa: BLE001 - an already flushed or failed encoder has nothing left
                pass
            self._ctx = None


def h264_nal_types(data: bytes) -> list[int]:
    """NAL unit types of an Annex B H.264 access unit (5 IDR, 1 slice, 7 SPS, 8 PPS, 6 SEI, ...)."""
    b = np.frombuffer(data, dtype=np.uint8)
    if len(b) < 4:
        return []
    z = np.flatnonzero((b[:-3] == 0) & (b[1:-2] == 0) & (b[2:-1] == 1))  # 00 00 01 (also ends 00 00 00 01)
    return [int(b[i + 3]) & 0x1F for i in z.tolist()]


# ---------------------------------------------------------------------------------------------- decoding
class ImageDecoder:
    """Decodes the image messages of one stream back to arrays, in order (H.264 needs every frame
    from a keyframe on: feed messages sequentially, starting at a keyframe).

    ``decode(schema, msg)`` takes the Foxglove schema name and the decoded protobuf message and returns
    (H, W, 3) uint8 RGB or (H, W) uint16 as written.
    """

    def __init__(self, where: str = "image") -> None:
        self.where = where
        self._h264: Any = None

    def decode(self, schema: str, msg: Any) -> np.ndarray:
        """One message -> array (colour RGB uint8, depth uint16)."""
        if schema == SCHEMA_RAW:
            return decode_raw(msg, self.where)
        fmt = str(msg.format)
        if schema == SCHEMA_COMPRESSED:
            if fmt == "png":
                return decode_png(msg.data, self.where)
            if fmt in ("jpeg", "jpg"):
                import cv2

                img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    raise CodecError(f"{self.where}: not a decodable JPEG ({len(msg.data)} bytes)")
                return np.ascontiguousarray(img[..., ::-1])
            raise CodecError(f"{self.where}: unsupported CompressedImage format {fmt!r} (expected png or jpeg)")
        if schema == SCHEMA_DEPTH:
            if fmt != "planes":
                raise CodecError(f"{self.where}: unsupported {SCHEMA_DEPTH} format {fmt!r} (expected planes)")
            return decode_planes(bytes(msg.data), self.where)
        if schema == SCHEMA_VIDEO:
            if fmt != "h264":
                raise CodecError(f"{self.where}: unsupported CompressedVideo format {fmt!r} (expected h264)")
            import av

            if self._h264 is None:
                self._h264 = av.CodecContext.create("h264", "r")
            try:
                frames = self._h264.decode(av.Packet(bytes(msg.data)))
            except av.FFmpegError as e:
                raise CodecError(f"{self.where}: H.264 data does not decode ({e})") from e
            if len(frames) != 1:
                raise CodecError(
                    f"{self.where}: H.264 message gave {len(frames)} frames (expected 1; a stream must be "
                    "decoded from a keyframe on, without B-frames)"
                )
            return frames[0].to_ndarray(format="rgb24")
        raise CodecError(f"{self.where}: unsupported image schema {schema!r}")


def decode_raw(msg: Any, where: str) -> np.ndarray:
    """A foxglove.RawImage (rgb8, bgr8, 16UC1, mono16, 32FC1 metres) -> RGB uint8 or uint16 (32FC1 -> mm)."""
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), msg.encoding
    rows = np.frombuffer(msg.data, dtype=np.uint8)
    if rows.size < h * step:
        raise CodecError(f"{where}: image data holds {rows.size} bytes, expected {h * step}")
    rows = rows[: h * step].reshape(h, step)
    if enc in ("rgb8", "bgr8"):
        img = rows[:, : w * 3].reshape(h, w, 3)
        return (img[..., ::-1] if enc == "bgr8" else img).copy()  # owned, writable
    if enc in ("16UC1", "mono16"):
        return np.ascontiguousarray(rows[:, : w * 2]).view("<u2").reshape(h, w).astype(np.uint16)
    if enc == "32FC1":  # metres -> mm
        m = np.ascontiguousarray(rows[:, : w * 4]).view("<f4").reshape(h, w)
        return np.clip(np.round(np.nan_to_num(m, nan=0.0) * 1000.0), 0, 65535).astype(np.uint16)
    raise CodecError(f"{where}: unsupported image encoding {enc!r}")
