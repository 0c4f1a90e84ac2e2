"""A map keeps one frame of positions (issue 52): latitude/longitude (projected into one UTM
zone) or planar x, y, and refuses the other; GeoJSON gives latitude/longitude back as given."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.map import SprintMap


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture
def folder(tmp_path):
    rng = np.random.default_rng(3)
    path = tmp_path / "drive"
    path.mkdir()
    for i in range(6):
        cv2.imwrite(str(path / f"{i:03d}.png"), rng.integers(0, 256, (48, 64, 3), np.uint8))
    return path


def csv(path, header, rows):
    path.write_text(header + "\n" + "".join(f"{i},{a!r},{b!r}\n" for i, (a, b) in
                                            enumerate(rows)))
    return path


def latlon(tmp_path, name="ll.csv", lat=59.9, lon=10.7):
    return csv(tmp_path / name, "frame,lat,lon", [(lat + i * 1e-4, lon + i * 1e-4)
                                                  for i in range(6)])


def planar(tmp_path, name="xy.csv"):
    return csv(tmp_path / name, "frame,x,y", [(10.0 * i, 5.0) for i in range(6)])


def state(path):
    with SprintMap.open(path, readonly=True) as m:
        return m.stats()["sequences"], m.store.geo_frame(), m.store.has_positions()


def refused(result, message):
    assert result.exit_code == InputError.exit_code, result.output
    assert result.output.startswith("Error: ") and result.output.count("\n") == 1
    assert message in result.output


@pytest.mark.parametrize("first", ["latlon", "planar"])
def test_a_map_refuses_positions_of_the_other_frame(tmp_path, folder, first):
    assert _cli("init", tmp_path / "m").exit_code == 0
    make = {"latlon": latlon, "planar": planar}
    other = "planar" if first == "latlon" else "latlon"
    done = _cli("ingest", tmp_path / "m", folder, "--positions", make[first](tmp_path),
                "--name", "a")
    assert done.exit_code == 0, done.output
    before = state(tmp_path / "m")
    result = _cli("ingest", tmp_path / "m", folder, "--positions", make[other](tmp_path),
                  "--name", "b")
    refused(result, "planar x, y positions given to a map of latitude/longitude (kept in UTM "
            "zone 32N)" if first == "latlon" else
            "latitude/longitude positions given to a map of planar x, y positions")
    assert state(tmp_path / "m") == before
    again = _cli("ingest", tmp_path / "m", folder, "--positions", make[first](tmp_path),
                 "--name", "b")
    assert again.exit_code == 0, again.output


def test_one_ingest_of_both_frames_changes_nothing(tmp_path, folder):
    assert _cli("init", tmp_path / "m").exit_code == 0
    second = tmp_path / "second"
    second.mkdir()
    for p in folder.iterdir():
        (second / p.name).write_bytes(p.read_bytes())
    latlon(folder, "positions.csv")
    planar(second, "positions.csv")
    result = _cli("ingest", tmp_path / "m", folder, second)
    refused(result, "positions mix latitude/longitude and planar x, y")
    assert state(tmp_path / "m") == (0, None, False)


def test_the_python_api_refuses_the_other_frame(tmp_path, folder):
    from sprint_map.frontend.positions import read_positions

    with SprintMap.create(tmp_path / "m", MapConfig.for_descriptor("hog")) as m:
        src = m.open_source(folder)
        rows = m.metric_positions(read_positions(planar(tmp_path), 6))
        m.add_sequence(src.read_all(), name="a", positions=rows)
        with pytest.raises(InputError, match="latitude/longitude positions given to a map of "
                                             "planar"):
            m.metric_positions(read_positions(latlon(tmp_path), 6))
        assert m.store.geo_frame() is None


def test_geojson_gives_latitude_longitude_back_as_given(tmp_path, folder):
    """Three drives into one map: in its zone, across the antimeridian and 90 degrees of
    longitude away; each drive's fixes come back as the CSV gave them (to 1e-9 degrees, a
    tenth of a millimetre: the projection's round trip, not a series' error)."""
    assert _cli("init", tmp_path / "m").exit_code == 0
    given = {"oslo": latlon(tmp_path, "a.csv"),
             "fiji": csv(tmp_path / "b.csv", "frame,lat,lon",
                         [(-16.8, 179.9997), (-16.8, 179.9998), (-16.8, 179.9999),
                          (-16.8, -180.0 + 1e-4), (-16.8, -180.0 + 2e-4), (-16.8, -180 + 3e-4)]),
             "far": latlon(tmp_path, "c.csv", lat=64.0, lon=100.0)}
    for name, path in given.items():
        done = _cli("ingest", tmp_path / "m", folder, "--positions", path, "--name", name)
        assert done.exit_code == 0, done.output
    out = tmp_path / "g.json"
    assert _cli("export", tmp_path / "m", "--geojson", out).exit_code == 0
    doc = json.loads(out.read_text())
    assert doc["sprint_map"]["crs"] == "EPSG:4326"
    drives = {f["properties"]["name"]: np.array(f["geometry"]["coordinates"])
              for f in doc["features"] if f["properties"]["kind"] == "drive"}
    for name, path in given.items():
        rows = np.loadtxt(path, delimiter=",", skiprows=1)[:, 1:]
        lonlat = drives[name]
        np.testing.assert_allclose(lonlat[:, 1], rows[:, 0], atol=1e-9, rtol=0)
        np.testing.assert_allclose((lonlat[:, 0] - rows[:, 1] + 180) % 360 - 180, 0,
                                   atol=1e-9)
        assert (np.abs(lonlat[:, 0]) <= 180).all()


def test_ray_ingest_refuses_a_drive_whose_positions_it_would_drop(tmp_path, folder):
    """The farm stores descriptors only: a drive folder's positions.csv (lat/lon here) would
    be lost without a word, and its GeoJSON would show nothing."""
    assert _cli("init", tmp_path / "m").exit_code == 0
    latlon(folder, "positions.csv")
    result = _cli("ingest", tmp_path / "m", folder, "--ray", "local")
    refused(result, "positions.csv) are not carried by --ray")
    assert state(tmp_path / "m") == (0, None, False)


def test_a_data_set_of_both_frames_is_refused(tmp_path):
    from sprint_map.frontend.dataset import Dataset

    for name, write in (("a", latlon), ("b", planar)):
        folder = tmp_path / "set" / name
        folder.mkdir(parents=True)
        np.save(folder / "descriptors.npy", np.eye(6, 8, dtype=np.float32))
        write(folder, "positions.csv")
    data = Dataset.open(tmp_path / "set")
    with pytest.raises(InputError, match="traversal 'a' has latitude/longitude positions and "
                                         "'b' planar x, y"):
        data.geo_frame()
