"""Frame reading: timestamps from the container, range and step, sequences, bad input."""

import cv2
import numpy as np
import pytest

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.processing.frames import FrameSource, read_color_frame


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "clip.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25, (64, 48))
    for i in range(20):
        w.write(np.full((48, 64, 3), i * 10, np.uint8))
    w.release()
    return path


def test_timestamps_range_and_step(video):
    src = FrameSource(video, start_s=0.2, end_s=0.6, step=2)
    frames = list(src)
    assert [f.index for f in frames] == [5, 7, 9, 11, 13, 15]
    np.testing.assert_allclose([f.t_s for f in frames], [0.2, 0.28, 0.36, 0.44, 0.52, 0.60], atol=1e-6)
    assert frames[0].image.shape == (48, 64) and frames[0].image.dtype == np.uint8
    assert src.estimated_count() == 5 or src.estimated_count() == 6


def test_sequence_needs_interval(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((10, 12), i * 50, np.uint8))
    with pytest.raises(ParameterError, match="video.frame_interval_s"):
        FrameSource(tmp_path)
    frames = list(FrameSource(tmp_path / "f*.png", frame_interval_s=0.5))
    assert [f.t_s for f in frames] == [0.0, 0.5, 1.0]
    assert read_color_frame(tmp_path, 0.5, 0.5)[0, 0, 0] == 50


def test_bad_inputs(tmp_path, video):
    with pytest.raises(InputFileError, match="video not found"):
        FrameSource(tmp_path / "missing.mp4")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all" * 100)
    with pytest.raises(InputFileError, match="cannot be read as a video"):
        FrameSource(junk)
    with pytest.raises(ParameterError, match="video.start_s: 5 s is outside the clip"):
        FrameSource(video, start_s=5)
    with pytest.raises(ParameterError, match="video.end_s: 9 s is beyond the end"):
        FrameSource(video, end_s=9)
    with pytest.raises(ParameterError, match="video.step"):
        FrameSource(video, step=0)
