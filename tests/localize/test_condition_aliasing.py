"""A map that holds a query's season elsewhere still answers it by place (drive centring).

On a generated world whose drives carry a season (a shared direction in every descriptor of
the drive, :mod:`sprint_map.synth.latent`), a map built drive after drive answers the later
drives; centred (the default) it must answer them clearly better than the same map storing
descriptors as given, and merge nothing wrong.
"""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.frontend.centring import Centring
from sprint_map.map import SprintMap
from tools.condition_worlds import latent_world


def answer_stream(tmp_path, world, centring: Centring) -> tuple[float, int, int]:
    """Recall@1 of each later drive's smoothed answers (frames with a true match), and the
    merged decisions (right, wrong) of the whole stream."""
    right = total = merged_ok = merged_bad = 0
    with SprintMap.create(tmp_path / centring.mode, world.config.replace(
            centring=centring.__dict__)) as m:
        names: dict[int, str] = {}
        for i, drive in enumerate(world.drives):
            if i >= 2:
                decisions, _ = m.localize(drive.rows, smooth=True)
                seqs = [s.name for s in m.sequences()]
                has = world.gt.has_match(drive.name, np.arange(len(drive.rows)), seqs)
                for d in decisions:
                    if has[d.frame]:
                        total += 1
                        right += bool(d.best is not None and world.gt.correct(
                            drive.name, d.frame, names[d.best[0]], d.best[1]))
            result = m.ingest(drive.rows, name=drive.name)
            names[result.added.sequence.seq_id] = drive.name
            for d, ok in zip(result.decisions, result.merged, strict=False):
                if ok:
                    good = world.gt.correct(drive.name, d.frame, names[d.seq_id], d.image_id)
                    merged_ok += bool(good)
                    merged_bad += not good
    return right / max(total, 1), merged_ok, merged_bad


@pytest.mark.slow
def test_centring_answers_by_place_where_raw_descriptors_alias(tmp_path):
    world = latent_world(0, 8, 80, None)
    centred, ok_c, bad_c = answer_stream(tmp_path, world, Centring("drive"))
    raw, _, _ = answer_stream(tmp_path, world, Centring("none"))
    assert centred > raw + 0.15, (centred, raw)
    assert centred > 0.85 and ok_c > 0 and bad_c <= ok_c // 50
