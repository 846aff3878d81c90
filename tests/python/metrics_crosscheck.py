#!/usr/bin/env python3
"""Cross-check `colf-eval` against the reference implementations uORF uses.

Usage: metrics_crosscheck.py COLF_EVAL_BINARY WORK_DIR

Writes random and structured image and mask pairs as PNG (Pillow), runs
`colf-eval images` / `colf-eval masks` on each, and compares with
skimage.metrics.peak_signal_noise_ratio, skimage.metrics.structural_similarity
(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
channel_axis=-1) and sklearn.metrics.adjusted_rand_score, to 1e-4. Exits 1 on any
disagreement, naming the case.
"""

import json
import os
import subprocess
import sys

import numpy as np
from PIL import Image
from scipy.ndimage import gaussian_filter
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from sklearn.metrics import adjusted_rand_score

TOL = 1e-4


def save(path, array):
    Image.fromarray(array).save(path)
    return path


def load_rgb(path):
    """What colf reads: 8-bit values / 255, alpha dropped, grey replicated."""
    a = np.asarray(Image.open(path))
    if a.ndim == 2:
        a = np.stack([a] * 3, axis=-1)
    return a[..., :3].astype(np.float64) / 255.0


def load_labels(path):
    """What colf reads: grey value as label; one label per colour, black = 0."""
    a = np.asarray(Image.open(path))
    if a.ndim == 2:
        return a.reshape(-1).astype(np.int64)
    rgb = a[..., :3].reshape(-1, 3).astype(np.int64)
    return (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]


def run(binary, *args):
    out = subprocess.run([binary, *args], capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"colf-eval {' '.join(args)} failed: {out.stderr}")
    return json.loads(out.stdout)


def check(case, name, ours, ref, failures):
    if ref is None or ours is None or not np.isfinite(ref):
        same = (ours is None) and (ref is None or not np.isfinite(ref))
    else:
        same = abs(ours - ref) <= TOL
    status = "ok" if same else "MISMATCH"
    print(f"{case:28s} {name:7s} colf={ours!s:24s} reference={ref!s:24s} {status}")
    if not same:
        failures.append(f"{case} {name}")


def image_cases(rng):
    h, w = 64, 64
    yy, xx = np.mgrid[0:h, 0:w]
    gradient = np.stack([xx / (w - 1), yy / (h - 1), (xx + yy) / (w + h - 2)], axis=-1)
    gradient = (gradient * 255).round().astype(np.uint8)
    noisy = np.clip(gradient + rng.normal(0, 12, gradient.shape), 0, 255).round().astype(np.uint8)
    blocks = ((xx // 8 + yy // 8) % 2 * 200 + 20).astype(np.uint8)
    blocks = np.stack([blocks, 255 - blocks, blocks // 2], axis=-1)
    blurred = np.clip(gaussian_filter(blocks.astype(float), sigma=(1.2, 1.2, 0)), 0, 255)
    blurred = blurred.round().astype(np.uint8)
    rect = rng.integers(0, 256, (23, 37, 3), dtype=np.uint8)
    rect_pred = np.clip(rect.astype(int) + rng.integers(-30, 31, rect.shape), 0, 255).astype(np.uint8)
    rgba = np.concatenate([noisy, rng.integers(0, 256, (h, w, 1), dtype=np.uint8)], axis=-1)
    return [
        ("random-vs-random", rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
         rng.integers(0, 256, (h, w, 3), dtype=np.uint8)),
        ("gradient-plus-noise", noisy, gradient),
        ("checker-blurred", blurred, blocks),
        ("rect-37x23", rect_pred, rect),
        ("black-vs-white-11x11", np.zeros((11, 11, 3), np.uint8), np.full((11, 11, 3), 255, np.uint8)),
        ("identical", gradient, gradient.copy()),
        ("rgba-pred", rgba, gradient),
        ("grey-pred", gradient[..., 0].copy(), gradient),
    ]


def mask_cases(rng):
    h, w = 64, 48
    yy, xx = np.mgrid[0:h, 0:w]
    blocks = ((yy // 16) * 3 + xx // 16).astype(np.uint8)  # 12 regions, label 0 at top-left
    shifted = (((yy + 3) % h // 16) * 3 + (xx + 5) % w // 16).astype(np.uint8) * 10 + 7
    disc = (((yy - 30) ** 2 + (xx - 20) ** 2) < 150).astype(np.uint8) * 2
    disc += ((yy - 10) ** 2 + (xx - 35) ** 2 < 60).astype(np.uint8) * 5
    disc_pred = np.roll(disc, 2, axis=1)
    palette = np.array([[0, 0, 0], [255, 0, 0], [0, 200, 0], [10, 20, 250], [255, 255, 255]], np.uint8)
    colour_gt = palette[rng.integers(0, 5, (h, w))]
    big = rng.integers(0, 7, (256, 256)).astype(np.uint8)
    big_gt = np.where(rng.random((256, 256)) < 0.7, big, rng.integers(0, 7, (256, 256))).astype(np.uint8)
    return [
        ("random-labels", rng.integers(0, 6, (h, w), dtype=np.uint8),
         rng.integers(0, 6, (h, w), dtype=np.uint8)),
        ("blocks-shifted-renamed", shifted, blocks),
        ("discs-shifted", disc_pred, disc),
        ("pred-single-cluster", np.full((h, w), 3, np.uint8), disc),
        ("identical-renamed", (disc * 3 + 1).astype(np.uint8), disc),
        ("no-foreground", disc, np.zeros((h, w), np.uint8)),
        ("colour-gt-grey-pred", rng.integers(0, 5, (h, w), dtype=np.uint8), colour_gt),
        ("256x256-70%-agree", big, big_gt),
    ]


def main():
    binary, work = sys.argv[1], sys.argv[2]
    rng = np.random.default_rng(20230601)
    failures = []
    for case, pred, gt in image_cases(rng):
        p = save(os.path.join(work, f"{case}.pred.png"), pred)
        g = save(os.path.join(work, f"{case}.gt.png"), gt)
        ours = run(binary, "images", p, g)
        x, y = load_rgb(p), load_rgb(g)
        with np.errstate(divide="ignore"):
            ref_psnr = peak_signal_noise_ratio(y, x, data_range=1.0)
        ref_ssim = structural_similarity(
            x, y, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
            data_range=1.0, channel_axis=-1,
        )
        check(case, "psnr", ours["psnr"], float(ref_psnr), failures)
        check(case, "ssim", ours["ssim"], float(ref_ssim), failures)
    for case, pred, gt in mask_cases(rng):
        p = save(os.path.join(work, f"{case}.pred.mask.png"), pred)
        g = save(os.path.join(work, f"{case}.gt.mask.png"), gt)
        ours = run(binary, "masks", p, g)
        x, y = load_labels(p), load_labels(g)
        fg = y != 0
        ref_fg = adjusted_rand_score(y[fg], x[fg]) if fg.any() else None
        check(case, "ari", ours["ari"], float(adjusted_rand_score(y, x)), failures)
        check(case, "fg_ari", ours["fg_ari"], ref_fg, failures)
    if failures:
        sys.exit(f"colf-eval disagrees with scikit-image/scikit-learn on: {', '.join(failures)}")


if __name__ == "__main__":
    main()
