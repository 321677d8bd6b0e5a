import numpy as np
import pytest

from lunarloc.core.errors import FileFormatError, InputError
from lunarloc.io.maps import (
    AggregationConfig,
    LandmarkMap,
    aggregate_detections,
    is_traverse_csv,
    load_map,
    load_traverse,
    save_map,
)


def write_traverse(path, rows):
    lines = ["frame,x,y,z,detections,boulders"]
    for frame, xyz, boulders in rows:
        blist = "[" + ", ".join(f"({a}, {b}, {c})" for a, b, c in boulders) + "]"
        lines.append(f'{frame},{xyz[0]},{xyz[1]},{xyz[2]},{len(boulders)},"{blist}"')
    path.write_text("\n".join(lines) + "\n")
    return path


def test_landmark_map_validation():
    with pytest.raises(InputError, match="NaN"):
        LandmarkMap(np.array([[0, 0, 0], [np.nan, 1, 1.0]]))
    with pytest.raises(InputError, match="shape"):
        LandmarkMap(np.zeros((4, 2)))
    with pytest.raises(InputError, match="sizes"):
        LandmarkMap(np.zeros((3, 3)), sizes=[1, 2])
    assert len(LandmarkMap(np.zeros((0, 3)))) == 0


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_map_round_trip(tmp_path, rng, suffix):
    m = LandmarkMap(
        rng.normal(size=(12, 3)),
        sizes=rng.uniform(0.1, 1, 12),
        sightings=np.arange(12),
        frame="site",
    )
    p = save_map(m, tmp_path / f"m{suffix}")
    back = load_map(p)
    assert np.allclose(back.positions_xyz, m.positions_xyz, atol=1e-6)
    assert np.allclose(back.sizes, m.sizes, atol=1e-6)
    assert np.allclose(back.sightings, m.sightings)
    assert back.frame == "site"


def test_map_csv_errors_name_file_and_line(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("x,y,q\n1,2,3\n")
    with pytest.raises(FileFormatError, match=r"bad.csv:1: missing column 'z'"):
        load_map(p)
    p.write_text("x,y,z\n1,2,3\n1,2\n")
    with pytest.raises(FileFormatError, match=r"bad.csv:3: expected 3 fields"):
        load_map(p)
    p.write_text("x,y,z\n1,2,abc\n")
    with pytest.raises(FileFormatError, match=r"bad.csv:2"):
        load_map(p)
    p.write_text("x,y,z\n1,2,nan\n")
    with pytest.raises(FileFormatError, match=r"bad.csv:2: non-finite"):
        load_map(p)
    with pytest.raises(FileFormatError, match="no such file"):
        load_map(tmp_path / "missing.csv")
    (tmp_path / "m.txt").write_text("x")
    with pytest.raises(InputError, match="unknown map format"):
        save_map(LandmarkMap(np.zeros((1, 3))), tmp_path / "m.txt")


def test_traverse_loader(tmp_path):
    p = write_traverse(
        tmp_path / "t.csv", [(1, (0, 0, 0), []), (2, (0.1, 0, 0), [(1, 2, 3), (4.5, -5e-1, 6)])]
    )
    assert is_traverse_csv(p)
    t = load_traverse(p)
    assert t.frames.tolist() == [1, 2]
    assert np.allclose(t.detections_xyz, [[1, 2, 3], [4.5, -0.5, 6]])
    assert t.detection_frame.tolist() == [2, 2]
    assert np.isclose(t.path_length, 0.1)


@pytest.mark.parametrize(
    "body,match",
    [
        ('1,0,0,0,2,"[(1, 2, 3)]"', r"t.csv:2: detections says 2"),
        ('1,0,0,zero,0,"[]"', r"t.csv:2"),
        ('1,0,0,0,1,"(1, 2, 3)"', r"t.csv:2: boulders must be a list"),
        ("1,0,0,0", r"t.csv:2: expected 6 fields"),
        ('1,0,0,0,1,"[(1, 2, nan)]"', r"t.csv:2: non-finite"),
    ],
)
def test_traverse_malformed_rows(tmp_path, body, match):
    p = tmp_path / "t.csv"
    p.write_text("frame,x,y,z,detections,boulders\n" + body + "\n")
    with pytest.raises(FileFormatError, match=match):
        load_traverse(p)


def test_traverse_wrong_header_and_empty(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("frame,x,y\n1,2,3\n")
    with pytest.raises(FileFormatError, match="expected traverse columns"):
        load_traverse(p)
    p.write_text("")
    with pytest.raises(FileFormatError, match="empty"):
        load_traverse(p)
    p.write_text("frame,x,y,z,detections,boulders\n")
    with pytest.raises(FileFormatError, match="no data rows"):
        load_traverse(p)


def test_aggregation_one_landmark_per_rock(rng):
    rocks = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0.5], [5, 5, 1.0]])
    det, frames = [], []
    for f in range(10):
        det.append(rocks + rng.normal(0, 0.01, rocks.shape))
        frames.append(np.full(len(rocks), f))
    det.append(np.array([[10.0, 10.0, 0.0]]))  # a one-off false detection
    frames.append(np.array([3]))
    m = aggregate_detections(np.vstack(det), np.concatenate(frames), AggregationConfig())
    assert len(m) == 4
    order = np.argsort(m.positions_xyz[:, 0] + 10 * m.positions_xyz[:, 1])
    assert np.allclose(
        m.positions_xyz[order], rocks[np.argsort(rocks[:, 0] + 10 * rocks[:, 1])], atol=0.02
    )
    assert np.all(m.sightings == 10)


def test_aggregation_empty_and_config_errors():
    assert len(aggregate_detections(np.zeros((0, 3)))) == 0
    with pytest.raises(InputError):
        AggregationConfig(radius_m=0)
    with pytest.raises(InputError):
        AggregationConfig(min_sightings=0)
