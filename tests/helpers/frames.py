"""Small synthetic images and videos for the frame-source tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

__all__ = ["frame", "write_video"]


def frame(index: int, h: int = 60, w: int = 80) -> np.ndarray:
    """A distinct, structured BGR frame per index."""
    rng = np.random.default_rng(index)
    image = cv2.GaussianBlur(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), (0, 0), 1.5)
    cv2.putText(image, str(index), (5, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
    return image


def write_video(path: Path, frames: int, fourcc: str = "MJPG") -> list[np.ndarray]:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (80, 60))
    assert writer.isOpened()
    for i in range(frames):
        writer.write(frame(i))
    writer.release()
    # What the decoder gives back (lossy codec), to compare descriptors against.
    capture = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        decoded.append(image)
    capture.release()
    return decoded
