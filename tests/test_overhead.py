"""Maps from above: LAC geometric maps and rock catalogues as references, LAC maps written
and scored, and their bad inputs."""

import json

import numpy as np
import pytest

from conftest import random_T, rock_field
from lunarloc.cli import main
from lunarloc.core.errors import FileFormatError, InputError
from lunarloc.core.geometry import invert_transform, transform_points
from lunarloc.localization.config import LocalizationConfig
from lunarloc.localization.localize import localize
from lunarloc.io.maps import LandmarkMap, load_map, save_map
from lunarloc.io.overhead import (
    LAC_CELL_M,
    empty_lac_grid,
    grid_landmarks,
    landmarks_to_lac_grid,
    load_lac_grid,
    load_rock_catalogue,
    score_geometric_map,
    site_geometric_map,
    validate_lac_grid,
)
from lunarloc.pipeline.reference import load_reference

# the vehicle maps below are true rock positions (no odometry): stated rigid. Without bounds the
# localizer fits a bend along a straight stand-in path and, against a grid's 4 cm quantisation,
# cannot rule one out at the map's edges (docs/verification.md)
RIGID = LocalizationConfig(odometry_scale_error=0.0, odometry_heading_drift_deg_per_m=0.0)


def grid_with_rocks(rng, n_rocks=300, cell=LAC_CELL_M):
    """A LAC grid on a gentle slope with square rocks of 1-3 x 1-3 cells (heights +0.2 m),
    and the true centres of those rocks."""
    g = empty_lac_grid()
    g[:, :, 2] = 0.02 * g[:, :, 0] + 0.01 * g[:, :, 1]
    n = g.shape[0]
    centres = []
    taken = np.zeros((n, n), dtype=bool)
    while len(centres) < n_rocks:
        i, j = rng.integers(2, n - 5, 2)
        a, b = rng.integers(1, 4, 2)
        if taken[i - 1 : i + a + 1, j - 1 : j + b + 1].any():
            continue
        taken[i : i + a, j : j + b] = True
        g[i : i + a, j : j + b, 3] = 1.0
        g[i : i + a, j : j + b, 2] += 0.2
        centres.append([g[i : i + a, j, 0].mean(), g[i, j : j + b, 1].mean()])
    return g, np.asarray(centres)


def test_grid_rocks_follow_the_grouping_rule(rng):
    g, centres = grid_with_rocks(rng, 40)
    lm = grid_landmarks(g)
    assert len(lm) == 40
    d = np.linalg.norm(lm.positions_xyz[:, None, :2] - centres[None], axis=2).min(axis=1)
    assert np.all(d < 1e-9)  # centroid of the cell centres
    assert np.allclose(lm.sigma_xy_m, LAC_CELL_M / np.sqrt(12 * lm.sightings))  # sightings = cells
    # height halfway between the ground around the rock and the rock's cells (0.2 m higher)
    ground = 0.02 * lm.positions_xyz[:, 0] + 0.01 * lm.positions_xyz[:, 1]
    assert np.allclose(lm.positions_xyz[:, 2] - ground, 0.1, atol=0.01)
    # diagonal neighbours are one rock (8-connectivity)
    g2 = empty_lac_grid()
    g2[10, 10, 3] = g2[11, 11, 3] = 1
    g2[50, 50, 3] = 1
    g2[60, 60, 3] = 1
    assert len(grid_landmarks(g2)) == 3


def test_localize_vehicle_map_in_a_lac_grid(rng):
    g, centres = grid_with_rocks(rng, 300)
    ref = grid_landmarks(g)
    pick = np.flatnonzero(
        np.linalg.norm(ref.positions_xyz[:, :2] - ref.positions_xyz[0, :2], axis=1) < 7
    )
    # the vehicle sees the true rock centres (not quantised) with 1 cm noise
    true = ref.positions_xyz[pick].copy()
    order = np.argmin(np.linalg.norm(true[:, None, :2] - centres[None], axis=2), axis=1)
    true[:, :2] = centres[order] + rng.normal(
        0, 0.03, (len(pick), 2)
    )  # within a cell of the grid's centroid
    T = random_T(rng, max_tilt_deg=0.5)
    veh = LandmarkMap(transform_points(invert_transform(T), true + rng.normal(0, 0.01, true.shape)))
    r = localize(ref, veh, RIGID)
    assert r.success, r.reason
    err = np.linalg.norm(transform_points(r.T_ref_veh @ invert_transform(T), true) - true, axis=1)
    assert err.max() < 0.10
    assert r.covariance.shape == (6, 6) and np.allclose(r.covariance, r.covariance.T)


def test_site_geometric_map_and_its_rocks():
    from lunarloc.sim.simulate import simulate_site
    from lunarloc.pipeline.reference import rocks_to_reference

    site = simulate_site(0)
    g = site_geometric_map(site)
    assert g.shape == (180, 180, 4)
    validate_lac_grid(g)
    ref = grid_landmarks(g)
    big = site.rocks.radii > 0.15
    # every large rock has a grid rock within one cell of its centre
    d = np.linalg.norm(
        site.rocks.centers[big, None, :2] - ref.positions_xyz[None, :, :2], axis=2
    ).min(axis=1)
    assert np.median(d) < LAC_CELL_M
    # a vehicle map of the true rocks of one area localizes in the grid
    truth = rocks_to_reference(site.rocks.table())
    rng = np.random.default_rng(0)
    sel = np.linalg.norm(truth.positions_xyz[:, :2] - np.array([3.0, -2.0]), axis=1) < 6
    P = truth.positions_xyz[sel] + rng.normal(0, 0.01, (int(sel.sum()), 3))
    T = random_T(rng, max_tilt_deg=0.3)
    r = localize(ref, LandmarkMap(transform_points(invert_transform(T), P)), RIGID)
    assert r.success, r.reason
    assert (
        np.linalg.norm(transform_points(r.T_ref_veh @ invert_transform(T), P) - P, axis=1).max()
        < 0.10
    )


def test_catalogue_with_and_without_heights(tmp_path, rng):
    xyz = rock_field(rng, 200)
    radius = rng.uniform(0.05, 0.4, len(xyz))
    p3 = tmp_path / "cat3.csv"
    p3.write_text(
        "x,y,z,radius\n" + "".join(f"{x},{y},{z},{r}\n" for (x, y, z), r in zip(xyz, radius))
    )
    p2 = tmp_path / "cat2.csv"
    p2.write_text(
        "radius,x,y,sigma_m\n" + "".join(f"{r},{x},{y},0.02\n" for (x, y, _), r in zip(xyz, radius))
    )
    c3 = load_reference(p3)
    assert (
        c3.has_heights and np.allclose(c3.positions_xyz, xyz) and np.allclose(c3.sizes, 2 * radius)
    )
    c2 = load_reference(p2)
    assert not c2.has_heights and np.allclose(c2.sigma_xy_m, 0.02)
    common = np.argsort(np.linalg.norm(xyz[:, :2] - xyz[0, :2], axis=1))[:35]
    T = random_T(rng, max_tilt_deg=0.0)
    veh = LandmarkMap(
        transform_points(invert_transform(T), xyz[common] + rng.normal(0, 0.01, (35, 3)))
    )
    for ref in (c3, c2):
        r = localize(ref, veh)
        assert r.success, r.reason
        E = r.T_ref_veh @ invert_transform(T)
        assert (
            np.linalg.norm(
                transform_points(E, xyz[common])[:, :2] - xyz[common][:, :2], axis=1
            ).max()
            < 0.05
        )
    # heights from a DEM: the grid's nearest cell
    dem = empty_lac_grid()
    dem[:, :, 2] = 0.5
    np.save(tmp_path / "dem.npy", dem)
    cd = load_reference(p2, dem=tmp_path / "dem.npy")
    assert cd.has_heights and np.allclose(cd.positions_xyz[:, 2], 0.5)


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda g: g[:, :, :3], "shape"),
        (lambda g: g[0], "shape"),
        (lambda g: g.astype(str), "dtype"),
        (lambda g: np.where(np.arange(4) == 2, np.nan, g), "non-finite height"),
        (lambda g: np.where(np.arange(4) == 3, 0.0, g), "no rock cells"),
        (lambda g: np.where(np.arange(4) == 3, 2.0, g), r"\[0, 1\]"),
    ],
)
def test_bad_grids_raise_clear_errors(tmp_path, make, match):
    g = empty_lac_grid()
    g[5:7, 5:7, 3] = 1
    bad = make(g)
    path = tmp_path / "bad.npy"
    np.save(path, bad)
    with pytest.raises(InputError, match=match):
        load_reference(path)
    assert main(["localize", str(path), str(path)]) == 2


def test_bad_catalogues_raise_clear_errors(tmp_path):
    cases = {
        "x,y,radius\n0,0,0.1\n1,0,-0.2\n": r"bad\.csv:3: negative radius",
        "x,y,radius,sigma_m\n0,0,0.1,-1\n": r"bad\.csv:2: negative sigma_m",
        "x,y,radius\n0,0,abc\n": r"bad\.csv:2:",
        "x,y,radius\n0,nan,0.1\n": r"bad\.csv:2: non-finite",
        "x,y,radius\n": "no rocks",
    }
    for text, match in cases.items():
        p = tmp_path / "bad.csv"
        p.write_text(text)
        with pytest.raises(FileFormatError, match=match):
            load_rock_catalogue(p)
    p.write_text("x,y,radius\n0,0,0.1\n1,0,-0.2\n")
    assert main(["localize", str(p), str(p)]) == 2
    with pytest.raises(FileFormatError, match="npy"):
        (tmp_path / "junk.npy").write_text("not numpy")
        load_lac_grid(tmp_path / "junk.npy")


def test_score_and_lac_grid_from_landmarks(rng):
    truth = empty_lac_grid()
    truth[40:44, 40:44, 3] = 1
    truth[:, :, 2] = 0.1
    s = score_geometric_map(truth, truth)
    assert s["geometric"] == 1.0 and s["rock_f1"] == 1.0
    produced = truth.copy()
    produced[:90, :, 2] += 0.06  # half the cells 6 cm off
    produced[40:42, 40:44, 3] = 0  # half the rock cells missed
    produced[100, 100, 3] = 1  # one false rock cell
    s = score_geometric_map(produced, truth)
    assert s["geometric"] == pytest.approx(0.5)
    assert s["rock_recall"] == pytest.approx(0.5) and s["rock_precision"] == pytest.approx(8 / 9)
    with pytest.raises(InputError, match="shape"):
        score_geometric_map(truth[:100, :100], truth)
    # landmarks -> grid -> landmarks keeps the rocks
    lm = LandmarkMap(
        np.array([[1.0, 2.0, 0.3], [-5.0, 4.0, 0.1], [6.0, -7.0, 0.2]]),
        sizes=np.array([0.5, 0.3, 0.2]),
    )
    g = landmarks_to_lac_grid(lm)
    back = grid_landmarks(g)
    assert len(back) == 3
    assert (
        np.linalg.norm(back.positions_xyz[:, None, :2] - lm.positions_xyz[None, :, :2], axis=2)
        .min(axis=0)
        .max()
        < 0.1
    )


def test_cli_localize_score_and_map_grid(tmp_path, rng, capsys):
    from test_cli_core import write_traverse_csv

    g, centres = grid_with_rocks(rng, 250)
    np.save(tmp_path / "map.npy", g)
    ref = grid_landmarks(g)
    pick = np.flatnonzero(
        np.linalg.norm(ref.positions_xyz[:, :2] - ref.positions_xyz[3, :2], axis=1) < 7
    )
    veh = LandmarkMap(ref.positions_xyz[pick] + rng.normal(0, 0.01, (len(pick), 3)))
    save_map(veh, tmp_path / "veh.csv")
    assert (
        main(
            [
                "localize",
                str(tmp_path / "map.npy"),
                str(tmp_path / "veh.csv"),
                "--json",
                "--odometry-scale-error",
                "0",
                "--odometry-drift",
                "0",
            ]
        )
        == 0
    )
    d = json.loads(capsys.readouterr().out)
    assert d["success"] is True and len(d["covariance"]) == 6
    assert np.allclose(np.array(d["T_ref_veh"])[:3, 3], 0, atol=0.05)
    # map --lac-grid from detections, then score it against the truth
    trav = write_traverse_csv(tmp_path / "trav.csv", ref.positions_xyz[:60], rng)
    out = tmp_path / "team.npy"
    assert main(["map", str(trav), "--lac-grid", str(out)]) == 0
    capsys.readouterr()
    assert main(["score", str(out), str(tmp_path / "map.npy"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert 0 < s["rock_recall"] <= 1 and 0 < s["rock_precision"] <= 1 and 0 <= s["geometric"] <= 1
    assert main(["map", str(trav)]) == 2  # nothing to write


def test_sigma_columns_round_trip_and_old_files_load(tmp_path, rng):
    m = LandmarkMap(rock_field(rng, 10), sigma_xy_m=np.full(10, 0.04), sigma_z_m=np.full(10, 0.02))
    for suffix in (".csv", ".npz"):
        back = load_map(save_map(m, tmp_path / f"m{suffix}"))
        assert np.allclose(back.sigma_xy_m, 0.04, atol=1e-6) and np.allclose(
            back.sigma_z_m, 0.02, atol=1e-6
        )
    old = tmp_path / "old.csv"
    old.write_text("x,y,z\n0,0,0\n1,0,0\n0,1,0\n")
    assert load_map(old).sigma_xy_m is None
    with pytest.raises(InputError, match="sigma_xy_m"):
        LandmarkMap(np.zeros((3, 3)), sigma_xy_m=np.array([0.1, -1, 0.1]))


def test_simulate_writes_the_ground_truth_geometric_map(tmp_path, monkeypatch):
    from lunarloc.sim import simulate as sim
    from lunarloc.sim.site import SiteConfig, generate_site

    small = SiteConfig(size_m=12.0, n_rocks=40, n_craters=1, rover_start_xy=(-2.0, -2.0))
    monkeypatch.setattr(sim, "simulate_site", lambda seed, config=None: generate_site(seed, small))
    sim.simulate_dataset(1, 0, tmp_path)
    g = load_lac_grid(tmp_path / "geometric_map.npy")
    assert g.shape == (80, 80, 4)  # 12 m in 0.15 m cells
    assert g[:, :, 3].sum() > 0 and np.ptp(g[:, :, 2]) > 0
    assert np.allclose(g[1, 0, :2] - g[0, 0, :2], [LAC_CELL_M, 0]) and np.allclose(
        g[0, 1, :2] - g[0, 0, :2], [0, LAC_CELL_M]
    )


def test_online_loop_with_a_geometric_map_reference(tmp_path):
    """`run` takes its reference through load_reference: a LAC geometric map works as one."""
    from _loop_data import synthetic_traverse
    from lunarloc.pipeline.evaluation import DriftModel
    from lunarloc.config.run import RunConfig
    from lunarloc.pipeline.runner import run
    from lunarloc.pipeline.sources import TraverseCsvSource

    rocks, trav = synthetic_traverse(length_m=20.0)
    keep = np.all(np.abs(rocks[:, :2]) < 13.3, axis=1)
    np.save(
        tmp_path / "map.npy",
        landmarks_to_lac_grid(LandmarkMap(rocks[keep], sizes=np.full(keep.sum(), 0.1))),
    )
    ref = load_reference(tmp_path / "map.npy")
    assert ref.sigma_xy_m is not None and len(ref) > 0.8 * keep.sum()
    s = run(
        TraverseCsvSource(trav, DriftModel(0.1, 0.03)), ref, RunConfig.for_detections()
    ).summary()
    assert s["fixes"] >= 3
    assert s["max_accepted_fix_error_m"] < 0.2
    assert s["ate_corrected"]["rmse_m"] < s["ate_odometry"]["rmse_m"] / 2


def test_grid_header_checked_before_allocating(tmp_path):
    """A .npy whose header declares a huge grid, or more data than the file holds, is refused
    from its header alone."""
    from lunarloc.core.errors import FileFormatError
    from lunarloc.io.overhead import load_lac_grid

    huge = tmp_path / "huge.npy"
    with open(huge, "wb") as fh:
        np.lib.format.write_array_header_1_0(
            fh, {"descr": "<f8", "fortran_order": False, "shape": (100000, 100000, 4)}
        )
    with pytest.raises(FileFormatError, match="outside"):
        load_lac_grid(huge)
    short = tmp_path / "short.npy"
    with open(short, "wb") as fh:
        np.lib.format.write_array_header_1_0(
            fh, {"descr": "<f8", "fortran_order": False, "shape": (180, 180, 4)}
        )
        fh.write(b"\0" * 1000)
    with pytest.raises(FileFormatError, match="truncated"):
        load_lac_grid(short)
