"""Videos of reaches: offscreen frames that show the arm moving, MP4 and GIF files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dammrl.stack.runner import ReachRunner
from dammrl.views.video import (
    OUTCOME_SHOWN_S,
    VideoSettings,
    frame_times,
    frames,
    track_of_reach,
    write_video,
)
from dammrl_core.errors import ConfigurationError

SMALL = VideoSettings(fps=5, width=160, height=120)


@pytest.fixture(scope="module")
def reach(runner: ReachRunner):  # type: ignore[no-untyped-def]
    return runner.run(7_000_001, (2, 1))


def test_frames_cover_the_reach_and_show_the_arm_moving(reach, runner: ReachRunner) -> None:  # type: ignore[no-untyped-def]
    track = track_of_reach(reach)
    images = list(frames(track, SMALL, runner))
    times = frame_times(track, SMALL)
    assert len(images) == len(times) == int((track.end_s + OUTCOME_SHOWN_S) * 5) + 1
    assert times[-1] >= track.end_s  # the last frames show the outcome, the arm still
    assert all(image.shape == (120, 160, 3) for image in images)
    moved = np.abs(images[0].astype(int) - images[len(images) // 2].astype(int)).mean()
    assert moved > 1.0, moved  # the arm is somewhere else half-way
    assert images[0][40:].std() > 10  # not a blank frame: the arm and the table are drawn


def test_mp4_and_gif_files(reach, tmp_path: Path, runner: ReachRunner) -> None:  # type: ignore[no-untyped-def]
    av = pytest.importorskip("av")
    track = track_of_reach(reach)
    count = write_video(track, tmp_path / "reach.mp4", SMALL)
    with av.open(str(tmp_path / "reach.mp4")) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(decoded) == count == len(frame_times(track, SMALL))
    assert decoded[0].shape == (120, 160, 3)
    assert write_video(track, tmp_path / "reach.gif", SMALL) == count
    with pytest.raises(ConfigurationError, match=r"\.mp4 or \.gif"):
        write_video(track, tmp_path / "reach.avi", SMALL)
    with pytest.raises(ConfigurationError, match="fps"):
        write_video(track, tmp_path / "reach.gif", VideoSettings(fps=0))


def test_reach_video_from_the_command_line(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "dammrl", "reach", "--seed", "7000002", "--model", "1,1",
         "--video", str(tmp_path / "reach.gif")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "reach.gif").stat().st_size > 20_000
    assert "video written" in done.stderr
