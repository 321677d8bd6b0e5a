"""`.lac` archives: write -> read round trips, recorder-style archives, random access, bad archives."""

from __future__ import annotations

import gzip
import io
import tarfile
import zlib

import numpy as np
import pytest

from lunarloc.io.lac.archive import (
    CAMERA_COLUMNS,
    DATA_SPEC,
    FRAME_COLUMNS,
    LacArchive,
    LacWriter,
    _IndexedGzipReader,
    float_text,
)
from lunarloc.core.errors import ArchiveError, InputError

W, H = 32, 24


def _initial(**over):
    cams = {
        "FrontLeft": {
            "camera_active": True,
            "light_intensity": 1.0,
            "width": W,
            "height": H,
            "use_semantic": True,
        },
        "FrontRight": {
            "camera_active": True,
            "light_intensity": 0.5,
            "width": W,
            "height": H,
            "use_semantic": False,
        },
        "Back": {
            "camera_active": False,
            "light_intensity": 0.0,
            "width": W,
            "height": H,
            "use_semantic": False,
        },
    }
    init = {
        "fiducials": False,
        "lander": [0, 0, 0, 0, 0, 0.1],
        "rover": [1, 2, 0, 0, 0, 0.5],
        "cameras": cams,
    }
    init.update(over)
    return init


def write_sample(path, n_frames=8, image_every=2, seed=0, **writer_kw):
    """Write a small archive; return (states, images) with what was written."""
    rng = np.random.default_rng(seed)
    states, images = {}, {}
    with LacWriter(path, _initial(), description="unit test", **writer_kw) as w:
        for f in range(1, n_frames + 1):
            st = {
                "x": f * 0.1,
                "y": 1.0 / 3.0 * f,
                "z": -0.01 * f,
                "roll": 1e-3 * f,
                "pitch": -2e-3,
                "yaw": 0.1 * f,
                "accel_x": 0.01,
                "accel_z": 1.62,
                "gyro_z": 0.02,
                "mission_time": 0.05 * f,
                "power": 500.0 - f,
                "linear_speed": 0.3,
                "angular_speed": 0.02,
                "cover_angle": 1.2,
            }
            w.add_frame(f, **st)
            states[f] = st
            if f % image_every == 0:
                g = rng.integers(0, 256, (H, W), dtype=np.uint8)
                s = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
                g2 = rng.integers(0, 256, (H, W), dtype=np.uint8)
                w.add_camera_frame(
                    "FrontLeft",
                    f,
                    [0.28, 0.081, 0.131, 0, 0, 0],
                    light_intensity=1.0,
                    grayscale=g,
                    semantic=s,
                )
                w.add_camera_frame(
                    "FrontRight",
                    f,
                    [0.28, -0.081, 0.131, 0, 0, 0],
                    light_intensity=0.5,
                    grayscale=g2,
                )
                images[("FrontLeft", f, "grayscale")] = g
                images[("FrontLeft", f, "semantic")] = s
                images[("FrontRight", f, "grayscale")] = g2
        w.add_custom(
            "rocks",
            ["id", "x", "y", "z", "radius"],
            [[1, 2.5, -3.25, 0.0, 0.1], [2, 0.1, 0.2, 0.3, 0.05]],
        )
        w.add_custom(
            "odometry",
            ["frame", "x", "y", "z", "roll", "pitch", "yaw"],
            np.array([[1, 0.1, 0.2, 0, 0, 0, 0.3]]),
        )
    return states, images


def tar_gz(path, members: dict[str, bytes], *, mode=0o644):
    with tarfile.open(path, "w:gz") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mode = mode
            tf.addfile(info, io.BytesIO(data))
    return path


def members_of(path) -> dict[str, bytes]:
    with tarfile.open(path, "r:gz") as tf:
        return {m.name: tf.extractfile(m).read() for m in tf.getmembers() if m.isfile()}


# ---------------------------------------------------------------------------- round trip


def test_round_trip_exact(tmp_path):
    path = tmp_path / "run.lac"
    states, images = write_sample(path)
    with LacArchive(path) as a:
        assert a.n_frames == 8
        assert a.frames.columns == list(FRAME_COLUMNS)
        assert a.frame_numbers.tolist() == list(range(1, 9))
        for i, f in enumerate(a.frame_numbers.tolist()):
            for k in FRAME_COLUMNS[1:]:
                v = states[f].get(k, 0.0)  # missing -> 0.0
                # what float_text wrote, bit-exact; the value itself within 15 significant digits
                assert a.frames[k][i] == float(float_text(v)), (f, k)
                assert a.frames[k][i] == pytest.approx(v, rel=5e-15, abs=1e-22)
        assert (
            a.frames["x"][a.frame_numbers.tolist().index(1)] == 0.1
        )  # shortest repr kept when pandas-exact
        assert a.metadata["frames"] == 8
        assert a.metadata["data_spec"] == DATA_SPEC and not a.lander_stored_in_map_frame
        assert a.metadata["description"] == "unit test"
        assert a.metadata["start_time"] and a.metadata["end_time"]
        assert a.initial["rover"] == [1.0, 2.0, 0.0, 0.0, 0.0, 0.5]
        assert all(
            isinstance(v, float) for v in a.initial["lander"]
        )  # homogeneous for the `toml` package
        assert a.initial["cameras"]["Back"]["camera_active"] is False
        assert a.cameras == [
            "FrontLeft",
            "FrontRight",
        ]  # Back recorded nothing: no table, as the LAC recorder
        assert a.image_count("FrontLeft") == 4 and a.image_count("FrontLeft", "semantic") == 4
        assert a.image_count("FrontRight", "semantic") == 0 and a.image_count("Back") == 0
        assert a.camera_frames("FrontLeft").columns == list(CAMERA_COLUMNS)
        assert len(a.camera_frames("Back")) == 0
        for (cam, f, kind), img in images.items():
            got = a.image(cam, f, kind)
            assert got.dtype == np.uint8 and got.shape == img.shape and np.array_equal(got, img)
        assert a.grayscale("FrontLeft", 3) is None and a.semantic("FrontRight", 2) is None
        row = a.camera_row("FrontRight", 4)
        assert row["enable"] is True and row["camera_y"] == -0.081 and row["light_intensity"] == 0.5
        assert row["semantic"] == "" and row["grayscale"] == "FrontRight_grayscale_4.png"
        assert a.custom_records == ["odometry", "rocks"]
        rocks = a.custom("rocks")
        assert rocks.columns == ["id", "x", "y", "z", "radius"] and len(rocks) == 2
        assert rocks["id"].dtype == np.int64 and rocks["y"][0] == -3.25
        assert a.custom("odometry")["yaw"][0] == 0.3
        assert a.path_length() > 0 and a.duration() == pytest.approx(0.35)
        with pytest.raises(ArchiveError, match="custom/nope.csv"):
            a.custom("nope")


def test_layout_matches_lac_recorder(tmp_path):
    path = tmp_path / "run.lac"
    write_sample(path, n_frames=4)
    with tarfile.open(path, "r:gz") as tf:
        names = tf.getnames()
    assert names[0] == "initial.toml"
    assert {
        "metadata.toml",
        "frames.csv",
        ".gitignore",
        "cameras/FrontLeft/FrontLeft_frames.csv",
        "cameras/FrontLeft/grayscale/FrontLeft_grayscale_2.png",
        "cameras/FrontLeft/semantic/FrontLeft_semantic_2.png",
        "custom/rocks.csv",
    } <= set(names)
    assert not any(n.startswith(("./", "/")) for n in names)
    m = members_of(path)
    header, first = m["cameras/FrontLeft/FrontLeft_frames.csv"].decode().splitlines()[:2]
    assert header == ",".join(CAMERA_COLUMNS)
    assert first.split(",")[1] == "True" and first.endswith(
        "FrontLeft_grayscale_2.png,FrontLeft_semantic_2.png"
    )
    assert (
        m["cameras/FrontRight/FrontRight_frames.csv"]
        .decode()
        .splitlines()[1]
        .endswith("FrontRight_grayscale_2.png,")
    )
    assert m["frames.csv"].decode().splitlines()[0] == ",".join(FRAME_COLUMNS)


def test_iter_frames_streams_images(tmp_path):
    path = tmp_path / "run.lac"
    _, images = write_sample(path)
    with LacArchive(path) as a:
        recs = list(a.iter_frames())
        assert [r.frame for r in recs] == list(range(1, 9))
        assert recs[0].grayscale == {} and recs[0].cameras == {}
        r = recs[1]
        assert set(r.cameras) == {"FrontLeft", "FrontRight"} and set(r.semantic) == {"FrontLeft"}
        assert np.array_equal(r.grayscale["FrontRight"], images[("FrontRight", 2, "grayscale")])
        assert r.state["yaw"] == 0.2
        light = list(a.iter_frames(images=False))
        assert all(rec.grayscale == {} for rec in light)


def test_semantic_uint16_and_gray_semantic_round_trip(tmp_path):
    path = tmp_path / "sem16.lac"
    sem16 = (np.arange(H * W, dtype=np.uint16).reshape(H, W) * 7) % 1000
    g = np.full((H, W), 7, np.uint8)
    with LacWriter(path, _initial()) as w:
        w.add_frame(0)
        w.add_frame(1)
        w.add_camera_frame("FrontLeft", 0, [0] * 6, grayscale=g, semantic=sem16)
        w.add_camera_frame(
            "FrontLeft", 1, [0] * 6, grayscale=g, semantic=(sem16 % 256).astype(np.uint8)
        )
    with LacArchive(path) as a:
        s0, s1 = a.semantic("FrontLeft", 0), a.semantic("FrontLeft", 1)
        assert s0.dtype == np.uint16 and np.array_equal(s0, sem16)
        assert s1.dtype == np.uint8 and np.array_equal(s1, sem16 % 256)


def test_reads_recorder_style_archive(tmp_path):
    """Bytes as the published LAC recorder writes them (toml package formatting, pandas CSVs,
    width/height strings, NaN-empty semantic, JPEG option, custom record with a frame column,
    a configured camera with no table, mode 0o666 members)."""
    from PIL import Image

    gray = np.tile(np.arange(W, dtype=np.uint8) * 8, (H, 1))
    png, jpg = io.BytesIO(), io.BytesIO()
    Image.fromarray(gray).save(png, format="PNG")
    Image.fromarray(gray).save(jpg, format="JPEG", quality=100)
    initial = (
        "fiducials = true\nlander = [ 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,]\nrover = [ 1.5, -2.0, 0.1, 0.0, 0.0, 3.1,]\n\n"
        '[cameras.FrontLeft]\ncamera_active = true\nlight_intensity = 1.0\nwidth = "32"\nheight = "24"\n'
        'use_semantic = false\n\n[cameras.Left]\ncamera_active = false\nlight_intensity = 0\nwidth = "32"\n'
        'height = "24"\nuse_semantic = false\n'
    )
    metadata = 'data_spec = "0.1"\ndescription = ""\nstart_time = "2025-03-01 10:00:00"\nend_time = "2025-03-01 10:01:00"\nframes = 3\n'
    frames = (
        ",".join(FRAME_COLUMNS)
        + "\n"
        + "".join(
            f"{f},{0.1 * f},0.2,0.0,0.0,0.0,0.5,0.0,0.0,1.62,0.0,0.0,0.0,{0.05 * f},100.0,0.3,0.0,0.0\n"
            for f in (1, 2, 3)
        )
    )
    cam = (
        ",".join(CAMERA_COLUMNS)
        + "\n"
        + (
            "2,True,0.28,0.081,0.131,0.0,0.0,0.0,1.0,FrontLeft_grayscale_2.png,\n"
            "3,True,0.28,0.081,0.131,0.0,0.0,0.0,1.0,FrontLeft_grayscale_3.jpg,\n"
        )
    )
    path = tar_gz(
        tmp_path / "sim-2025-03-01_10.00.00.lac",
        {
            "initial.toml": initial.encode(),
            ".gitignore": b"*\n",
            "cameras/FrontLeft/grayscale/FrontLeft_grayscale_2.png": png.getvalue(),
            "cameras/FrontLeft/grayscale/FrontLeft_grayscale_3.jpg": jpg.getvalue(),
            "metadata.toml": metadata.encode(),
            "frames.csv": frames.encode(),
            "cameras/FrontLeft/FrontLeft_frames.csv": cam.encode(),
            "custom/gravity.csv": b"frame,location,accel\n1,earth,9.81\n2,moon,1.62\n",
        },
        mode=0o666,
    )
    with LacArchive(path) as a:
        assert a.initial["fiducials"] is True and a.initial["rover"][5] == 3.1
        assert a.cameras == ["FrontLeft"] and set(a.configured_cameras) == {"FrontLeft", "Left"}
        assert a.frames["x"].tolist() == [0.1 * f for f in (1, 2, 3)]
        assert np.array_equal(a.grayscale("FrontLeft", 2), gray)
        assert np.abs(a.grayscale("FrontLeft", 3).astype(int) - gray).max() <= 3  # JPEG
        assert a.semantic("FrontLeft", 2) is None
        g = a.custom("gravity")
        assert g["location"].tolist() == ["earth", "moon"] and g["accel"].tolist() == [9.81, 1.62]


def test_tolerates_dot_prefix_and_top_level_folder(tmp_path):
    src = tmp_path / "a.lac"
    _, images = write_sample(src, n_frames=2)
    m = members_of(src)
    for prefix in ("./", "run/"):
        path = tar_gz(tmp_path / f"re{len(prefix)}.lac", {prefix + k: v for k, v in m.items()})
        with LacArchive(path) as a:
            assert a.n_frames == 2
            assert np.array_equal(
                a.grayscale("FrontLeft", 2), images[("FrontLeft", 2, "grayscale")]
            )


# ----------------------------------------------------------------------- random access


def test_indexed_gzip_reader_random_seeks_match():
    rng = np.random.default_rng(3)
    payload = (
        rng.integers(0, 256, 300_000, dtype=np.uint8).tobytes() + bytes(100_000) + b"abc" * 50_000
    )
    blob = gzip.compress(payload[:200_000], compresslevel=1) + gzip.compress(
        payload[200_000:]
    )  # multi-member
    r = _IndexedGzipReader(io.BytesIO(blob), spacing=16 * 1024)
    assert r.read_to_end() == len(payload)
    assert r.n_checkpoints > 10
    for _ in range(200):
        a = int(rng.integers(0, len(payload)))
        n = int(rng.integers(0, 40_000))
        r.seek(a)
        assert r.read(n) == payload[a : a + n]
    r.seek(len(payload) - 5)
    assert r.read() == payload[-5:] and r.read(10) == b""


def test_random_access_many_checkpoints(tmp_path):
    path = tmp_path / "big.lac"
    _, images = write_sample(path, n_frames=40, image_every=1, seed=5)
    with LacArchive(path, checkpoint_spacing=4096) as a:
        assert a._stream.n_checkpoints > 20
        keys = list(images)
        order = np.random.default_rng(0).permutation(len(keys))
        for k in order:
            cam, f, kind = keys[k]
            assert np.array_equal(a.image(cam, f, kind), images[keys[k]])


def test_sequential_iteration_is_forward_only(tmp_path, monkeypatch):
    path = tmp_path / "big.lac"
    write_sample(path, n_frames=30, image_every=1)
    with LacArchive(path, checkpoint_spacing=2048) as a:
        restores = []
        orig = _IndexedGzipReader._restore
        monkeypatch.setattr(
            _IndexedGzipReader, "_restore", lambda self, k: (restores.append(k), orig(self, k))
        )
        n = sum(len(r.grayscale) + len(r.semantic) for r in a.iter_frames())
        assert n == 90
        assert len(restores) <= 1  # one jump back to the first image, then forward only


# ----------------------------------------------------------------------- bad archives


def _good_members(tmp_path):
    src = tmp_path / "good.lac"
    write_sample(src, n_frames=4)
    return members_of(src)


def _raises(path, *fragments):
    with pytest.raises(ArchiveError) as ei:
        LacArchive(path)
    msg = str(ei.value)
    assert str(path) in msg
    for frag in fragments:
        assert frag in msg, msg
    return msg


def test_truncated_gzip(tmp_path):
    src = tmp_path / "good.lac"
    write_sample(src, n_frames=4)
    data = src.read_bytes()
    bad = tmp_path / "trunc.lac"
    bad.write_bytes(data[: len(data) // 2])
    _raises(bad, "truncated")
    bad.write_bytes(data[:-4])  # only the gzip trailer cut
    _raises(bad, "truncated")


def test_corrupt_gzip(tmp_path):
    src = tmp_path / "good.lac"
    write_sample(src, n_frames=4)
    data = bytearray(src.read_bytes())
    data[-6] ^= 0xFF  # CRC32 in the trailer
    bad = tmp_path / "crc.lac"
    bad.write_bytes(bytes(data))
    _raises(bad, "corrupt gzip")


def test_not_a_gzip(tmp_path):
    bad = tmp_path / "plain.lac"
    bad.write_bytes(b"frame,x\n1,2\n")
    _raises(bad, "not a gzip")
    notar = tmp_path / "notar.lac"
    notar.write_bytes(gzip.compress(b"hello world" * 100))
    _raises(notar, "tar")


def test_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        LacArchive(tmp_path / "absent.lac")


@pytest.mark.parametrize("member", ["initial.toml", "metadata.toml", "frames.csv"])
def test_missing_required_member(tmp_path, member):
    m = _good_members(tmp_path)
    del m[member]
    _raises(tar_gz(tmp_path / "bad.lac", m), member, "missing")


def test_initial_missing_key_and_bad_toml(tmp_path):
    m = _good_members(tmp_path)
    m["initial.toml"] = b"lander = [0.0,0.0,0.0,0.0,0.0,0.0]\n[cameras]\n"
    _raises(tar_gz(tmp_path / "k.lac", m), "initial.toml", "fiducials")
    m["initial.toml"] = b"this is = = not toml"
    _raises(tar_gz(tmp_path / "t.lac", m), "initial.toml", "invalid TOML")


def test_missing_columns(tmp_path):
    m = _good_members(tmp_path)
    lines = m["frames.csv"].decode().splitlines()
    cols = lines[0].split(",")
    j = cols.index("yaw")
    m2 = dict(m)
    m2["frames.csv"] = "\n".join(
        ",".join(c for i, c in enumerate(ln.split(",")) if i != j) for ln in lines
    ).encode()
    _raises(tar_gz(tmp_path / "f.lac", m2), "frames.csv", "yaw")
    cam = "cameras/FrontLeft/FrontLeft_frames.csv"
    lines = m[cam].decode().splitlines()
    m3 = dict(m)
    m3[cam] = "\n".join(ln.rsplit(",", 1)[0] for ln in lines).encode()  # drop `semantic`
    _raises(tar_gz(tmp_path / "c.lac", m3), cam, "semantic")


def test_image_listed_but_absent(tmp_path):
    m = _good_members(tmp_path)
    member = "cameras/FrontLeft/semantic/FrontLeft_semantic_4.png"
    del m[member]
    _raises(tar_gz(tmp_path / "img.lac", m), member, "absent")


def test_malformed_numbers(tmp_path):
    m = _good_members(tmp_path)
    text = m["frames.csv"].decode().replace("1.33333333333333", "0.3.3", 1)
    assert "0.3.3" in text
    m["frames.csv"] = text.encode()
    _raises(tar_gz(tmp_path / "n.lac", m), "frames.csv", "0.3.3", "line")
    m = _good_members(tmp_path)
    cam = "cameras/FrontRight/FrontRight_frames.csv"
    m[cam] = m[cam].decode().replace(",True,", ",maybe,", 1).encode()
    _raises(tar_gz(tmp_path / "b.lac", m), cam, "enable")
    m = _good_members(tmp_path)
    m["frames.csv"] = m["frames.csv"].decode().replace("\n2,", "\n2.5,", 1).encode()
    _raises(tar_gz(tmp_path / "i.lac", m), "frames.csv", "frame")


def test_duplicate_and_ragged_rows(tmp_path):
    m = _good_members(tmp_path)
    lines = m["frames.csv"].decode().splitlines()
    m["frames.csv"] = "\n".join([*lines, lines[1]]).encode()
    _raises(tar_gz(tmp_path / "d.lac", m), "frames.csv", "twice")
    m["frames.csv"] = "\n".join([*lines, "9,1,2"]).encode()
    _raises(tar_gz(tmp_path / "r.lac", m), "frames.csv", "fields")


def test_undecodable_image_names_member(tmp_path):
    m = _good_members(tmp_path)
    member = "cameras/FrontLeft/grayscale/FrontLeft_grayscale_2.png"
    m[member] = b"not a png"
    with (
        LacArchive(tar_gz(tmp_path / "png.lac", m)) as a,
        pytest.raises(ArchiveError, match=member),
    ):
        a.grayscale("FrontLeft", 2)


# ---------------------------------------------------------------------------- writer


def test_writer_is_atomic_on_error(tmp_path):
    path = tmp_path / "out" / "run.lac"
    with pytest.raises(RuntimeError), LacWriter(path, _initial()) as w:
        w.add_frame(1)
        raise RuntimeError("simulator crashed")
    assert not path.exists()
    assert list(path.parent.iterdir()) == []  # no temp file left behind


def test_writer_rejects_bad_input(tmp_path):
    g = np.zeros((H, W), np.uint8)
    with LacWriter(tmp_path / "w.lac", _initial()) as w:
        with pytest.raises(InputError, match="unknown"):
            w.add_frame(1, velocity=3.0)
        w.add_frame(1)
        with pytest.raises(InputError, match="increase"):
            w.add_frame(1)
        with pytest.raises(InputError, match="initial"):
            w.add_camera_frame("Nope", 1, [0] * 6, grayscale=g)
        with pytest.raises(InputError, match="32x24"):
            w.add_camera_frame("FrontRight", 1, [0] * 6, grayscale=np.zeros((10, 10), np.uint8))
        with pytest.raises(InputError, match="uint8"):
            w.add_camera_frame("FrontRight", 1, [0] * 6, grayscale=g.astype(np.float32))
        with pytest.raises(InputError, match="use_semantic"):
            w.add_camera_frame("FrontRight", 1, [0] * 6, grayscale=g, semantic=g)
        with pytest.raises(InputError, match="semantic image is required"):
            w.add_camera_frame("FrontLeft", 1, [0] * 6, grayscale=g)
        with pytest.raises(InputError, match="grayscale"):
            w.add_camera_frame("FrontRight", 1, [0] * 6)
        with pytest.raises(InputError, match="6 values"):
            w.add_camera_frame("FrontRight", 1, [0] * 3, grayscale=g)
        with pytest.raises(InputError, match="name"):
            w.add_custom("rocks.v2", ["a"], [[1]])
        with pytest.raises(InputError, match="values"):
            w.add_custom("rocks", ["a", "b"], [[1]])
        w.add_camera_frame("FrontRight", 1, [0] * 6, enable=False)  # a disabled row needs no image
    with LacArchive(tmp_path / "w.lac") as a:
        assert a.camera_row("FrontRight", 1)["enable"] is False
        assert a.grayscale("FrontRight", 1) is None


def test_gzip_member_crc_is_checked_by_zlib():
    # guard for the corrupt-gzip test: zlib's gzip mode verifies the CRC at the end of a member
    d = zlib.decompressobj(31)
    blob = bytearray(gzip.compress(b"x" * 1000))
    blob[-6] ^= 1
    with pytest.raises(zlib.error):
        d.decompress(bytes(blob))
