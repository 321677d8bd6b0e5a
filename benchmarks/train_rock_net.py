"""Train the small-rock stage's rock network (lunarloc.perception.rock_net) on the simulator's
labelled images of rendered LAC-look sites.

Usage
-----
    # 1. render the training sites (LAC look, as sim_heldout.py renders them), sunlit and lamp-lit
    python benchmarks/sim_heldout.py --seeds 430 ... 452 --render-only --out-dir TRAIN
    python benchmarks/sim_heldout.py --seeds 530 ... 539 --lighting lamps --render-only \
        --out-dir TRAIN
    # 2. half-resolution left images and their labels, one .npz per archive (in --cache)
    python benchmarks/train_rock_net.py extract TRAIN/*.lac --cache CACHE
    # 3. fit (needs torch, CPU build: pip install torch numpy, in a scratch environment; the
    #    package itself never imports torch) and write the model (plain arrays)
    python benchmarks/train_rock_net.py fit CACHE/site4*.npz CACHE/site53*.npz --out MODEL.npz
    # 4. offline check on other sites' images (numpy inference, the package's code): pixel
    #    precision / recall and the share of small rocks with a peak above the threshold
    python benchmarks/train_rock_net.py check DEVCACHE/site30*.npz [--model MODEL.npz]

Data recipe
-----------
Training sites: 430-452 (sun+lamps; /tmp/s21/h33p/train, /tmp/s22/h34a/train) and 530-539
(``--lighting lamps``; /tmp/s23/lamps/train), 60 s traverses of 31 front stereo frames each.

Per frame: the left grey image resized to half resolution (640x360, INTER_AREA) and a label
image of the same size from the simulator's semantic image of the left camera
(``semantic_to_rock_id``, its pixel at the top-left of each 2x2 block): 0 ground, 1 a rock of
radius <= SMALL_RADIUS_M, 2 a larger rock, 3 anything else (sky, lander: left out of the loss).
The rows above the first row holding ground are dropped.

Fit: random crops (CROP x CROP half-resolution pixels, half of them centred on a small rock's
pixel), the network of ``--widths`` (rock_net's layers: 3x3 conv, ReLU; a 2x2 max-pool before
the second layer; the third dilated by 2; a 1x1 output), binary cross-entropy of rock (labels 1
and 2) against ground, the small rocks' pixels weighted SMALL_WEIGHT, Adam; torch's CPU build,
one thread, seeded (``--seed``). The exported file's logits are checked against torch's on one
frame (the numpy inference is what the package runs).

The packaged ``perception/rock_net.npz``: ``fit CACHE/site4[3-5]*.npz CACHE/site53*.npz --steps
6000 --stride-first --lamp-share 0.5`` (widths 8 12 12, the first layer at stride 2, half the crops
from the 10 lamp-lit sites, 2349 parameters, seed 0; torch 2.13.0 CPU build, about 140 s CPU):
1023 frames of 33 sites (430-452, 530-539), the bottom 264 rows of each (the fewest any site
keeps). Offline (``check``) and in the detector: docs/perception-status.md, "The rock network".
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from lunarloc.perception.rock_net import N_INPUTS, RockNet, load_rock_net, make_layer, net_inputs

SMALL_RADIUS_M = 0.05
SMALL_WEIGHT = 3.0
CROP = 96
OTHER = 3


def extract(path: Path, cache: Path) -> Path:
    """Half-resolution left images and labels of every frame of one archive."""
    import cv2

    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.sim.render import SEM_GROUND, semantic_to_rock_id

    out = cache / f"{path.stem}.npz"
    if out.exists():
        return out
    t0 = time.process_time()
    imgs, labs = [], []
    with LacArchive(path) as ar:
        t = ar.custom("rocks")
        ids = np.asarray(t["id"], int)
        radii = np.asarray(t["radius"], float)
        cam = "FrontLeft"
        for f in ar.frame_numbers:
            f = int(f)
            if ar.image_member(cam, f) is None or ar.image_member(cam, f, "semantic") is None:
                continue
            g = ar.grayscale(cam, f)
            sem = ar.semantic(cam, f)
            H, W = g.shape
            small = cv2.resize(g, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
            s = np.asarray(sem)[: H // 2 * 2 : 2, : W // 2 * 2 : 2]
            rid = semantic_to_rock_id(s)
            lab = np.full(s.shape, OTHER, np.uint8)
            lab[s == SEM_GROUND] = 0
            rock = rid >= 0
            rr = np.full(int(rid.max()) + 2 if rock.any() else 1, np.inf)
            ok = ids < rr.size
            rr[ids[ok]] = radii[ok]
            r_px = np.where(rock, rr[np.where(rock, rid, 0)], np.inf)
            lab[rock & (r_px <= SMALL_RADIUS_M)] = 1
            lab[rock & (r_px > SMALL_RADIUS_M)] = 2
            imgs.append(small)
            labs.append(lab)
    imgs_a, labs_a = np.stack(imgs), np.stack(labs)
    ground_rows = np.flatnonzero((labs_a == 0).any(axis=(0, 2)))
    r0 = int(ground_rows[0]) // 4 * 4 if ground_rows.size else 0
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, image=imgs_a[:, r0:], label=labs_a[:, r0:], row0=np.array(r0))
    n1 = int((labs_a == 1).sum())
    print(
        f"{path.name}: {len(imgs)} frames, rows from {r0}, small-rock pixels {n1}, "
        f"{time.process_time() - t0:.1f} s CPU",
        file=sys.stderr,
    )
    return out


def _load(paths: list[Path], with_lamps: bool = False):
    X, Y, lamps = [], [], []
    for p in paths:
        with np.load(p) as z:
            X.append(z["image"])
            Y.append(z["label"])
        lamps.append(np.full(len(X[-1]), "_lamps_" in p.name))
    h = min(x.shape[1] for x in X)
    out = np.concatenate([x[:, -h:] for x in X]), np.concatenate([y[:, -h:] for y in Y])
    return out + (np.concatenate(lamps),) if with_lamps else out


def _draw(cdf: np.ndarray, rng) -> int:
    """An index drawn from a cumulative distribution."""
    return min(int(np.searchsorted(cdf, rng.random() * cdf[-1], side="right")), len(cdf) - 1)


def _torch():
    try:
        import torch
    except ImportError as e:  # pragma: no cover
        raise SystemExit(
            "train_rock_net.py fit needs torch (CPU build), in a scratch environment: "
            "python -m venv ENV && ENV/bin/pip install torch numpy"
        ) from e
    return torch


def fit(
    paths: list[Path],
    out: Path,
    widths: tuple[int, ...],
    steps: int,
    seed: int,
    stride_first: bool = False,
    lamp_share: float | None = None,
) -> None:
    torch = _torch()
    nn = torch.nn
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    imgs, labs, lamps = _load(paths, with_lamps=True)
    t0 = time.process_time()
    inputs = np.stack([net_inputs(im) for im in imgs])  # (N, C, h, w)
    print(f"{len(imgs)} frames {imgs.shape[1:]}, inputs {time.process_time() - t0:.0f} s CPU")
    w1, w2, w3 = widths
    convs = nn.ModuleList(
        [
            nn.Conv2d(N_INPUTS, w1, 3, padding=1, stride=2 if stride_first else 1),
            nn.Conv2d(w1, w2, 3, padding=1),
            nn.Conv2d(w2, w3, 3, padding=2, dilation=2),
            nn.Conv2d(w3, 1, 1),
        ]
    )
    # a 2x2 max-pool before the second layer, or (stride_first) the first layer at every second
    # pixel of every second row instead: it costs a quarter (no pool)
    pools = (False, not stride_first, False, False)

    def forward(x, up=True):
        for i, c in enumerate(convs):
            if pools[i]:
                x = torch.nn.functional.max_pool2d(x, 2)
            x = c(x)
            if i < len(convs) - 1:
                x = torch.relu(x)
        if not up:
            return x
        return torch.nn.functional.interpolate(
            x, scale_factor=2, mode="bilinear", align_corners=False
        )

    opt = torch.optim.Adam(convs.parameters(), lr=3e-3)
    N, _, h, w = inputs.shape
    small_pix = np.argwhere(labs == 1)
    # uniform draws, or (lamp_share) lamp_share of the crops from the lamp-lit sites' frames
    # (and of the small-rock-centred crops from their small rocks' pixels)
    pf = ps = None
    if lamp_share is not None and lamps.any() and (~lamps).any():
        pf = np.where(lamps, lamp_share / lamps.sum(), (1 - lamp_share) / (~lamps).sum())
        lp = lamps[small_pix[:, 0]]
        ps = np.where(lp, lamp_share / max(lp.sum(), 1), (1 - lamp_share) / max((~lp).sum(), 1))
        pf, ps = np.cumsum(pf / pf.sum()), np.cumsum(ps / ps.sum())  # drawn by inverse CDF
    B = 16
    t0 = time.process_time()
    for step in range(steps):
        if step == int(steps * 0.7):
            for g in opt.param_groups:
                g["lr"] = 1e-3
        xb, yb = [], []
        for b in range(B):
            if b % 2 == 0 and len(small_pix):
                i = rng.integers(len(small_pix)) if ps is None else _draw(ps, rng)
                n, y, x = small_pix[i]
                y0 = int(np.clip(y - rng.integers(8, CROP - 8), 0, h - CROP))
                x0 = int(np.clip(x - rng.integers(8, CROP - 8), 0, w - CROP))
            else:
                n = rng.integers(N) if pf is None else _draw(pf, rng)
                y0, x0 = int(rng.integers(0, h - CROP + 1)), int(rng.integers(0, w - CROP + 1))
            xb.append(inputs[n, :, y0 : y0 + CROP, x0 : x0 + CROP])
            yb.append(labs[n, y0 : y0 + CROP, x0 : x0 + CROP])
        xt = torch.from_numpy(np.stack(xb))
        ya = np.stack(yb)
        target = torch.from_numpy(((ya == 1) | (ya == 2)).astype(np.float32))
        wt = np.where(ya == OTHER, 0.0, np.where(ya == 1, SMALL_WEIGHT, 1.0)).astype(np.float32)
        logit = forward(xt)[:, 0]
        loss = torch.nn.functional.binary_cross_entropy_with_logits(
            logit, target, weight=torch.from_numpy(wt), reduction="sum"
        ) / max(float(wt.sum()), 1.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 200 == 0 or step == steps - 1:
            print(f"step {step} loss {loss.item():.4f} {time.process_time() - t0:.0f} s CPU")
    layers = []
    for i, c in enumerate(convs):
        layers.append(
            make_layer(
                c.weight.detach().numpy(),
                c.bias.detach().numpy(),
                dilation=c.dilation[0],
                pool=pools[i],
                stride=c.stride[0],
            )
        )
    net = RockNet(layers)
    # the numpy inference against torch's on one frame (the exported file is what the package
    # runs): the last layer's logits
    with torch.no_grad():
        ref = forward(torch.from_numpy(inputs[:1]), up=False)[0, 0].numpy()
    got = net.logits(inputs[0])
    print(f"numpy vs torch: max |d logit| {np.abs(ref - got).max():.2e}; params {net.n_params}")
    net.save(out)
    print(f"wrote {out} ({out.stat().st_size} bytes)")


def check(paths: list[Path], model: Path | None, thresholds=(0.3, 0.5, 0.7)) -> None:
    """Pixel precision/recall of rock (all rocks) and, per small rock (label 1 component of at
    least 6 half-resolution pixels, ~ at 0.8-4 m), whether its pixels reach each threshold."""
    import cv2

    net = load_rock_net(model) if model else None
    if net is None:
        from lunarloc.perception.rock_net import rock_net_at

        net = rock_net_at(None)
    for p in paths:
        imgs, labs = _load([p])
        t0 = time.process_time()
        stats = {t: [0, 0, 0, 0, 0] for t in thresholds}  # tp, fp, fn, small hit, small total
        for im, lab in zip(imgs, labs):
            pr = net.probability(im)
            valid = lab != OTHER
            rock = (lab == 1) | (lab == 2)
            n_c, comp = cv2.connectedComponents((lab == 1).astype(np.uint8), connectivity=8)
            sizes = np.bincount(comp.ravel(), minlength=n_c)
            for t in thresholds:
                pos = (pr >= t) & valid
                s = stats[t]
                s[0] += int((pos & rock).sum())
                s[1] += int((pos & ~rock).sum())
                s[2] += int((~pos & rock).sum())
                mx = np.zeros(n_c)
                np.maximum.at(mx, comp.ravel(), pr.ravel())
                big = np.flatnonzero(sizes >= 6)
                big = big[big > 0]
                s[3] += int((mx[big] >= t).sum())
                s[4] += int(big.size)
        dt = (time.process_time() - t0) / max(len(imgs), 1)
        for t in thresholds:
            tp, fp, fn, sh, st = stats[t]
            print(
                f"{p.stem} t={t}: pixel P {tp / max(tp + fp, 1):.3f} R {tp / max(tp + fn, 1):.3f}; "
                f"small rocks reached {sh}/{st} = {sh / max(st, 1):.3f}; {dt * 1e3:.0f} ms/frame"
            )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("extract")
    e.add_argument("archives", nargs="+", type=Path)
    e.add_argument("--cache", type=Path, required=True)
    f = sub.add_parser("fit")
    f.add_argument("caches", nargs="+", type=Path)
    f.add_argument("--out", type=Path, required=True)
    f.add_argument("--widths", type=int, nargs=3, default=(8, 12, 12))
    f.add_argument("--steps", type=int, default=1500)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument(
        "--stride-first", action="store_true", help="the first layer at stride 2 (no max-pool)"
    )
    f.add_argument(
        "--lamp-share", type=float, default=None, help="share of crops from lamp-lit sites"
    )
    c = sub.add_parser("check")
    c.add_argument("caches", nargs="+", type=Path)
    c.add_argument("--model", type=Path)
    a = ap.parse_args(argv)
    if a.cmd == "extract":
        for p in a.archives:
            extract(p, a.cache)
    elif a.cmd == "fit":
        fit(a.caches, a.out, tuple(a.widths), a.steps, a.seed, a.stride_first, a.lamp_share)
    else:
        check(a.caches, a.model)


if __name__ == "__main__":
    main()
