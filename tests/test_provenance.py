"""Pose provenance: which poses placed a vehicle map's detections, written by lunarloc's writers,
read back from every map format, and used by localize for the odometry bounds (stated bounds >
the map's pose provenance > the odometry prior; lunarloc.localization.provenance)."""

from __future__ import annotations

import ast
import csv
import json

import numpy as np
import pytest

from conftest import make_pair
from lunarloc.cli import main
from lunarloc.core.errors import FileFormatError, InputError
from lunarloc.io.maps import (
    DATASET_PROVENANCE,
    LandmarkMap,
    PoseProvenance,
    load_map,
    load_traverse,
    load_vehicle,
    save_map,
    save_traverse,
)
from lunarloc.localization.config import LocalizationConfig
from lunarloc.localization.localize import localize
from lunarloc.localization.provenance import PRIOR, PROVENANCE, STATED, resolve_odometry_bounds
from lunarloc.localization.verify import Evidence, verify

ODO = PoseProvenance("odometry", "visual")
GT = PoseProvenance("ground-truth")


def _rows(rng, n_frames=6, per_frame=4):
    return [
        (f, rng.normal(0, 1, 3), rng.normal(0, 3, (per_frame, 3)))
        for f in range(0, 20 * n_frames, 20)
    ]


def _dataset_csv(path, rows):
    """A traverse CSV as the LunarLoc dataset writes it: six columns, no provenance."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "x", "y", "z", "detections", "boulders"])
        for f, xyz, det in rows:
            b = "[" + ", ".join(f"({x!r}, {y!r}, {z!r})" for x, y, z in det.tolist()) + "]"
            w.writerow([f, *map(repr, map(float, xyz)), len(det), b])
    return path


@pytest.mark.parametrize("prov", [ODO, GT, PoseProvenance("odometry")])
def test_traverse_provenance_round_trip(tmp_path, rng, prov):
    rows = _rows(rng)
    p = tmp_path / "t.csv"
    assert save_traverse(p, rows, prov) == len(rows)
    trav = load_traverse(p)
    assert (trav.pose_provenance.poses, trav.pose_provenance.detail) == (prov.poses, prov.detail)
    assert trav.pose_provenance.stated_by == "the file's pose column"
    assert np.allclose(trav.detections_xyz, np.vstack([d for _, _, d in rows]))
    assert np.allclose(trav.rover_xyz, np.array([x for _, x, _ in rows]))
    # the map made from it keeps it (load_vehicle: what the CLI and the README's snippet use)
    assert load_vehicle(p).pose_provenance == trav.pose_provenance


def test_pose_column_leaves_the_dataset_columns_readable_by_name(tmp_path, rng):
    """A reader of the dataset by column name (csv.DictReader; pandas does the same) still finds
    its six columns and literal-evaluates the boulders: the provenance is an extra column."""
    rows = _rows(rng)
    p = save_traverse(tmp_path / "t.csv", rows, ODO) and tmp_path / "t.csv"
    with open(p, newline="") as fh:
        got = list(csv.DictReader(fh))
    assert [int(r["frame"]) for r in got] == [f for f, _, _ in rows]
    for r, (_, _, det) in zip(got, rows):
        assert np.allclose(np.array(ast.literal_eval(r["boulders"])), det)
        assert int(r["detections"]) == len(det) and r["pose"] == "odometry:visual"


def test_dataset_schema_without_provenance_is_ground_truth(tmp_path, rng):
    p = _dataset_csv(tmp_path / "traverse_3.csv", _rows(rng))
    assert load_traverse(p).pose_provenance == DATASET_PROVENANCE
    v = load_vehicle(p)
    assert v.pose_provenance.rigid and "dataset" in v.pose_provenance.stated_by


def test_detect_sidecar_states_provenance_of_older_files(tmp_path, rng):
    """A traverse CSV written by an older `lunarloc detect` (no pose column) beside its
    OUTPUT.config.json: info.pose names the poses; an unreadable sidecar reads as odometry."""
    p = _dataset_csv(tmp_path / "det.csv", _rows(rng))
    side = tmp_path / "det.csv.config.json"
    side.write_text(json.dumps({"info": {"pose": "visual"}}))
    pp = load_traverse(p).pose_provenance
    assert (pp.poses, pp.detail) == ("odometry", "visual") and "config.json" in pp.stated_by
    side.write_text(json.dumps({"info": {"pose": "ground-truth (evaluation only)"}}))
    assert load_traverse(p).pose_provenance.rigid
    side.write_text("{not json")
    assert not load_traverse(p).pose_provenance.rigid


def test_mixed_rows_are_odometry_and_bad_values_are_refused(tmp_path, rng):
    rows = _rows(rng)
    p = tmp_path / "t.csv"
    save_traverse(p, rows, GT)
    lines = p.read_text().splitlines()
    lines[3] = lines[3].replace("ground-truth", "odometry")
    p.write_text("\n".join(lines) + "\n")
    assert load_traverse(p).pose_provenance.poses == "odometry"
    lines[3] = lines[3].replace("odometry", "sextant")
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(FileFormatError, match=r"t\.csv:4: pose provenance"):
        load_traverse(p)
    p.write_text("frame,x,y,z,detections,boulders,heading\n")
    with pytest.raises(FileFormatError, match="unexpected column"):
        load_traverse(p)
    with pytest.raises(InputError):
        PoseProvenance("sextant")
    with pytest.raises(InputError, match="detail"):  # would break the CSV row or comment line
        PoseProvenance("odometry", "visual,\n# pose: ground-truth")


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_map_file_provenance_round_trip(tmp_path, rng, suffix):
    m = LandmarkMap(rng.normal(0, 3, (10, 3)), pose_provenance=ODO)
    back = load_map(save_map(m, tmp_path / f"m{suffix}"))
    assert (back.pose_provenance.poses, back.pose_provenance.detail) == ("odometry", "visual")
    plain = load_map(save_map(LandmarkMap(m.positions_xyz), tmp_path / f"p{suffix}"))
    assert plain.pose_provenance is None
    assert m.subset([0, 1]).pose_provenance == ODO
    assert m.transformed(np.eye(4)).pose_provenance == ODO


def test_map_csv_bad_pose_line_is_refused(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("# frame: map\n# pose: sextant\nx,y,z\n0,0,0\n")
    with pytest.raises(FileFormatError, match=r"m\.csv:2"):
        load_map(p)


def test_precedence_stated_over_provenance_over_prior(rng):
    m = LandmarkMap(np.zeros((3, 3)), pose_provenance=GT)
    stated = LocalizationConfig(odometry_scale_error=0.01, odometry_heading_drift_deg_per_m=0.05)
    cfg, b = resolve_odometry_bounds(stated, m)
    assert b.source == STATED and cfg.odometry_scale_error == 0.01 and "stated" in b.text
    cfg, b = resolve_odometry_bounds(LocalizationConfig(), m)
    assert b.source == PROVENANCE and cfg.odometry_scale_error == 0.0
    assert cfg.odometry_heading_drift_deg_per_m == 0.0 and "pose provenance" in b.text
    for prov in (ODO, None):
        m.pose_provenance = prov
        cfg, b = resolve_odometry_bounds(LocalizationConfig(), m)
        assert b.source == PRIOR and not cfg.odometry_bounds_stated and "prior" in b.text


def test_localize_result_says_where_the_bounds_came_from(rng):
    ref, veh, _, _ = make_pair(rng)
    out = {}
    for name, prov, cfg in [
        ("provenance", GT, None),
        ("prior", ODO, None),
        (
            "stated",
            GT,
            LocalizationConfig(odometry_scale_error=0.0, odometry_heading_drift_deg_per_m=0.0),
        ),
    ]:
        veh.pose_provenance = prov
        res = localize(ref, veh, cfg)
        out[name] = res.to_dict()["odometry_bounds"]
    assert [out[k]["source"] for k in ("provenance", "prior", "stated")] == [
        PROVENANCE,
        PRIOR,
        STATED,
    ]
    assert out["prior"]["pose_provenance"]["detail"] == "visual"
    assert (
        out["stated"]["pose_provenance"]["poses"] == "ground-truth"
    )  # recorded, but the config won


def test_refusal_text_names_the_bounds_source():
    ev = Evidence(
        inliers=20,
        rmse_m=0.01,
        rmse_limit_m=0.05,
        sigma_h_m=0.01,
        sigma_z_m=0.01,
        extent_m=5.0,
        planarity=0.5,
        tilt_deg=0.0,
        handedness=1.0,
        scale_error=0.0,
        scale_se=0.001,
        near_misses=0,
        near_misses_expected=1.0,
        near_inner_m=0.1,
        near_outer_m=0.3,
        predicted_error_m=0.5,
        distortion_error_m=0.45,
        predicted_rotation_deg=0.1,
        distortion_rotation_deg=0.05,
        inliers_beyond_chance=20,
        required_inliers=8,
        chance_inliers=4,
        num_associations=1000,
        competitor=3,
        distortion_fitted=True,
        odometry_bounds="no odometry bounds: fitted; the map's pose provenance is odometry visual",
    )
    (pe,) = [c for c in verify(ev, LocalizationConfig()) if c.name == "predicted_error"]
    assert not pe.passed and "the map's pose provenance is odometry visual" in pe.detail


def test_cli_names_the_source_and_precedence(tmp_path, rng, capsys):
    """The plain CLI on a dataset-schema vehicle file says its bounds came from the file's
    provenance; stated options win over it, in the text and in --json."""
    ref, veh, _, _ = make_pair(rng)
    ref_p = save_map(ref, tmp_path / "ref.csv")
    pts = veh.positions_xyz  # every landmark seen in 8 frames, 1 mm apart
    rows = [(20 * f, pts.mean(axis=0), pts + rng.normal(0, 0.001, pts.shape)) for f in range(8)]
    veh_p = _dataset_csv(tmp_path / "veh.csv", rows)
    assert main(["localize", str(ref_p), str(veh_p)]) == 0
    text = capsys.readouterr().out.replace("\n", " ")
    assert "odometry bounds: 0 (rigid), from the map's pose provenance: ground truth" in text
    assert (
        main(["localize", str(ref_p), str(veh_p), "--odometry-scale-error", "0.01", "--json"]) == 0
    )
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d["odometry_bounds"]["source"] == "stated"
    assert d["odometry_bounds"]["scale_error"] == 0.01
