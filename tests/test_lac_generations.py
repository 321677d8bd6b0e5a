"""Archives as each LAC recorder generation wrote them, byte for byte, read by LacArchive.

Generations (from the recorder's history in ``Robaire/MAPLE`` ``maple/data/recorder.py``
and ``Robaire/lac-data``):

* G0 (MAPLE, 2025-04-21 morning): tables and images under ``images/<Cam>/``; a camera row
  for every frame (empty file name without an image), the *member path* in the
  ``grayscale`` column, extra ``light_x .. light_yaw`` columns; no ``.gitignore``.
* G2 (MAPLE, 2025-04-21 afternoon): ``cameras/<Cam>/``, bare file names, rows only with an
  image, a 1-byte table (``"\\n"``, pandas' empty DataFrame) for a camera without images;
  custom records without a ``frame`` column.
* G5 (lac-data 2025-05): ``.gitignore``, no table for a camera without images, custom
  records with ``frame`` first, PNG or JPEG (quality 100).

All generations pass numpy scalars to the ``toml`` package, which writes them as strings
(``"1.5"`` under numpy 1, ``"np.float64(1.5)"`` under numpy 2); the example agent gives
``width``/``height`` as strings. The TOML and CSV texts below are what ``toml.dumps`` and
``DataFrame.to_csv(index=False)`` produce for them (checked against toml 0.10.2 and pandas
2.2.3 once, offline).
"""

from __future__ import annotations

import io
import tarfile

import numpy as np
import pytest

from lunarloc.io.lac.archive import (
    FRAME_COLUMNS,
    LacArchive,
    LacWriter,
    float_text,
    lander_pose_map,
)
from lunarloc.core.errors import ArchiveError

W, H = 32, 24
CAMS = ("Front", "FrontLeft", "FrontRight", "BackLeft")


def _np_str(v: float, numpy2: bool) -> str:
    return f'"np.float64({v!r})"' if numpy2 else f'"{v!r}"'


def initial_toml(numpy2: bool = True, *, semantic_front: bool = True) -> bytes:
    """initial.toml as the recorder wrote it for the example agent (numpy scalars as strings)."""
    lander = (1.5, -7.25, -0.4, 0.0, 0.0, -1.2)
    rover = (-3.5, 6.25, 0.4, 0.01, -0.02, 1.2)
    text = "fiducials = false\n"
    text += "lander = [ " + ", ".join(_np_str(v, numpy2) for v in lander) + ",]\n"
    text += "rover = [ " + ", ".join(_np_str(v, numpy2) for v in rover) + ",]\n"
    for cam in CAMS:
        active = cam != "BackLeft"
        sem = semantic_front and cam == "Front"
        light = "1.0" if cam == "Front" else "0"
        text += (
            f"\n[cameras.{cam}]\ncamera_active = {str(active).lower()}\nlight_intensity = {light}\n"
            f'width = "{W}"\nheight = "{H}"\nuse_semantic = {str(sem).lower()}\n'
        )
    return text.encode()


def metadata_toml(frames: int) -> bytes:
    return (
        f'data_spec = "0.1"\ndescription = ""\nstart_time = "2025-04-21 20:00:00"\n'
        f'end_time = "2025-04-21 20:01:00"\nframes = {frames}\n'
    ).encode()


def frames_csv(n: int, *, speed_text=None, gyro_text=None) -> tuple[bytes, np.ndarray]:
    """frames.csv of a rover driving forward at 0.2 m/s from the initial pose, as pandas writes it."""
    rows, states = [], []
    for k in range(n):
        t = 0.05 * k
        st = [
            -3.5 + 0.2 * t,
            6.25,
            0.4,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            1.622,
            0.0,
            0.0,
            0.0,
            t,
            283.0 - t / 120,
            0.2,
            0.0,
            0.0,
        ]
        states.append(st)
        cells = [str(k + 1)] + [repr(float(v)) for v in st]
        if speed_text is not None and k == 3:
            cells[FRAME_COLUMNS.index("linear_speed")] = speed_text
        if gyro_text is not None and k == 4:
            cells[FRAME_COLUMNS.index("gyro_z")] = gyro_text
        rows.append(",".join(cells))
    return (",".join(FRAME_COLUMNS) + "\n" + "\n".join(rows) + "\n").encode(), np.array(states)


def _png(img: np.ndarray, fmt: str = "PNG") -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    if fmt == "JPEG":
        Image.fromarray(img).save(buf, format="JPEG", quality=100, optimize=True, progressive=False)
    else:
        Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def tar_members(path, members: list[tuple[str, bytes]]):
    with tarfile.open(path, "w:gz") as tf:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mode = 0o666
            tf.addfile(info, io.BytesIO(data))
    return path


_POSE = {
    "FrontLeft": "0.28,0.081,0.131",
    "FrontRight": "0.28,-0.081,0.131",
    "Front": "0.28,0.0,0.131",
}


def g0_archive(path, n=6):
    """First MAPLE recorder: images/ layout, member paths, a row every frame, light_* columns."""
    rng = np.random.default_rng(0)
    members = [("initial.toml", initial_toml(numpy2=False, semantic_front=False))]
    tables, images = {}, {}
    for cam in ("FrontLeft", "FrontRight"):
        rows = []
        for k in range(1, n + 1):
            name = ""
            if k % 2 == 0:
                img = rng.integers(0, 256, (H, W), dtype=np.uint8)
                name = f"images/{cam}/grayscale/{cam}_grayscale_{k}.png"
                members.append((name, _png(img)))
                images[(cam, k)] = img
            rows.append(f"{k},True,{_POSE[cam]},0.0,0.0,0.0,0,{_POSE[cam]},0.0,0.0,0.0,{name},")
        tables[cam] = (
            "frame,enable,camera_x,camera_y,camera_z,camera_roll,camera_pitch,camera_yaw,light_intensity,"
            "light_x,light_y,light_z,light_roll,light_pitch,light_yaw,grayscale,semantic\n"
            + "\n".join(rows)
            + "\n"
        ).encode()
    frames, states = frames_csv(n)
    members += [("metadata.toml", metadata_toml(n)), ("frames.csv", frames)]
    members += [(f"images/{c}/{c}_frames.csv", t) for c, t in tables.items()]
    members += [(f"images/{c}/{c}_frames.csv", b"\n") for c in CAMS if c not in tables]
    return tar_members(path, members), states, images


def g2_archive(
    path, n=6, *, images_from=("FrontLeft", "FrontRight"), fmt="PNG", custom=True, numpy2=True
):
    """MAPLE recorder of 2025-04-21 afternoon: cameras/, bare names, 1-byte empty tables."""
    rng = np.random.default_rng(1)
    members = [("initial.toml", initial_toml(numpy2=numpy2, semantic_front=False))]
    tables, images = {}, {}
    ext = "jpg" if fmt == "JPEG" else "png"
    for cam in images_from:
        rows = []
        for k in range(2, n + 1, 2):
            img = rng.integers(0, 256, (H, W), dtype=np.uint8)
            name = f"{cam}_grayscale_{k}.{ext}"
            members.append((f"cameras/{cam}/grayscale/{name}", _png(img, fmt)))
            images[(cam, k)] = img
            rows.append(f"{k},True,{_POSE[cam]},0.0,0.0,0.0,0,{name},")
        tables[cam] = (
            "frame,enable,camera_x,camera_y,camera_z,camera_roll,camera_pitch,camera_yaw,light_intensity,"
            "grayscale,semantic\n" + "\n".join(rows) + "\n"
        ).encode()
    frames, states = frames_csv(n)
    members += [("metadata.toml", metadata_toml(n)), ("frames.csv", frames)]
    members += [(f"cameras/{c}/{c}_frames.csv", tables.get(c, b"\n")) for c in CAMS]
    if custom:
        members.append(
            ("custom/estimate.csv", b"x,y\n" + b"".join(b"%d.5,0.25\n" % k for k in range(n)))
        )
    return tar_members(path, members), states, images


# ------------------------------------------------------------------------------- readers


def test_g0_images_layout_member_paths_and_every_frame_rows(tmp_path):
    path, states, images = g0_archive(tmp_path / "g0.lac")
    with LacArchive(path) as a:
        assert a.cameras == ["FrontLeft", "FrontRight"]  # the 1-byte tables: no images
        assert a.image_count("FrontLeft") == 3 and a.camera_frames("FrontLeft").n_rows == 6
        for (cam, k), img in images.items():
            np.testing.assert_array_equal(a.grayscale(cam, k), img)
        assert a.grayscale("FrontLeft", 3) is None  # a row without an image
        assert a.initial["rover"] == [-3.5, 6.25, 0.4, 0.01, -0.02, 1.2]  # "1.5"-style strings
        assert (
            a.initial["cameras"]["Front"]["width"] == W
            and a.initial["cameras"]["Front"]["light_intensity"] == 1.0
        )
        assert a.initial_raw["cameras"]["Front"]["width"] == str(W)
        np.testing.assert_array_equal(a.poses(), states[:, :6])


@pytest.mark.parametrize("numpy2", [True, False])
def test_g2_one_byte_tables_and_numbers_as_strings(tmp_path, numpy2):
    path, states, images = g2_archive(tmp_path / "g2.lac", numpy2=numpy2)
    with LacArchive(path) as a:
        assert a.cameras == ["FrontLeft", "FrontRight"]
        assert set(a.configured_cameras) == set(CAMS)
        assert a.camera_frames("Front").n_rows == 0 and a.image_count("Front") == 0
        assert a.initial["lander"] == [1.5, -7.25, -0.4, 0.0, 0.0, -1.2]
        assert all(isinstance(v, float) for v in a.initial["rover"])
        assert (
            a.initial["cameras"]["FrontLeft"]["height"] == H
            and a.initial["cameras"]["FrontLeft"]["light_intensity"] == 0.0
        )
        for (cam, k), img in images.items():
            np.testing.assert_array_equal(a.grayscale(cam, k), img)
        assert (
            a.custom_records == ["estimate"] and a.custom("estimate").n_rows == 6
        )  # no frame column


def test_jpeg_images(tmp_path):
    path, _, images = g2_archive(tmp_path / "jpg.lac", fmt="JPEG")
    with LacArchive(path) as a:
        for (cam, k), img in images.items():
            got = a.grayscale(cam, k)
            assert got.shape == (H, W) and got.dtype == np.uint8
            assert np.abs(got.astype(int) - img).mean() < 8  # quality 100 is near-lossless on noise


def test_only_frames_imu_and_empty_camera_tables(tmp_path):
    """The issue's archive: 1-byte tables for every camera, no images, no custom records."""
    path, states, _ = g2_archive(tmp_path / "bare.lac", n=40, images_from=(), custom=False)
    with LacArchive(path) as a:
        assert a.cameras == [] and a.custom_records == [] and a.n_frames == 40
        assert a.image_count("FrontLeft") == 0
        np.testing.assert_array_equal(a.frames["accel_z"], states[:, 8])


def test_info_and_plot_on_the_bare_archive(tmp_path, capsys):
    from lunarloc.cli.app import main

    path, _, _ = g2_archive(tmp_path / "bare.lac", n=40, images_from=(), custom=False)
    assert main(["info", str(path), "--plot", str(tmp_path / "p.png")]) == 0
    out = capsys.readouterr().out
    assert "frames      : 40" in out and (tmp_path / "p.png").stat().st_size > 0


def test_not_a_number_in_initial_toml_names_the_key(tmp_path):
    path, _, _ = g2_archive(tmp_path / "x.lac")
    m = _members(path)
    m["initial.toml"] = m["initial.toml"].replace(b'width = "32"', b'width = "wide"', 1)
    with pytest.raises(ArchiveError, match=r"initial.toml.*cameras\.Front\.width.*'wide'"):
        LacArchive(tar_members(tmp_path / "y.lac", list(m.items())))


def _members(path) -> dict[str, bytes]:
    with tarfile.open(path, "r:gz") as tf:
        return {mb.name: tf.extractfile(mb).read() for mb in tf.getmembers() if mb.isfile()}


# ------------------------------------------------------------------------------- lander frame


def _initial(lander, rover):
    cam = {
        "camera_active": True,
        "light_intensity": 0.0,
        "width": W,
        "height": H,
        "use_semantic": False,
    }
    return {"fiducials": False, "lander": lander, "rover": rover, "cameras": {"FrontLeft": cam}}


def test_lander_is_rover_relative_and_map_pose_composes(tmp_path):
    rover = [-3.5, 6.25, 0.4, 0.0, 0.0, np.pi / 2]
    with LacWriter(
        tmp_path / "a.lac", _initial([7.0, 2.0, -0.4, 0.0, 0.0, -np.pi / 2], rover)
    ) as w:
        w.add_frame(0)
    with LacArchive(tmp_path / "a.lac") as a:
        assert not a.lander_stored_in_map_frame
        np.testing.assert_allclose(
            a.lander_pose_map(), [-5.5, 13.25, 0.0, 0.0, 0.0, 0.0], atol=1e-12
        )


def test_legacy_lunarloc_archive_with_map_frame_lander_is_converted(tmp_path):
    """Archives lunarloc wrote before data_spec lunarloc-2 carry a map-frame lander."""
    rover = [-3.5, 6.25, 0.4, 0.0, 0.0, np.pi / 2]
    lander_map = [0.0, 0.0, 0.0, 0.0, 0.0, 0.3]
    with LacWriter(tmp_path / "new.lac", _initial(lander_map, rover)) as w:
        w.add_frame(0)
    m = _members(tmp_path / "new.lac")
    m["metadata.toml"] = m["metadata.toml"].replace(b'"lunarloc-2"', b'"lunarloc-sim"')
    legacy = tar_members(tmp_path / "old.lac", list(m.items()))
    with LacArchive(legacy) as a:
        assert a.lander_stored_in_map_frame
        np.testing.assert_allclose(a.lander_pose_map(), lander_map, atol=1e-12)
        np.testing.assert_allclose(
            a.initial["lander"][:3], [-6.25, -3.5, -0.4], atol=1e-12
        )  # ahead-left is +x+y: behind and right
        assert a.initial_raw["lander"] == lander_map
    with pytest.raises(ValueError, match="map-frame lander"):
        LacWriter(tmp_path / "refused.lac", _initial(lander_map, rover), data_spec="lunarloc-sim")


def test_simulator_writes_a_rover_relative_lander(tmp_path):
    from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse

    cfg = SimulationConfig(duration_s=1.0, cameras=(), semantic=False)
    site = simulate_site(0, cfg.site)
    path, traj = simulate_traverse(site, tmp_path / "s.lac", 0, cfg)
    with LacArchive(path) as a:
        np.testing.assert_allclose(a.lander_pose_map(), site.lander_pose, atol=1e-9)
        np.testing.assert_allclose(lander_pose_map(a.initial_raw), site.lander_pose, atol=1e-9)
        assert np.linalg.norm(a.initial["lander"][:2]) == pytest.approx(
            np.linalg.norm(traj.xyz[0, :2] - site.lander_xyz[:2]), abs=0.5
        )


# ------------------------------------------------------------------------------- float text


@pytest.mark.parametrize(
    "value",
    [
        0.1 + 0.2,
        0.15000000000000002,
        -0.00445413312008323,
        1e-5 / 3,
        2.7755575615628914e-17,
        123.456,
        1e300,
        -0.0,
        0.05 * 7,
        1.0 / 3.0,
    ],
)
def test_float_text_is_read_the_same_by_a_correctly_rounding_and_pandas_parser(value):
    from lunarloc.io.lac.writer import _pandas_exact

    text = float_text(value)
    assert float(text) == pytest.approx(value, rel=5e-15, abs=1e-22)
    if abs(value) < 1e30:
        assert _pandas_exact(text), (
            text
        )  # digits < 2**53 and a power of ten pandas divides by exactly


def test_float_text_against_pandas():
    pd = pytest.importorskip("pandas")
    rng = np.random.default_rng(3)
    vals = np.concatenate(
        [
            rng.normal(size=3000),
            rng.normal(size=3000) * 10.0 ** rng.integers(-25, 10, 3000),
            np.arange(300) * 0.05,
        ]
    )
    text = "v\n" + "\n".join(float_text(v) for v in vals) + "\n"
    back = pd.read_csv(io.StringIO(text))["v"].to_numpy()
    ours = np.array([float(s) for s in text.split("\n")[1:-1]])
    np.testing.assert_array_equal(back, ours)


def test_readme_layout_images_folder_with_bare_names(tmp_path):
    """The layout the READMEs draw: images/<Cam>/<Cam>_frames.csv with bare file names."""
    path, _, images = g2_archive(tmp_path / "g2.lac")
    moved = {
        (n.replace("cameras/", "images/", 1) if n.startswith("cameras/") else n): d
        for n, d in _members(path).items()
    }
    with LacArchive(tar_members(tmp_path / "readme.lac", list(moved.items()))) as a:
        assert a.cameras == ["FrontLeft", "FrontRight"]
        for (cam, k), img in images.items():
            np.testing.assert_array_equal(a.grayscale(cam, k), img)


def test_empty_custom_record_reads_as_an_empty_table(tmp_path, capsys):
    from lunarloc.cli.app import main

    path, _, _ = g2_archive(tmp_path / "g2.lac", custom=False)
    m = _members(path)
    m["custom/estimate.csv"] = b"\n"  # pandas' empty DataFrame
    p = tar_members(tmp_path / "e.lac", list(m.items()))
    with LacArchive(p) as a:
        t = a.custom("estimate")
        assert a.custom_records == ["estimate"] and t.n_rows == 0 and t.columns == []
    assert main(["info", str(p)]) == 0
    assert "estimate" in capsys.readouterr().out
