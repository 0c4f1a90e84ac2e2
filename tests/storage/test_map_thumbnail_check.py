"""``check`` decodes every thumbnail (issue 29 item 14): a JPEG signature around garbage, or a
2 MB value with one, is a violation that ``check --repair`` drops (the drive's whole set)."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.frontend.thumbnails import make_thumbnail
from sprint_map.map import SprintMap
from sprint_map.storage.keys import THUMB_KEY
from sprint_map.storage.thumbnails import THUMBNAILS_DB


@pytest.mark.parametrize("value", [b"\xff\xd8\xff\xd9", b"\xff\xd8" + bytes(40) + b"\xff\xd9",
                                   b"\xff\xd8" + bytes(2 << 20) + b"\xff\xd9"])
def test_check_decodes_every_thumbnail(tmp_path, rng, value):
    path = tmp_path / "m.map"
    frames = [rng.integers(0, 256, (40, 60, 3), dtype=np.uint8) for _ in range(4)]
    with SprintMap.create(path, MapConfig(dim=8)) as m:
        m.add_sequence(rng.standard_normal((4, 8)).astype(np.float32), name="a",
                       thumbnails=[make_thumbnail(f) for f in frames])
        m.add_sequence(rng.standard_normal((4, 8)).astype(np.float32), name="b",
                       thumbnails=[make_thumbnail(f) for f in frames])
        m.store.env.write(lambda txn: txn.put(THUMB_KEY.pack(1, 2), value,
                                              db=m.store.env.db(THUMBNAILS_DB)))
    result = CliRunner().invoke(main, ["check", str(path)])
    assert result.exit_code == 1 and "sequence 1 image 2" in result.output, result.output
    fixed = CliRunner().invoke(main, ["check", str(path), "--repair"])
    assert fixed.exit_code == 0, fixed.output
    with SprintMap.open(path, readonly=True) as m:
        assert m.thumbnail_count(1) == 0 and m.thumbnail_count(0) == 4
        assert m.check().ok
