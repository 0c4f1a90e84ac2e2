"""The one image path: encoded bytes -> the image a descriptor spec reads -> descriptor rows.

Every entry point that turns pixels into descriptor rows (``ingest`` and ``localize`` of an
image folder, ``eval`` of a data set's traversals, the service's image frames, the thumbnails
kept beside the rows) decodes through :func:`decode_for`, which asks the
:class:`~sprint_map.frontend.descriptors.DescriptorSpec` how to decode (8-bit gray for HoG,
patchnorm and a gray ONNX model; BGR for a colour ONNX model) instead of each caller choosing a
default. A caller that decoded gray for a colour model described other pixels than ``ingest``
did, without a word (issue 52, item 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.frontend.imagefiles import decode_image, read_image_bytes
from sprint_map.frontend.imageheader import MAX_IMAGE_PIXELS
from sprint_map.util.arrays import Descriptors, Image

__all__ = ["decode_for", "describe_encoded", "describe_files"]


def decode_for(spec: DescriptorSpec, data: bytes, label: str,
               max_pixels: int = MAX_IMAGE_PIXELS) -> Image:
    """Decode image bytes as ``spec`` reads them: ``(H, W)`` gray if ``spec.grayscale``, else
    ``(H, W, 3)`` BGR. Raises :class:`~sprint_map.errors.InputError` starting with ``label``
    (see :func:`~sprint_map.frontend.imagefiles.decode_image`). O(pixels)."""
    return decode_image(data, label, grayscale=spec.grayscale, max_pixels=max_pixels)


def describe_encoded(spec: DescriptorSpec, blobs: Sequence[tuple[bytes, str]],
                     max_pixels: int = MAX_IMAGE_PIXELS) -> tuple[Descriptors, list[Image]]:
    """The ``(len(blobs), dim)`` float32 rows of ``(bytes, label)`` pairs, and the decoded
    images (for thumbnails). O(pixels + model)."""
    images = [decode_for(spec, data, label, max_pixels) for data, label in blobs]
    return spec.describe_batch(images), images


def describe_files(spec: DescriptorSpec, paths: Sequence[Path]
                   ) -> tuple[Descriptors, list[Image], list[bytes]]:
    """Read, decode and describe image files; also returns their images and bytes (for
    thumbnails). Raises :class:`~sprint_map.errors.InputError` naming the file. O(pixels)."""
    blobs = [(read_image_bytes(path), str(path)) for path in paths]
    rows, images = describe_encoded(spec, blobs)
    return rows, images, [data for data, _ in blobs]
