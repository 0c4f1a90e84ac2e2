"""Whole-image descriptors: the paper's HoG and a SeqSLAM-style patch-normalised thumbnail.

A :class:`DescriptorSpec` names a descriptor kind and its parameters. It is a small frozen value
(a string and a dict of numbers), so it pickles cheaply to worker processes and can be stored in a
map's configuration; the OpenCV objects it needs are built lazily, once per thread, and never
pickled.

Kinds
-----
``"hog"``
    The SPRINT paper's descriptor (Latif et al. 2020, section IV-B): grayscale, resized to
    ``size x size`` with ``cv2.INTER_AREA``, one HoG window ``cv2.HOGDescriptor((size, size),
    (block, block), (stride, stride), (cell, cell), bins)``, vectorised, L2-normalised. The
    defaults (64, 16, 8, 8, 9) give 1764 dimensions. About 0.45 ms per 640x480 image (resize
    included) on one core.
``"patchnorm"``
    SeqSLAM-style (Milford & Wyeth 2012): grayscale, resized to ``width x height`` with
    ``cv2.INTER_AREA``, every non-overlapping ``patch x patch`` block shifted to zero mean and
    scaled to unit standard deviation (a flat block becomes zeros), flattened, L2-normalised.
    The defaults (32 x 16, patch 4) give 512 dimensions. Invariant to any per-patch affine
    brightness change, which is what makes it robust to lighting.

Every descriptor is float32 with unit L2 norm, except that an image with no structure at all (a
black frame, a flat wall) gives the zero vector rather than NaN. The raw vector is checked
before it is normalised (``check_described``: NaN, Inf or an overflow is an
:class:`~sprint_map.errors.InvalidDescriptorError` naming the image), so a normalisation never
turns a broken vector into zeros.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import NDArray

from sprint_map.errors import ConfigError
from sprint_map.util.arrays import Descriptors, Float32Array, Image
from sprint_map.util.validation import check_described

if TYPE_CHECKING:
    import cv2

__all__ = ["DEFAULT_PARAMS", "DESCRIPTOR_KINDS", "DescriptorSpec", "to_gray"]

#: Parameter defaults per kind; a spec always carries every parameter of its kind, so two specs
#: that describe the same computation compare (and serialise) equal.
DEFAULT_PARAMS: dict[str, dict[str, int]] = {
    "hog": {"size": 64, "block": 16, "stride": 8, "cell": 8, "bins": 9},
    "patchnorm": {"width": 32, "height": 16, "patch": 4},
}

#: A user's ONNX model (:mod:`sprint_map.frontend.onnx_model`): its parameters are the model's
#: path, digest, card and dimension, made by ``onnx_params`` when a map is created.
ONNX_KIND = "onnx"

DESCRIPTOR_KINDS = (*DEFAULT_PARAMS, ONNX_KIND)

# Norms below this are treated as zero: the image had no gradients / no contrast at all.
_ZERO_NORM = 1e-12

# One cv2.HOGDescriptor per (thread, parameters). HOGDescriptor::compute is const in OpenCV, but a
# per-thread instance costs microseconds and removes any doubt about sharing one across threads.
_local = threading.local()


@dataclass(frozen=True, eq=True)
class DescriptorSpec:
    """A descriptor kind and its parameters.

    Parameters
    ----------
    kind : str
        ``"hog"`` or ``"patchnorm"`` (see the module docstring).
    params : dict
        Overrides of the kind's defaults (:data:`DEFAULT_PARAMS`); missing ones are filled in,
        so ``spec.params`` always holds the complete set.

    Raises
    ------
    ConfigError
        On an unknown kind, an unknown parameter, or an inconsistent value (e.g. a HoG window
        the blocks do not tile, a patchnorm size the patch does not divide).

    Examples
    --------
    >>> spec = DescriptorSpec("hog")
    >>> spec.dim
    1764
    >>> DescriptorSpec("patchnorm", {"width": 64, "height": 32, "patch": 8}).dim
    2048
    """

    kind: str
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind == ONNX_KIND:
            from sprint_map.frontend.onnx_model import check_params

            if not isinstance(self.params, Mapping):
                raise ConfigError("descriptor params must be a mapping")
            object.__setattr__(self, "params", check_params(self.params))
            return
        if self.kind not in DEFAULT_PARAMS:
            raise ConfigError(
                f"unknown descriptor kind {self.kind!r}; expected one of {', '.join(DESCRIPTOR_KINDS)}"
            )
        if not isinstance(self.params, Mapping):
            raise ConfigError(
                f"descriptor params must be a mapping, got {type(self.params).__name__}"
            )
        defaults = DEFAULT_PARAMS[self.kind]
        unknown = sorted(set(self.params) - set(defaults))
        if unknown:
            raise ConfigError(
                f"unknown {self.kind} parameter(s) {', '.join(unknown)}; "
                f"expected {', '.join(defaults)}"
            )
        full = dict(defaults)
        for name, value in self.params.items():
            # bool is an int subclass; True as a size is a typo, not a 1.
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"{self.kind} parameter {name} must be a positive integer")
            full[name] = int(value)
        object.__setattr__(self, "params", full)
        _validate(self.kind, full)

    def __hash__(self) -> int:
        return hash((self.kind, json.dumps(self.params, sort_keys=True)))

    @property
    def grayscale(self) -> bool:
        """Whether the descriptor reads gray images (so sources may decode them gray)."""
        return self.kind != ONNX_KIND or self.params["channels"] == "gray"

    @property
    def dim(self) -> int:
        """Number of dimensions of one descriptor."""
        if self.kind == ONNX_KIND:
            return int(self.params["dim"])
        p: dict[str, int] = self.params
        if self.kind == "hog":
            windows_per_side = (p["size"] - p["block"]) // p["stride"] + 1
            cells_per_block = (p["block"] // p["cell"]) ** 2
            return windows_per_side**2 * cells_per_block * p["bins"]
        return p["width"] * p["height"]

    def describe(self, image: Image) -> Descriptors:
        """Describe one image.

        Parameters
        ----------
        image : ndarray of uint8
            Grayscale ``(H, W)``, BGR ``(H, W, 3)`` or BGRA ``(H, W, 4)`` (OpenCV channel
            order); uint16 images are reduced to 8 bits first.

        Returns
        -------
        ndarray of float32, shape (dim,)
            Unit L2 norm, or all zeros for an image without any structure.
        """
        if self.kind == ONNX_KIND:
            row: Descriptors = self.describe_batch([image])[0]
            return row
        return self._describe(image, 0, 1)

    def _describe(self, image: Image, index: int, count: int) -> Descriptors:
        """HoG or patchnorm of image ``index`` of ``count``: its raw vector checked
        (:func:`~sprint_map.util.validation.check_described`), then L2-normalised."""
        gray = to_gray(image)
        raw = _hog(gray, self.params) if self.kind == "hog" else _patchnorm(gray, self.params)
        check_described(raw.reshape(1, -1), self.kind, index, count)
        return _l2_normalise(raw)

    def describe_batch(self, images: Iterable[Image]) -> Descriptors:
        """Describe several images (a sequence, or an array stacked along axis 0).

        Returns
        -------
        ndarray of float32, shape (N, dim)
        """
        if self.kind == ONNX_KIND:
            from sprint_map.frontend.onnx_model import describe_images

            return describe_images(self.params, list(images))
        images = list(images)
        rows = [self._describe(image, i, len(images)) for i, image in enumerate(images)]
        if not rows:
            return np.empty((0, self.dim), dtype=np.float32)
        return np.stack(rows)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict (``{"kind": ..., "params": {...}}``)."""
        return {"kind": self.kind, "params": dict(self.params)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DescriptorSpec:
        """Inverse of :meth:`to_dict`."""
        if not isinstance(data, Mapping) or set(data) - {"kind", "params"} or "kind" not in data:
            raise ConfigError(
                f"descriptor spec must be {{'kind': ..., 'params': {{...}}}}, got {data!r}"
            )
        return cls(str(data["kind"]), dict(data.get("params", {})))

    @classmethod
    def parse(cls, text: str) -> DescriptorSpec:
        """Parse a command-line form: ``"hog"``, ``"patchnorm:width=64,height=32,patch=8"``.

        Raises
        ------
        ConfigError
            On a malformed string or a value :class:`DescriptorSpec` refuses.
        """
        kind, _, rest = text.strip().partition(":")
        if kind.strip() == ONNX_KIND:
            raise ConfigError("an onnx descriptor is made from its model: init --descriptor "
                              "onnx --model FILE")
        params: dict[str, Any] = {}
        for item in filter(None, (part.strip() for part in rest.split(","))):
            name, sep, value = item.partition("=")
            try:
                if not sep:
                    raise ValueError
                params[name.strip()] = int(value)
            except ValueError:
                raise ConfigError(
                    f"bad descriptor option {item!r} in {text!r}; expected name=integer"
                ) from None
        return cls(kind.strip(), params)

    def __str__(self) -> str:
        if self.kind == ONNX_KIND:
            return f"onnx:{self.params['model']} (dim {self.params['dim']})"
        return f"{self.kind}:" + ",".join(f"{k}={v}" for k, v in self.params.items())

    def __repr__(self) -> str:
        return f"DescriptorSpec({self.kind!r}, {json.dumps(self.params)})"


def _validate(kind: str, p: dict[str, int]) -> None:
    if kind == "hog":
        if p["block"] > p["size"] or (p["size"] - p["block"]) % p["stride"]:
            raise ConfigError("hog: (size - block) must be a non-negative multiple of stride")
        if p["block"] % p["cell"] or p["stride"] % p["cell"]:
            # OpenCV requires block and block stride to be multiples of the cell size.
            raise ConfigError("hog: block and stride must be multiples of cell")
    elif p["width"] % p["patch"] or p["height"] % p["patch"]:
        raise ConfigError("patchnorm: width and height must be multiples of patch")


def to_gray(image: Image) -> Image:
    """Return an 8-bit single-channel view/copy of a gray, BGR or BGRA image.

    Raises
    ------
    ValueError
        On an empty image, an unsupported number of channels or an unsupported dtype.
    """
    if not isinstance(image, np.ndarray) or image.size == 0:
        raise ValueError("expected a non-empty image array")
    if image.dtype == np.uint16:
        image = (cast("NDArray[np.uint16]", image) >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 or uint16 image, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3:
        channels = image.shape[2]
        if channels == 1:
            return image[:, :, 0]
        if channels == 3:
            import cv2  # (OpenCV loads with the first image, not with the package)

            return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if channels == 4:
            import cv2

            return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise ValueError(f"expected a (H, W), (H, W, 3) or (H, W, 4) image, got shape {image.shape}")


def _l2_normalise(vector: Float32Array) -> Descriptors:
    norm = float(np.linalg.norm(vector))
    if norm < _ZERO_NORM:
        return np.zeros_like(vector, dtype=np.float32)
    return (vector / norm).astype(np.float32, copy=False)


def _hog_object(p: dict[str, int]) -> cv2.HOGDescriptor:
    cache: dict[tuple[int, ...], cv2.HOGDescriptor] | None = getattr(_local, "hog", None)
    if cache is None:
        cache = _local.hog = {}
    key = (p["size"], p["block"], p["stride"], p["cell"], p["bins"])
    hog = cache.get(key)
    if hog is None:
        import cv2

        hog = cv2.HOGDescriptor(
            (p["size"], p["size"]),
            (p["block"], p["block"]),
            (p["stride"], p["stride"]),
            (p["cell"], p["cell"]),
            p["bins"],
        )
        cache[key] = hog
    return hog


def _hog(gray: Image, p: dict[str, int]) -> Float32Array:
    """The raw (not normalised) HoG vector of a gray image."""
    size = p["size"]
    if gray.shape != (size, size):
        import cv2

        gray = cv2.resize(gray, (size, size), interpolation=cv2.INTER_AREA)
    # compute() needs a contiguous buffer; a channel slice of a BGR array is not one.
    vector = _hog_object(p).compute(np.ascontiguousarray(gray))
    return np.asarray(vector, dtype=np.float32).reshape(-1)


def _patchnorm(gray: Image, p: dict[str, int]) -> Float32Array:
    """The raw (not normalised) patch-normalised thumbnail of a gray image."""
    width, height, patch = p["width"], p["height"], p["patch"]
    if gray.shape != (height, width):
        import cv2

        gray = cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA)
    # (rows of patches, patch row, cols of patches, patch col): statistics over axes 1 and 3.
    blocks = gray.astype(np.float32).reshape(height // patch, patch, width // patch, patch)
    mean = blocks.mean(axis=(1, 3), keepdims=True)
    std = blocks.std(axis=(1, 3), keepdims=True)
    # A flat patch (std ~ 0; 8-bit quantisation makes "flat" mean < ~0.5 grey levels) has no
    # structure to normalise; dividing would amplify rounding noise into a full-scale pattern.
    flat = std < 0.5
    normalised = np.where(flat, 0.0, (blocks - mean) / np.where(flat, 1.0, std))
    return np.asarray(normalised.reshape(-1), dtype=np.float32)
