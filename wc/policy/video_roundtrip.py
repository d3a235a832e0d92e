"""The dataset's video codec as an observation filter: what a policy trained on the LeRobot dataset saw.

The dataset stage stores camera frames as videos (lerobot's encoder, `dataset.video_codec` / `video_crf` /
`video_gop_frames`, yuv420p); training decodes them. Closed-loop evaluation renders raw frames, so without
this filter the policy would meet sharper, differently coloured images than it learnt from. Each frame is
encoded as a one-frame video with the same encoder settings (the intra frame that opens each of the
dataset's GOPs) and decoded with PyAV, the dataset's decoder, in RGB order.
"""

from __future__ import annotations

import io
import os
from typing import Any

import av
import numpy as np

from wc.policy.dataset_config import DatasetConfig


def video_encoder(cfg: DatasetConfig) -> Any:
    """lerobot's encoder config for the dataset's camera videos."""
    from lerobot.configs.video import RGBEncoderConfig

    return RGBEncoderConfig(vcodec=cfg.video_codec, crf=cfg.video_crf, g=cfg.video_gop_frames)


class VideoRoundTrip:
    """frame (H, W, 3) uint8 RGB -> the same frame after the dataset's encode and decode."""

    def __init__(self, cfg: DatasetConfig, fps: int) -> None:
        os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its whole config at every encoder start otherwise
        self.encoder = video_encoder(cfg)
        self.options = self.encoder.get_codec_options(cfg.encoder_threads or None, as_strings=True)
        self.fps = int(fps)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise ValueError(f"video round trip needs an (H, W, 3) uint8 RGB frame, got {frame.shape} {frame.dtype}")
        buffer = io.BytesIO()
        with av.open(buffer, "w", format="mp4") as container:
            stream = container.add_stream(self.encoder.vcodec, self.fps, options=self.options)
            stream.pix_fmt, stream.height, stream.width = self.encoder.pix_fmt, *frame.shape[:2]
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")):
                container.mux(packet)
            for packet in stream.encode():  # flush
                container.mux(packet)
        buffer.seek(0)
        with av.open(buffer) as container:
            decoded = next(container.decode(video=0)).to_ndarray(format="rgb24")
        if decoded.shape != frame.shape:
            raise RuntimeError(f"video round trip changed the frame shape {frame.shape} -> {decoded.shape}")
        return decoded
