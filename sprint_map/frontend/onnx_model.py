"""Learned global descriptors: a user's ONNX model run on the CPU with onnxruntime.

The ``[onnx]`` extra; onnxruntime is imported only when a model is loaded. A model is described
by a small *model card* (JSON), shipped beside it (``model.card.json`` for ``model.onnx``) or
given with ``--model-card``::

    {"input_size": [224, 224], "channels": "rgb", "mean": [0.485, 0.456, 0.406],
     "std": [0.229, 0.224, 0.225], "normalize": "l2"}

``input_size`` is ``[height, width]``; ``channels`` ``rgb``, ``bgr`` or ``gray`` (the order the
model wants); ``mean``/``std`` per channel on 0-1 pixel values; ``normalize`` ``l2`` or
``none``. Without a card: the model's fixed input size, RGB, ImageNet mean/std, ``l2``. The
descriptor dimension is read from the model (one dummy batch of two images is run when the map
is created): its output must be one vector per image, ``(N, D)`` (trailing singleton axes are
dropped); a model of a fixed batch size (often 1) is run that many images at a time. An
``input_size`` side beyond :data:`MAX_INPUT_SIDE` is refused.

A model's identity is the digest of every file it loads: the map stores the card, the
dimension, the model's path, its SHA-256 (``digest``) and, for a model saved with external
weights (``model.onnx`` + ``model.onnx.data``), the SHA-256 of each such file
(``external_data``, ``{location: sha256}``, read from the graph with the ``onnx`` package). A
model or weights file at that path with another digest is refused when the map loads it. A map
made before external weights were recorded has ``digest`` only: it opens and describes as
before, its ``.onnx`` file checked, and ``SprintMap.open_source`` warns that the weights files
(:func:`unverified_files`) are not.

The model's raw output is checked before it is normalised: NaN, Inf or a value beyond
``MAX_DESCRIPTOR_VALUE`` (1e15, an overflow) is an ``InvalidDescriptorError`` naming the model
and the frame; a normalisation never hides it as a zero row.

Pre-processing per image: resize to ``input_size`` (``INTER_AREA`` when shrinking, else
``INTER_LINEAR``), convert to the card's channels, scale to 0-1, subtract ``mean``, divide by
``std``, NCHW float32. Frames are described in batches (the sources' chunks, up to 32): decoding
and pre-processing run in the sources' worker threads while one ``session.run`` at a time uses
every core (onnxruntime's intra-op threads: all cores by default). Cost per frame: the model's
FLOPs plus O(pixels) pre-processing.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.errors import ConfigError, InputError
from sprint_map.util.arrays import Descriptors, Image
from sprint_map.util.validation import check_described

__all__ = ["CARD_KEYS", "IMAGENET_MEAN", "IMAGENET_STD", "INSTALL_HINT", "MAX_INPUT_SIDE",
           "card_path_for", "check_params", "describe_images", "external_data", "file_digest",
           "onnx_params", "unverified_files"]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CARD_KEYS = ("input_size", "channels", "mean", "std", "normalize")
PARAM_KEYS = (*CARD_KEYS, "model", "digest", "dim", "input_name")
#: Parameters a map made before them lacks: ``external_data``, ``{location: sha256}`` of each
#: file the model loads beside ``model`` (absent: none, or a map made before it was recorded).
OPTIONAL_KEYS = ("external_data",)
#: The largest ``input_size`` side (pixels): one 4096 x 4096 RGB input is 201 MB of float32.
MAX_INPUT_SIDE = 4096
#: Bytes of model input per ``session.run`` (fewer images per batch for large inputs).
MAX_BATCH_BYTES = 256 << 20
CHANNELS = ("rgb", "bgr", "gray")
NORMALIZE = ("l2", "none")
INSTALL_HINT = 'ONNX descriptors need the onnx extra: pip install "sprint-map[onnx]"'
#: Images per ``session.run``: the sources hand over chunks of up to 32 frames.
MAX_BATCH = 32

_sessions: dict[tuple[str, str, int, int, int], Any] = {}
_sessions_lock = threading.Lock()
_run_lock = threading.Lock()


def file_digest(path: Path) -> str:
    """SHA-256 of a file, hex. O(file size)."""
    h = hashlib.sha256()
    try:
        with path.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise InputError(f"{path}: cannot read model ({exc.strerror or exc})") from exc
    return h.hexdigest()


def card_path_for(model: Path) -> Path | None:
    """The card shipped beside ``model``: ``<stem>.card.json``, else None."""
    card = model.with_name(model.stem + ".card.json")
    return card if card.is_file() else None


def _number_list(value: Any, what: str, n: int | None = None) -> list[float]:
    if (not isinstance(value, Sequence) or isinstance(value, str) or not value
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value)):
        raise ConfigError(f"{what} must be a list of numbers, got {value!r}")
    out = [float(v) for v in value]
    if not all(math.isfinite(v) for v in out) or (n is not None and len(out) != n):
        raise ConfigError(f"{what} must be {n} finite numbers, got {value!r}")
    return out


def check_params(params: Mapping[str, Any]) -> dict[str, Any]:
    """The complete, validated parameters of an ``onnx`` descriptor (as a map stores them).
    Pure validation: loads nothing. O(1).

    Raises
    ------
    ConfigError
        A missing or unknown key, or a value of the wrong kind.
    """
    unknown = sorted(set(params) - set(PARAM_KEYS) - set(OPTIONAL_KEYS))
    missing = [k for k in PARAM_KEYS if k not in params]
    if unknown or missing:
        raise ConfigError("onnx descriptor: " + (f"unknown parameter(s) {', '.join(unknown)}"
                          if unknown else f"missing parameter(s) {', '.join(missing)}"))
    size = params["input_size"]
    if (not isinstance(size, Sequence) or isinstance(size, str) or len(size) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in size)):
        raise ConfigError(f"input_size must be [height, width] in pixels, got {size!r}")
    if max(size) > MAX_INPUT_SIDE:
        raise ConfigError(f"input_size {list(size)} is too large: at most {MAX_INPUT_SIDE} "
                          "pixels a side")
    channels = params["channels"]
    if channels not in CHANNELS:
        raise ConfigError(f"channels must be one of {', '.join(CHANNELS)}, got {channels!r}")
    n = 1 if channels == "gray" else 3
    mean = _number_list(params["mean"], "mean", n)
    std = _number_list(params["std"], "std", n)
    if any(s <= 0 for s in std):
        raise ConfigError(f"std must be > 0, got {params['std']!r}")
    if params["normalize"] not in NORMALIZE:
        raise ConfigError(f"normalize must be l2 or none, got {params['normalize']!r}")
    dim = params["dim"]
    if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
        raise ConfigError(f"onnx descriptor dim must be a positive integer, got {dim!r}")
    for key in ("model", "digest", "input_name"):
        if not isinstance(params[key], str) or not params[key]:
            raise ConfigError(f"onnx descriptor {key} must be a non-empty string")
    out = {"model": params["model"], "digest": params["digest"],
           "input_name": params["input_name"], "input_size": [int(v) for v in size],
           "channels": channels, "mean": mean, "std": std, "normalize": params["normalize"],
           "dim": dim}
    if "external_data" in params:
        files = params["external_data"]
        if (not isinstance(files, Mapping) or not files
                or not all(isinstance(k, str) and k and isinstance(v, str) and len(v) == 64
                           for k, v in files.items())):
            raise ConfigError("onnx descriptor external_data must map each file the model "
                              "loads to its sha256")
        out["external_data"] = {k: files[k] for k in sorted(files)}
    return out


def _ort() -> Any:
    try:
        import onnxruntime
    except ImportError:
        raise InputError(INSTALL_HINT) from None
    return onnxruntime


def _new_session(path: Path) -> Any:
    ort = _ort()
    options = ort.SessionOptions()
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for a bad graph
        raise InputError(f"{path}: cannot load ONNX model ({_first_line(exc)})") from None


def external_data(path: Path) -> list[str]:
    """The files the model ``path`` loads its weights from besides itself (ONNX external
    data: ``location`` of every tensor stored outside, in its graphs, subgraphs and
    attributes), relative to its folder, sorted. Reads the graph without the weights
    (the ``onnx`` package of the extra). O(model file).

    Raises
    ------
    InputError
        The ``onnx`` package missing, or a file that is not an ONNX model.
    """
    try:
        import onnx
    except ImportError:
        raise InputError(INSTALL_HINT) from None
    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as exc:  # protobuf's DecodeError, onnx's own errors
        raise InputError(f"{path}: cannot load ONNX model ({_first_line(exc)})") from None
    found: set[str] = set()

    def tensors(tensor_list: Any) -> None:
        for tensor in tensor_list:
            if tensor.data_location == onnx.TensorProto.EXTERNAL:
                found.update(e.value for e in tensor.external_data if e.key == "location")

    def graph(g: Any) -> None:
        tensors(g.initializer)
        for sparse in g.sparse_initializer:
            tensors([sparse.values, sparse.indices])
        for node in g.node:
            for attr in node.attribute:
                tensors([attr.t] if attr.HasField("t") else [])
                tensors(attr.tensors)
                for sub in ([attr.g] if attr.HasField("g") else []) + list(attr.graphs):
                    graph(sub)

    graph(model.graph)
    for function in model.functions:
        for node in function.node:
            for attr in node.attribute:
                tensors([attr.t] if attr.HasField("t") else [])
    return sorted(found)


def _external_digests(path: Path, files: Sequence[str]) -> dict[str, str]:
    """SHA-256 of each of the model's external data ``files``. O(their size)."""
    out = {}
    for name in files:
        data = path.parent / name
        if not data.is_file():
            raise InputError(f"{path}: the model's weights file {name!r} is missing (ONNX "
                             f"external data, expected at {data})")
        out[name] = file_digest(data)
    return out


def unverified_files(params: Mapping[str, Any]) -> list[str]:
    """The external data files the map's model loads that the map holds no digest of: a map
    made before they were recorded (its digest covers the ``.onnx`` file only). Empty for
    every map made since, and for a model without external data. O(model file)."""
    if "external_data" in params:
        return []
    path = Path(params["model"])
    return external_data(path) if path.is_file() else []


def _first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:240]


def _read_card(card: Path) -> dict[str, Any]:
    try:
        data = json.loads(card.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{card}: cannot read model card ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(f"{card}: a model card is a JSON object")
    unknown = sorted(set(data) - set(CARD_KEYS) - {"name", "source", "license", "notes"})
    if unknown:
        raise InputError(f"{card}: unknown model-card key(s) {', '.join(unknown)}; expected "
                         f"{', '.join(CARD_KEYS)}")
    return data


def onnx_params(model: str | Path, card: str | Path | None = None) -> dict[str, Any]:
    """Load ``model``, check it against its card, and return the descriptor parameters a map
    stores (:func:`check_params`). O(one batch of two images through the model).

    Raises
    ------
    InputError
        onnxruntime missing; an unreadable model or card; a card that disagrees with the
        model (input size, channel count); no card and a model without a fixed input size;
        a model whose output is not one vector per image.
    """
    path = Path(model).resolve()
    if not path.is_file():
        raise InputError(f"{path}: no such model file")
    card_file = Path(card) if card is not None else card_path_for(path)
    data = _read_card(card_file) if card_file is not None else {}
    label = str(card_file) if card_file is not None else str(path)
    session = _new_session(path)
    inputs = session.get_inputs()
    if len(inputs) != 1:
        raise InputError(f"{path}: the model has {len(inputs)} inputs; expected one image "
                         "batch (N, C, H, W)")
    shape = list(inputs[0].shape)
    if len(shape) != 4:
        raise InputError(f"{path}: the model's input has shape {shape}; expected (N, C, H, W)")
    if inputs[0].type != "tensor(float)":
        raise InputError(f"{path}: the model's input is a {inputs[0].type}; expected a float32 "
                         "image batch (N, C, H, W)")
    fixed = [v if isinstance(v, int) and v > 0 else None for v in shape]
    channels = data.get("channels", "rgb")
    want_c = 1 if channels == "gray" else 3
    if fixed[1] is not None and fixed[1] != want_c:
        raise InputError(f"{label}: channels {channels!r} give {want_c} channel(s), the model "
                         f"takes {fixed[1]}")
    if "input_size" in data:
        size = data["input_size"]
        if (isinstance(size, list) and len(size) == 2 and
                any(f is not None and f != s for f, s in zip(fixed[2:], size, strict=True))):
            raise InputError(f"{label}: input_size {size} but the model takes "
                             f"{shape[2]}x{shape[3]} images")
    elif fixed[2] is None or fixed[3] is None:
        raise InputError(f"{path}: the model's input size is not fixed ({shape}); give a model "
                         "card with input_size")
    else:
        size = [fixed[2], fixed[3]]
    rgb = channels != "gray"
    given = {
        "model": str(path), "digest": file_digest(path), "input_name": inputs[0].name,
        "input_size": size, "channels": channels,
        "mean": data.get("mean", list(IMAGENET_MEAN) if rgb else [IMAGENET_MEAN[0]]),
        "std": data.get("std", list(IMAGENET_STD) if rgb else [IMAGENET_STD[0]]),
        "normalize": data.get("normalize", "l2"), "dim": 1}
    try:
        params = check_params(given)
    except ConfigError as exc:
        raise InputError(f"{label}: {exc}") from None
    files = external_data(path)
    if files:
        params["external_data"] = _external_digests(path, files)
    # a batch of two tells one vector per image from one per batch; a fixed batch is its size
    probe = np.zeros((_batch_size(session, params) if fixed[0] is not None else 2, want_c,
                      params["input_size"][0], params["input_size"][1]), np.float32)
    out = _run(session, params, probe, str(path))
    params["dim"] = int(out.shape[1])
    return params


def _batch_size(session: Any, params: Mapping[str, Any]) -> int:
    """Images per ``session.run``: the model's fixed batch (1: frame by frame), else up to
    :data:`MAX_BATCH` within :data:`MAX_BATCH_BYTES` of input. O(1)."""
    batch = session.get_inputs()[0].shape[0]
    if isinstance(batch, int) and batch > 0:
        return int(batch)
    height, width = params["input_size"]
    image_bytes = 4 * (1 if params["channels"] == "gray" else 3) * int(height) * int(width)
    return max(1, min(MAX_BATCH, MAX_BATCH_BYTES // image_bytes))


def _run(session: Any, params: Mapping[str, Any], batch: np.ndarray, label: str) -> np.ndarray:
    """One ``session.run``; the output as ``(N, D)`` float32 or InputError. O(model)."""
    try:
        with _run_lock:  # one batch at a time, each on every core
            outputs = session.run(None, {params["input_name"]: batch})
    except MemoryError:
        raise InputError(f"{label}: out of memory running the model on {len(batch)} "
                         f"image(s) of {list(batch.shape[1:])}") from None
    except Exception:  # onnxruntime's own exception types, and messages
        raise InputError(f"{label}: the model cannot run on a batch of {len(batch)} image(s) "
                         f"of shape {list(batch.shape[1:])} (C, H, W) float32: its graph "
                         "refuses it (a batch axis or a size it does not take?)") from None
    out = np.asarray(outputs[0])
    while out.ndim > 2 and out.shape[-1] == 1:
        out = out[..., 0]
    if out.ndim != 2 or out.shape[0] != len(batch):
        raise InputError(f"{label}: the model's output has shape {list(np.shape(outputs[0]))} "
                         f"for {len(batch)} images; expected one vector per image (N, D)")
    return out.astype(np.float32, copy=False)


def _session(params: Mapping[str, Any]) -> Any:
    """The process's session of the map's model, loaded after checking its digest; loaded
    again (and checked again) when the file changed since (size, mtime, inode). O(1) when
    cached, else O(model file)."""
    path = Path(params["model"])
    files = params.get("external_data", {})
    try:
        st = path.stat()
    except OSError:
        raise InputError(f"{path}: the map's ONNX model is missing (the map was made with it; "
                         "put it back at this path)") from None
    stats: list[Any] = [params["model"], params["digest"], st.st_size, st.st_mtime_ns,
                        st.st_ino]
    for name in files:
        try:
            data = (path.parent / name).stat()
        except OSError:
            raise InputError(f"{path}: the map's model's weights file {name!r} is missing (the "
                             "map was made with it; put it back beside the model)") from None
        stats += [name, data.st_size, data.st_mtime_ns, data.st_ino]
    key = tuple(stats)
    with _sessions_lock:
        session = _sessions.get(key)
        if session is None:
            digest = file_digest(path)
            if digest != params["digest"]:
                raise InputError(f"{path}: a different model (sha256 {digest[:12]}...) than the "
                                 f"map was made with ({params['digest'][:12]}...): refused")
            for name, want in _external_digests(path, list(files)).items():
                if want != files[name]:
                    raise InputError(f"{path}: different weights in {name!r} (sha256 "
                                     f"{want[:12]}...) than the map was made with "
                                     f"({files[name][:12]}...): refused")
            session = _sessions[key] = _new_session(path)
    return session


def preprocess(image: Image, params: Mapping[str, Any]) -> np.ndarray:
    """One gray/BGR/BGRA uint8 image as the model's ``(C, H, W)`` float32 input. O(pixels)."""
    import cv2

    height, width = params["input_size"]
    if image.dtype == np.uint16:
        image = (np.asarray(image, dtype=np.uint16) >> 8).astype(np.uint8)
    if params["channels"] == "gray":
        pixels = image if image.ndim == 2 else image[:, :, 0] if image.shape[2] == 1 else (
            cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3
                         else cv2.COLOR_BGRA2GRAY))
    else:
        if image.ndim == 2:
            pixels = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        elif image.shape[2] == 4:
            pixels = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        else:
            pixels = image
        if params["channels"] == "rgb":
            pixels = cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB)
    shrink = pixels.shape[0] > height or pixels.shape[1] > width
    if pixels.shape[:2] != (height, width):
        pixels = cv2.resize(pixels, (width, height),
                            interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    data = pixels.astype(np.float32).reshape(height, width, -1) / np.float32(255.0)
    mean, std = np.asarray(params["mean"], np.float32), np.asarray(params["std"], np.float32)
    return np.ascontiguousarray(((data - mean) / std).transpose(2, 0, 1), dtype=np.float32)


def describe_images(params: Mapping[str, Any], images: Sequence[Image]) -> Descriptors:
    """Descriptors of ``images`` (batches of :func:`_batch_size`: one at a time for a model
    of a fixed batch of 1; a fixed batch of more is padded), L2-normalised when the card says
    so (a zero output stays zero). The model's raw output is checked first: NaN, Inf or a
    value beyond :data:`~sprint_map.util.validation.MAX_DESCRIPTOR_VALUE` is an
    :class:`InvalidDescriptorError` naming the model and the image (the frame source names
    its frame), never a row normalised to zeros. O(images * model)."""
    if not len(images):
        return np.empty((0, params["dim"]), dtype=np.float32)
    session = _session(params)
    step = _batch_size(session, params)
    fixed = session.get_inputs()[0].shape[0] == step
    parts = []
    for start in range(0, len(images), step):
        batch = np.stack([preprocess(image, params) for image in images[start:start + step]])
        n = len(batch)
        if fixed and n < step:  # the model takes exactly `step` images: pad, drop the rest
            batch = np.concatenate([batch, np.zeros((step - n, *batch.shape[1:]), np.float32)])
        out = _run(session, params, batch, params["model"])[:n]
        if out.shape[1] != params["dim"]:
            raise InputError(f"{params['model']}: the model gives {out.shape[1]} dimensions, "
                             f"the map holds {params['dim']}")
        check_described(out, f"the model {params['model']}", start, len(images))
        parts.append(out)
    rows = np.concatenate(parts) if len(parts) > 1 else parts[0]
    if params["normalize"] == "l2":  # in float64: no norm of a checked row overflows
        wide = rows.astype(np.float64)
        norms = np.linalg.norm(wide, axis=1, keepdims=True)
        rows = np.where(norms > 0, wide / np.where(norms > 0, norms, 1.0), 0.0)
    return np.ascontiguousarray(rows, dtype=np.float32)
