"""Episode image codecs: lossless depth, H.264 stream layout, and every encoding read back by the episode reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orchestrator.config import ColorOutputConfig, ConfigError, DepthOutputConfig, parse_config
from orchestrator.recorder import EpisodeWriter
from tdcommon.types import CameraIntrinsics, RGBDFrame
from tdrecord import read_episodes
from tdrecord.codecs import (
    SCHEMA_VIDEO,
    CodecError,
    ColorEncoder,
    DepthEncoder,
    ImageDecoder,
    decode_planes,
    decode_png,
    encode_planes,
    encode_png16,
    h264_nal_types,
)

W, H = 96, 64


def _scene(n: int) -> RGBDFrame:
    """A smooth moving colour scene (what a camera sees, unlike uniform noise) and noisy depth with holes."""
    rng = np.random.default_rng(n)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    color = np.stack([128 + 100 * np.sin((xx + 2 * n) / 9.0), 128 + 90 * np.cos(yy / 7.0),
                      100 + 0.8 * xx + 0.5 * yy], axis=-1)
    color = np.clip(color + rng.normal(0, 1.0, color.shape), 0, 255).astype(np.uint8)
    depth = (900 + 3 * xx + rng.normal(0, 6, (H, W))).astype(np.uint16)
    depth[rng.random((H, W)) < 0.05] = 0
    depth[0, :3] = [65535, 1, 256]
    return RGBDFrame(color, depth, 0.001, CameraIntrinsics.from_fov(W, H, 69.0), n / 30.0, n / 30.0 + 0.01, n)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def test_png16_is_bit_exact_on_every_value() -> None:
    rng = np.random.default_rng(0)
    d = rng.integers(0, 65536, (37, 53), dtype=np.uint16)  # odd sizes, full range, no smoothness
    d[5] = 0
    data = encode_png16(d)
    assert data.startswith(b"\x89PNG\r\n\x1a\n") and data.rstrip(b"\x00").endswith(b"IEND\xaeB`\x82")
    back = decode_png(data)
    assert back.dtype == np.uint16 and back.shape == d.shape
    np.testing.assert_array_equal(back, d)
    with pytest.raises(CodecError, match="uint16"):
        encode_png16(d.astype(np.int32))


def test_planes_depth_is_bit_exact_on_every_value_and_refuses_other_bytes() -> None:
    rng = np.random.default_rng(1)
    for d in (rng.integers(0, 65536, (37, 53), dtype=np.uint16),  # full range, no smoothness
              _scene(3).depth, np.zeros((1, 1), np.uint16), np.full((4, 7), 65535, np.uint16)):
        back = decode_planes(encode_planes(d))
        assert back.dtype == np.uint16 and back.shape == d.shape
        np.testing.assert_array_equal(back, d)
    smooth = _scene(4).depth
    assert len(encode_planes(smooth)) < len(encode_png16(smooth))  # the point of it, on noisy depth
    data = encode_planes(smooth)
    for bad in (b"", data[:10], b"XXXX" + data[4:], data[:-5]):
        with pytest.raises(CodecError, match="where-it-was"):
            decode_planes(bad, "where-it-was")
    with pytest.raises(CodecError, match="uint16"):
        encode_planes(smooth.astype(np.float32))


def test_h264_stream_layout_keyframes_and_headers() -> None:
    enc = ColorEncoder("h264", crf=18, gop=8)
    images = [enc.encode(_scene(n).color) for n in range(20)]
    enc.close()
    assert [i for i, im in enumerate(images) if im.keyframe] == [0, 8, 16]
    for im in images:
        assert im.schema == SCHEMA_VIDEO and im.fmt == "h264" and im.data[:4] == b"\x00\x00\x00\x01"  # Annex B
        nals = h264_nal_types(im.data)
        if im.keyframe:
            assert {7, 8, 5} <= set(nals), nals  # SPS, PPS and an IDR slice in every keyframe message
        else:
            assert 5 not in nals and 1 in nals
    # one message decodes to exactly one frame, in order, with no lookahead (no B-frames)
    dec = ImageDecoder()
    for n, im in enumerate(images):
        rgb = dec.decode(SCHEMA_VIDEO, type("M", (), {"format": "h264", "data": im.data})())
        assert rgb.shape == (H, W, 3) and _psnr(rgb, _scene(n).color) > 35.0


def test_h264_refuses_odd_sizes_and_bad_settings() -> None:
    with pytest.raises(CodecError, match="even"):
        ColorEncoder("h264").encode(np.zeros((5, 8, 3), np.uint8))
    with pytest.raises(CodecError, match="preset"):
        ColorEncoder("h264", preset="placebo-ish")
    with pytest.raises(CodecError, match="depth codec"):
        DepthEncoder("ffv1")  # type: ignore[arg-type]


@pytest.mark.parametrize("codec", ["h264", "jpeg", "raw"])
@pytest.mark.parametrize("depth_codec", ["png", "planes", "raw"])
def test_every_encoding_reads_back(tmp_path: Path, codec: str, depth_codec: str) -> None:
    path = tmp_path / "episode_000000.mcap"
    w = EpisodeWriter(path, "cam0", color=ColorOutputConfig(codec=codec, gop=10),
                      depth=DepthOutputConfig(codec=depth_codec))
    frames = [_scene(n) for n in range(25)]
    for f in frames:
        w.write_frame(f, np.eye(4))
    K = frames[0].intrinsics.K
    w.close({"calibration": {"width": W, "height": H, "K": K.tolist(), "T_world_cam": np.eye(4).tolist()}})
    seq = read_episodes(path)
    got = list(seq.frames)
    assert [g.frame_number for g in got] == list(range(25))
    for g, f in zip(got, frames, strict=True):
        np.testing.assert_array_equal(g.depth, f.depth)  # lossless: bit-exact
        assert g.depth.dtype == np.uint16 and g.depth_scale == 0.001
        if codec == "raw":
            np.testing.assert_array_equal(g.color, f.color)
        else:
            assert _psnr(g.color, f.color) > 35.0
    # starting in the middle of a GOP decodes from the keyframe before it: the same images as a full pass
    for start in (0, 7, 10, 13, 24):
        tail = list(seq.frames.iter_from(start))
        assert [t.frame_number for t in tail] == list(range(start, 25))
        np.testing.assert_array_equal(tail[0].color, got[start].color)
        np.testing.assert_array_equal(tail[-1].depth, got[-1].depth)
    assert list(seq.frames.iter_from(25)) == []


def test_recorder_encodes_off_the_caller_and_counts_cpu(tmp_path: Path) -> None:
    from orchestrator.recorder import Recorder

    rec = Recorder("cam0", close_grace=0)
    rec.open_episode(tmp_path / "episode_000000.mcap", {"object": "rope"})
    for n in range(12):
        rec.frame(_scene(n), np.eye(4))
    rec.close_episode({"complete": True})
    rec.stop()
    assert not rec.errors and rec.frames_written == 12 and rec.cpu_seconds > 0
    seq = read_episodes(rec.finished[0])
    assert len(seq) == 12
    assert seq.metadata["image_encoding"]["color"]["codec"] == "h264"
    np.testing.assert_array_equal(list(seq.frames)[11].depth, _scene(11).depth)


def test_output_encoding_settings_are_validated() -> None:
    import yaml

    from tests.conftest import REPO

    data = yaml.safe_load((REPO / "configs" / "mock.yaml").read_text())
    data.setdefault("output", {})["color"] = {"codec": "h264", "crf": 60}
    with pytest.raises(ConfigError, match=r"output\.color\.crf"):
        parse_config(data)
    data["output"]["color"] = {"codec": "vp8"}
    with pytest.raises(ConfigError, match=r"output\.color\.codec"):
        parse_config(data)
    data["output"]["color"] = {"codec": "jpeg", "jpeg_quality": 80}
    data["output"]["depth"] = {"codec": "raw"}
    cfg = parse_config(data)
    assert cfg.output.color.codec == "jpeg" and cfg.output.depth.codec == "raw"
