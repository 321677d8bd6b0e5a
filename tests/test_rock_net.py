"""The rock network's numpy inference, its file format and the small-rock stage's hook."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lunarloc.core.errors import InputError
from lunarloc.perception.rock_net import (
    N_INPUTS,
    NET_PATH,
    RockNet,
    load_rock_net,
    make_layer,
    net_inputs,
    rock_net_at,
)
from lunarloc.perception.small_rocks import SmallRockConfig


def _ref_conv(x, W, b, d, s=1):
    """A direct 'same' convolution (cross-correlation, as torch's Conv2d), zero padded, at
    stride s (the outputs at every s-th row and column)."""
    cout, cin, k, _ = W.shape
    _, h, w = x.shape
    p = d * (k // 2)
    xp = np.pad(x, ((0, 0), (p, p), (p, p)))
    y = np.zeros((cout, h, w))
    for o in range(cout):
        for c in range(cin):
            for i in range(k):
                for j in range(k):
                    y[o] += W[o, c, i, j] * xp[c, i * d : i * d + h, j * d : j * d + w]
        y[o] += b[o]
    return y[:, ::s, ::s]


def _tiny(rng) -> RockNet:
    return RockNet(
        [
            make_layer(rng.normal(size=(3, N_INPUTS, 3, 3)), rng.normal(size=3)),
            make_layer(rng.normal(size=(4, 3, 3, 3)), rng.normal(size=4), pool=True),
            make_layer(rng.normal(size=(4, 4, 3, 3)), rng.normal(size=4), dilation=2),
            make_layer(rng.normal(size=(1, 4, 1, 1)), rng.normal(size=1)),
        ]
    )


def _strided(rng) -> RockNet:
    """The packaged network's form: the first layer at stride 2, no max-pool, wider layers
    (their products run in several runs of columns)."""
    return RockNet(
        [
            make_layer(rng.normal(size=(5, N_INPUTS, 3, 3)), rng.normal(size=5), stride=2),
            make_layer(rng.normal(size=(6, 5, 3, 3)), rng.normal(size=6)),
            make_layer(rng.normal(size=(6, 6, 3, 3)), rng.normal(size=6), dilation=2),
            make_layer(rng.normal(size=(1, 6, 1, 1)), rng.normal(size=1)),
        ]
    )


@pytest.mark.parametrize(
    "make, shape, out", [(_tiny, (13, 18), (6, 9)), (_strided, (13, 18), (7, 9))]
)
def test_inference_matches_a_reference_convolution(make, shape, out, monkeypatch):
    import lunarloc.perception.rock_net as rn

    monkeypatch.setattr(rn, "_COLUMNS", 40)  # several runs of columns per product
    rng = np.random.default_rng(0)
    net = make(rng)
    x = rng.normal(size=(N_INPUTS,) + shape).astype(np.float32)
    ref = x.astype(float)
    for i, L in enumerate(net.layers):
        if L.pool:
            c, h, w = ref.shape
            ref = (
                ref[:, : h // 2 * 2, : w // 2 * 2].reshape(c, h // 2, 2, w // 2, 2).max(axis=(2, 4))
            )
        ref = _ref_conv(ref, L.W.astype(float), L.b.astype(float), L.dilation, L.stride)
        if i < len(net.layers) - 1:
            ref = np.maximum(ref, 0)
    got = net.logits(x)
    assert got.shape == out
    np.testing.assert_allclose(got, ref[0], rtol=1e-4, atol=1e-4)


def test_probability_has_the_image_size_and_round_trips_through_a_file(tmp_path):
    rng = np.random.default_rng(1)
    net = _tiny(rng)
    img = rng.integers(0, 255, size=(40, 64)).astype(np.uint8)
    p = net.probability(img)
    assert p.shape == img.shape and p.dtype == np.float32
    assert np.all((p >= 0) & (p <= 1))
    net.save(tmp_path / "n.npz")
    again = load_rock_net(tmp_path / "n.npz")
    np.testing.assert_array_equal(again.probability(img), p)
    assert net_inputs(img).shape == (N_INPUTS, 40, 64)
    strided = _strided(rng)
    strided.save(tmp_path / "s.npz")
    assert [L.stride for L in load_rock_net(tmp_path / "s.npz").layers] == [2, 1, 1, 1]
    np.testing.assert_array_equal(
        load_rock_net(tmp_path / "s.npz").probability(img), strided.probability(img)
    )


def test_the_packaged_network_loads_and_runs():
    net = rock_net_at(None)
    assert NET_PATH.stat().st_size < 200_000
    img = np.full((60, 80), 90, np.uint8)
    img[28:33, 38:44] = 200  # a lit patch
    p = net.probability(img)
    assert p.shape == img.shape and np.isfinite(p).all()


def test_bad_model_files_give_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="rock net"):
        load_rock_net(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="rock net"):
        load_rock_net(tmp_path / "junk.npz")
    np.savez(tmp_path / "nolayers.npz", format=np.array(1))
    with pytest.raises(InputError, match="rock net"):
        load_rock_net(tmp_path / "nolayers.npz")
    rng = np.random.default_rng(2)

    def one_layer(name, n_inputs=2, **extra):
        path = tmp_path / name
        np.savez(
            path,
            format=np.array(1),
            n_layers=np.array(1),
            W0=rng.normal(size=(1, n_inputs, 3, 3)),
            b0=np.zeros(1),
            dilation0=np.array(1),
            pool0=np.array(False),
            **extra,
        )
        return path

    with pytest.raises(InputError, match="take 2 inputs"):
        load_rock_net(one_layer("shape.npz", n_inputs=3))
    with pytest.raises(InputError, match="stride"):
        load_rock_net(one_layer("stride.npz", stride0=np.array(0)))
    assert load_rock_net(one_layer("good.npz")) is not None  # the same file, well formed
    with pytest.raises(InputError, match="at least 4x4"):
        net_inputs(np.zeros((2, 50)))


def test_the_config_round_trips_and_checks_its_range(tmp_path):
    from lunarloc.config.run import RunConfig, load_config_file

    p = tmp_path / "c.json"
    p.write_text(
        json.dumps(
            {
                "detector": {
                    "small_rocks": {
                        "net_candidates": 12,
                        "net_min_score": 0.7,
                        "net_max_range_m": 3.5,
                        "net_path": "x.npz",
                        "net_window_margin": 1.0,
                    }
                }
            }
        )
    )
    cfg = load_config_file(p)[0]
    sr = cfg.detector.small_rocks
    assert RunConfig.from_dict(cfg.to_dict()).detector.small_rocks == sr
    assert (
        sr.net_candidates,
        sr.net_min_score,
        sr.net_max_range_m,
        sr.net_path,
        sr.net_window_margin,
    ) == (12, 0.7, 3.5, "x.npz", 1.0)
    assert SmallRockConfig().net_candidates == 10  # on by default (0: off)
    from lunarloc.core.errors import ConfigError

    with pytest.raises(ConfigError):
        SmallRockConfig(net_min_score=1.0)
    with pytest.raises(ConfigError):
        SmallRockConfig(net_window_margin=0.0)


def test_the_stage_takes_candidates_from_the_network_only_when_asked(tmp_path):
    """A lit 5 cm rock 2 m ahead on a textured plane: with the appearance candidates off, the
    packaged network's candidates hold one on the rock, and none come without net_candidates;
    a network that sees no rock anywhere (its output bias -30) gives none either."""
    from dataclasses import replace

    from test_small_rocks import BASELINE_M, CAM, _render, _uv

    from lunarloc.perception.camera import ipex_rig
    from lunarloc.perception.detector import Detector, DetectorConfig
    from lunarloc.perception.small_rocks import small_rock_candidates

    x, z = 0.3, 2.0
    L, R = _render(0.0, (x, z, 0.025, 0.025), seed=3)
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    hm = Detector(DetectorConfig(), CAM).height_map(L, R, T_ro)
    u, v = _uv(x, z, 0.0)
    cfg = SmallRockConfig(max_candidates=0, dark_contrast_z=0.0, net_candidates=5)

    def centres(c):
        cands = small_rock_candidates(L, hm.disparity, hm.scale, CAM.fx, BASELINE_M, c)
        return [(u0 + m.shape[1] / 2, v0 + m.shape[0] / 2) for u0, v0, m, *_ in cands]

    got = centres(cfg)
    assert any(abs(cu - u) < 15 and abs(cv - v) < 15 for cu, cv in got), (got, (u, v))
    assert centres(replace(cfg, net_candidates=0)) == []
    net = rock_net_at(None)
    blind = RockNet(net.layers[:-1] + [make_layer(net.layers[-1].W, [-30.0])])
    blind.save(tmp_path / "blind.npz")
    assert centres(replace(cfg, net_path=str(tmp_path / "blind.npz"))) == []


def test_the_network_candidates_windows_take_their_own_margin(monkeypatch):
    """net_window_margin sizes the windows of the network's candidates, window_margin the
    others' (bright and dark)."""
    from test_small_rocks import BASELINE_M, CAM, _render

    import lunarloc.perception.small_rocks as sr
    from lunarloc.perception.camera import ipex_rig
    from lunarloc.perception.detector import Detector, DetectorConfig

    L, R = _render(0.0, (0.3, 2.0, 0.025, 0.025), seed=3)
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    hm = Detector(DetectorConfig(), CAM).height_map(L, R, T_ro)
    seen = []
    real = sr._local_heights

    def spy(*args):
        seen.append(args[-1])  # the margin
        return real(*args)

    monkeypatch.setattr(sr, "_local_heights", spy)
    for net, bright in ((5, 0), (0, 40)):
        seen.clear()
        cfg = SmallRockConfig(
            max_candidates=bright,
            dark_contrast_z=0.0,
            net_candidates=net,
            net_window_margin=0.8,
            judge_min_score=0.0,
        )
        sr.detect_small_rocks(L, R, hm.disparity, hm.scale, CAM, BASELINE_M, cfg)
        assert seen and set(seen) == ({0.8} if net else {cfg.window_margin})
