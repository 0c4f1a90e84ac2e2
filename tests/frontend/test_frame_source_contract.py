"""Every frame source passes the one contract
(:class:`tests.helpers.contracts.FrameSourceContract`): a directory of images, a video (two
containers) and a ``.npy`` of descriptors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.helpers.contracts import FrameSourceContract
from tests.helpers.frames import frame, write_video


class TestImageDirectory(FrameSourceContract):
    kind = "images"

    def make(self, tmp_path: Path) -> Path:
        folder = tmp_path / "walk"
        folder.mkdir()
        for i in range(self.FRAMES):
            assert cv2.imwrite(str(folder / f"img{i}.png"), frame(i))
        return folder


class TestVideoAVI(FrameSourceContract):
    kind = "video"
    fourcc = "MJPG"
    suffix = ".avi"

    def make(self, tmp_path: Path) -> Path:
        path = tmp_path / f"drive{self.suffix}"
        assert len(write_video(path, self.FRAMES, self.fourcc)) == self.FRAMES
        return path


class TestVideoMP4(TestVideoAVI):
    fourcc = "mp4v"
    suffix = ".mp4"


class TestNpy(FrameSourceContract):
    kind = "npy"

    def make(self, tmp_path: Path) -> Path:
        path = tmp_path / "descriptors.npy"
        np.save(path, np.random.default_rng(3).standard_normal((self.FRAMES, 24)))
        return path
