"""DescriptorSpec: the paper's HoG and the patch-normalised descriptor."""

from __future__ import annotations

import pickle
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sprint_map.errors import ConfigError
from sprint_map.frontend.descriptors import DescriptorSpec, to_gray


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def textured(rng: np.random.Generator, h: int = 120, w: int = 160, channels: int = 3) -> np.ndarray:
    """A random blurred image with real gradients (pure noise would be too easy a case)."""
    shape = (h, w, channels) if channels > 1 else (h, w)
    noise = rng.integers(0, 256, size=shape, dtype=np.uint8)
    return cv2.GaussianBlur(noise, (0, 0), 2.0)


@pytest.mark.parametrize(
    ("kind", "params", "dim"),
    [
        ("hog", {}, 1764),
        ("hog", {"size": 32}, 324),
        ("patchnorm", {}, 512),
        ("patchnorm", {"width": 64, "height": 32, "patch": 8}, 2048),
    ],
)
def test_dim_dtype_and_unit_norm(rng, kind, params, dim):
    spec = DescriptorSpec(kind, params)
    assert spec.dim == dim
    vector = spec.describe(textured(rng))
    assert vector.shape == (dim,)
    assert vector.dtype == np.float32
    assert np.linalg.norm(vector) == pytest.approx(1.0, abs=1e-5)


def test_hog_is_the_papers_descriptor(rng):
    """Gray, 64x64 INTER_AREA, cv2.HOGDescriptor((64,64),(16,16),(8,8),(8,8),9), L2-normalised."""
    image = textured(rng, 480, 640)
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    small = cv2.resize(gray, (64, 64), interpolation=cv2.INTER_AREA)
    raw = cv2.HOGDescriptor((64, 64), (16, 16), (8, 8), (8, 8), 9).compute(small).ravel()
    expected = raw / np.linalg.norm(raw)
    np.testing.assert_allclose(
        DescriptorSpec("hog").describe(image), expected, rtol=1e-5, atol=1e-7
    )


@pytest.mark.parametrize("kind", ["hog", "patchnorm"])
def test_flat_image_gives_zero_vector_not_nan(kind):
    for value in (0, 128, 255):
        vector = DescriptorSpec(kind).describe(np.full((48, 64), value, np.uint8))
        assert np.isfinite(vector).all()
        assert not vector.any()


@pytest.mark.parametrize("kind", ["hog", "patchnorm"])
def test_gray_bgr_bgra_uint16_agree(rng, kind):
    spec = DescriptorSpec(kind)
    bgr = textured(rng)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    bgra = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
    expected = spec.describe(gray)
    np.testing.assert_array_equal(spec.describe(bgr), expected)
    np.testing.assert_array_equal(spec.describe(bgra), expected)
    np.testing.assert_array_equal(spec.describe(gray[:, :, None]), expected)
    np.testing.assert_array_equal(spec.describe(gray.astype(np.uint16) << 8), expected)


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((0, 10), np.uint8),
        np.zeros((10, 10, 2), np.uint8),
        np.zeros((10, 10), np.float32),
        np.zeros((2, 10, 10, 3), np.uint8),
    ],
    ids=["empty", "two-channels", "float", "4-d"],
)
def test_unsupported_arrays_are_refused(image):
    with pytest.raises(ValueError):
        to_gray(image)


def test_describe_batch(rng):
    spec = DescriptorSpec("hog")
    images = [textured(rng) for _ in range(3)]
    batch = spec.describe_batch(images)
    assert batch.shape == (3, 1764) and batch.dtype == np.float32
    np.testing.assert_array_equal(batch[1], spec.describe(images[1]))
    np.testing.assert_array_equal(spec.describe_batch(np.stack(images)), batch)
    assert spec.describe_batch([]).shape == (0, 1764)


@given(  # base 60-190 stays inside 0-255 under any of these (clipping is not affine)
    gains=st.lists(st.floats(0.4, 1.2), min_size=8, max_size=8),
    offsets=st.lists(st.integers(-10, 20), min_size=8, max_size=8),
)
@settings(max_examples=30, deadline=None)
def test_patchnorm_ignores_per_patch_brightness_and_contrast(gains, offsets):
    """Each patch is z-normalised, so an affine change per patch leaves the descriptor alone."""
    rng = np.random.default_rng(7)
    spec = DescriptorSpec("patchnorm", {"width": 16, "height": 8, "patch": 4})
    base = rng.uniform(60, 190, size=(8, 16))  # already at the descriptor's size: no resize
    changed = base.copy()
    for k in range(8):
        r, c = divmod(k, 4)
        block = changed[r * 4 : (r + 1) * 4, c * 4 : (c + 1) * 4]
        block[:] = block * gains[k] + offsets[k]
    a = spec.describe(np.clip(np.round(base), 0, 255).astype(np.uint8))
    b = spec.describe(np.clip(np.round(changed), 0, 255).astype(np.uint8))
    assert float(a @ b) > 0.97  # equal up to 8-bit rounding


def test_hog_tolerates_global_brightness_change(rng):
    spec = DescriptorSpec("hog")
    image = textured(rng).astype(np.float32)
    darker = np.clip(image * 0.6 + 10, 0, 255).astype(np.uint8)
    assert float(spec.describe(image.astype(np.uint8)) @ spec.describe(darker)) > 0.97


@pytest.mark.parametrize(
    ("kind", "params"),
    [
        ("sift", {}),
        ("hog", {"size": 60}),  # blocks of 16 at stride 8 do not tile 60
        ("hog", {"cell": 5}),
        ("hog", {"bins": 0}),
        ("hog", {"size": True}),
        ("hog", {"colour": 1}),
        ("patchnorm", {"width": 30}),
        ("patchnorm", {"patch": 2.0}),
    ],
)
def test_invalid_specs_are_config_errors(kind, params):
    with pytest.raises(ConfigError):
        DescriptorSpec(kind, params)


def test_spec_value_semantics_and_serialisation():
    spec = DescriptorSpec("patchnorm", {"width": 64, "height": 32, "patch": 8})
    assert spec == DescriptorSpec("patchnorm", {"patch": 8, "height": 32, "width": 64})
    assert DescriptorSpec("hog") == DescriptorSpec("hog", {"size": 64})  # defaults filled in
    assert hash(DescriptorSpec("hog")) == hash(DescriptorSpec("hog", {"bins": 9}))
    assert DescriptorSpec.from_dict(spec.to_dict()) == spec
    assert DescriptorSpec.parse(str(spec)) == spec
    assert DescriptorSpec.parse(" hog ") == DescriptorSpec("hog")
    assert pickle.loads(pickle.dumps(spec)) == spec
    assert len(pickle.dumps(DescriptorSpec("hog"))) < 400  # cheap to send to workers


@pytest.mark.parametrize("text", ["hog:size", "hog:size=big", "patchnorm:width=64,,height=x"])
def test_parse_rejects_malformed_options(text):
    with pytest.raises(ConfigError):
        DescriptorSpec.parse(text)


def test_from_dict_rejects_unknown_keys():
    with pytest.raises(ConfigError):
        DescriptorSpec.from_dict({"kind": "hog", "params": {}, "extra": 1})


def test_describe_is_thread_safe(rng):
    spec = DescriptorSpec("hog")
    images = [textured(rng) for _ in range(32)]
    serial = spec.describe_batch(images)
    with ThreadPoolExecutor(4) as pool:
        parallel = np.stack(list(pool.map(spec.describe, images)))
    np.testing.assert_array_equal(parallel, serial)


@pytest.mark.parametrize("kind", ["hog", "patchnorm"])
@pytest.mark.parametrize(("value", "why"), [(1e30, "beyond"), (np.inf, "infinite")])
def test_a_broken_raw_vector_is_refused_before_it_is_normalised(rng, monkeypatch, kind, value,
                                                                 why):
    """Whatever breaks the raw vector (a build of OpenCV, a parameter) is an error naming the
    image, not a row that the normalisation turns to zeros (1e30: its float32 norm is Inf)."""
    import sprint_map.frontend.descriptors as descriptors
    from sprint_map.errors import InvalidDescriptorError

    real = getattr(descriptors, f"_{kind}")

    def broken(gray, p):
        vector = real(gray, p).copy()
        if gray.mean() > 100:
            vector[3] = value
        return vector

    monkeypatch.setattr(descriptors, f"_{kind}", broken)
    frames = [rng.integers(0, 90, (48, 64), dtype=np.uint8) for _ in range(4)]
    frames[2] = np.full((48, 64), 200, np.uint8)
    frames[2][::2] = 255
    with pytest.raises(InvalidDescriptorError, match=rf"^{kind} gave no descriptor for image 2 "
                                                     rf"of 4 \(element 3 is .*{why}"):
        DescriptorSpec(kind).describe_batch(frames)
