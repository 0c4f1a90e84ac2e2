"""The one image path: the same image files through every entry point that turns pixels into
descriptor rows (ingest, localize, eval, the service's image frames, the thumbnail variant)
give the same rows, on HoG and ONNX (colour and gray) maps, for gray and colour images."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.evaluation.runner import describe_with_thumbnails
from sprint_map.frontend.dataset import Dataset
from sprint_map.frontend.image_path import decode_for
from sprint_map.map import SprintMap
from tests.helpers.serve import run_service

N_FRAMES = 12


def _write_drive(folder: Path, rng: np.random.Generator, colour: bool) -> list[Path]:
    """A slowly panning smooth texture, colour (hue varies along the drive) or gray PNGs."""
    folder.mkdir(parents=True)
    world = cv2.GaussianBlur(rng.uniform(0, 255, (48, 64 + 4 * N_FRAMES, 3)).astype(np.float32),
                             (0, 0), 2)
    paths = []
    for i in range(N_FRAMES):
        frame = np.clip(world[:, 4 * i: 4 * i + 64], 0, 255).astype(np.uint8)
        image = frame if colour else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        paths.append(folder / f"{i:03d}.png")
        cv2.imwrite(str(paths[-1]), image)
    return paths


def _init_args(kind: str, tmp_path: Path) -> list[str]:
    if kind == "hog":
        return ["--descriptor", "hog"]
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from tests.helpers.onnx_graphs import projection_model

    gray = kind == "onnx-gray"
    model = projection_model(tmp_path / "m.onnx", size=(16, 16), channels=1 if gray else 3,
                             dim=24)
    card = {"input_size": [16, 16], "channels": "gray" if gray else "rgb",
            "mean": [0.5] if gray else [0.485, 0.456, 0.406],
            "std": [0.25] if gray else [0.229, 0.224, 0.225]}
    (tmp_path / "card.json").write_text(json.dumps(card))
    return ["--descriptor", "onnx", "--model", str(model), "--model-card",
            str(tmp_path / "card.json")]


def _cli(*args: Any) -> Any:
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result


@pytest.mark.parametrize("colour", [True, False], ids=["colour-images", "gray-images"])
@pytest.mark.parametrize("kind", ["hog", "onnx-rgb", "onnx-gray"])
def test_every_entry_point_gives_the_same_rows(tmp_path, rng, kind, colour):
    drive = tmp_path / "data" / "first"
    paths = _write_drive(drive, rng, colour)
    map_path = tmp_path / "map"
    _cli("init", map_path, *_init_args(kind, tmp_path))
    _cli("ingest", map_path, drive, "--name", "first")
    _cli("ingest", map_path, drive, "--name", "thumbs", "--thumbnails", "--no-merge")

    with SprintMap.open(map_path, readonly=True) as m:
        spec = m.config.descriptor_spec()
        assert spec is not None
        # The reference: each file decoded as the spec reads it, described alone.
        want = np.stack([spec.describe(decode_for(spec, p.read_bytes(), str(p)))
                         for p in paths]).astype(np.float32)
        rows = {"ingest": m.descriptors(0), "ingest --thumbnails": m.descriptors(1),
                "localize": m.open_source(drive).read_all(),
                "localize --thumbnails": m.open_source(drive, thumbnails=True).read_all()}
        traversal = Dataset.open(tmp_path / "data", {"alignment": "frame"})["first"]
        rows["eval"] = describe_with_thumbnails(m, traversal, 1)[0]
    localized = json.loads(_cli("localize", map_path, drive, "--json", "-q").output)

    async def body(service: Any, client: httpx.AsyncClient) -> tuple[list[Any], dict[str, Any]]:
        sid = (await client.post("/v1/sessions")).json()["session_id"]
        answers = []
        for path in paths:
            response = await client.post(f"/v1/sessions/{sid}/frames", content=path.read_bytes(),
                                         headers={"content-type": "image/png"})
            assert response.status_code == 200, response.text
            answers.append(response.json())
        return answers, (await client.post(f"/v1/sessions/{sid}/commit")).json()

    served, committed = run_service(map_path, body)
    with SprintMap.open(map_path, readonly=True) as m:
        rows["serve"] = m.descriptors(committed["seq_id"])
    for entry, got in rows.items():
        assert got.shape == want.shape, entry
        np.testing.assert_allclose(got, want, atol=1e-6, rtol=0, err_msg=entry)
    # Same rows, same answers: the service answers each frame as localize does.
    assert [a["image_id"] for a in served] == [d["image_id"] for d in localized["decisions"]]
