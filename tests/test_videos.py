"""Rollout videos are H.264 MP4 (what browsers, GitHub and notebooks play), frame for frame."""

from __future__ import annotations

import subprocess
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np
import pytest

from memrl.evaluation.rollouts import write_rgb_video


def codec_line(path: Path) -> str:
    """ffmpeg's description of the video stream (ffmpeg -i prints it and exits non-zero)."""
    err = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-i", str(path)],
                         capture_output=True, text=True).stderr
    [line] = [x for x in err.splitlines() if "Video:" in x]
    return line


def fourcc(path: Path) -> str:
    cap = cv2.VideoCapture(str(path))
    code = int(cap.get(cv2.CAP_PROP_FOURCC))
    cap.release()
    return code.to_bytes(4, "little").decode()


def test_video_is_h264_yuv420p_with_every_frame(tmp_path):
    frames = [np.full((60, 80, 3), (20 * i, 100, 200 - 20 * i), np.uint8) for i in range(10)]
    path = write_rgb_video(frames, tmp_path / "v.mp4", fps=10)
    line = codec_line(path)
    assert "Video: h264" in line and "yuv420p" in line and "80x60" in line
    assert fourcc(path) in ("avc1", "h264")
    cap = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        decoded.append(cv2.cvtColor(f, cv2.COLOR_BGR2RGB))
    cap.release()
    assert len(decoded) == len(frames)
    # lossy codec: each flat frame comes back as its own colour, not a neighbour's (20 apart)
    for original, back in zip(frames, decoded, strict=True):
        assert np.abs(back.astype(int) - original.astype(int)).mean() < 5


def test_odd_frame_sizes_are_refused(tmp_path):
    with pytest.raises(ValueError, match="even frame sizes"):
        write_rgb_video([np.zeros((61, 80, 3), np.uint8)], tmp_path / "odd.mp4")
    assert not (tmp_path / "odd.mp4").exists()
