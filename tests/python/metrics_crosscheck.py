#!/usr/bin/env python3
"""Cross-check `colf-eval` against the reference implementations uORF uses.

Usage: metrics_crosscheck.py COLF_EVAL_BINARY WORK_DIR [DATASET_DIR ...]

Writes random and structured image and mask pairs as PNG (Pillow), runs
`colf-eval images` / `colf-eval masks` on each, and compares with
skimage.metrics.peak_signal_noise_ratio, skimage.metrics.structural_similarity
(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
channel_axis=-1) and sklearn.metrics.adjusted_rand_score, to 1e-4.

With DATASET_DIR (a colf-synth dataset), also runs `colf-eval --data DATASET_DIR --fast
--per-scene --renders R` and recomputes the segmentation scores from the saved masks as uORF's
evaluation code (models/uorf_eval_model.py) does: ari = adjusted_rand_score of view 0's full
label maps, fg_ari = the same over view 0's ground-truth foreground pixels, nv_ari =
adjusted_rand_score of the full label maps (background included) of each novel view, averaged
over the views, nv_fg_ari = the novel views' FG-ARI, averaged; then the means over scenes and
their population standard deviations (np.std), the summary's NAME and NAME_std. Where some
view shows a single object (a city street), also the FG-ARI split by objects in view
(fg_ari_multi, lone_object_views, lone_object_whole_share and their nv_ forms; docs/eval.md),
recomputed the same way; elsewhere, that none of it is written. And object_psnr and
background_psnr, the novel views' PSNR over the ground-truth object pixels and over the rest,
recomputed with skimage from the saved 8-bit renders (to 0.05 dB: colf-eval scores its renders
before they are rounded).

Exits 1 on any disagreement, naming the case.
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


def check(case, name, ours, ref, failures, tol=TOL):
    if ref is None or ours is None or not np.isfinite(ref):
        same = (ours is None) and (ref is None or not np.isfinite(ref))
    else:
        same = abs(ours - ref) <= tol
    status = "ok" if same else "MISMATCH"
    print(f"{case:28s} {name:13s} colf={ours!s:24s} reference={ref!s:24s} {status}")
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


def dataset_check(binary, work, data, failures):
    """The dataset scores of `colf-eval --data` against sklearn on the saved renders."""
    renders = os.path.join(work, "renders")
    doc = run(binary, "--data", data, "--fast", "-q", "--per-scene", "--renders", renders)
    rows = doc["per_scene"]
    if len(rows) < 2:
        sys.exit(f"{data}: the dataset check needs at least 2 scenes, found {len(rows)}")
    names = ("ari", "fg_ari", "nv_ari", "nv_fg_ari")
    per_scene = {name: [] for name in names}
    lone_rows, region_rows = [], []
    for row in rows:
        scene = row["scene"]
        views = sorted(f for f in os.listdir(os.path.join(data, scene)) if f.endswith(".mask.png"))
        if len(views) < 2:
            sys.exit(f"{data}/{scene}: no novel view with a mask")
        full, fg_only, objects, whole = [], [], [], []
        for v, name in enumerate(views):
            gt = load_labels(os.path.join(data, scene, name))
            pred = load_labels(os.path.join(renders, f"{scene}_v{v}.mask.png"))
            fg = gt != 0
            full.append(adjusted_rand_score(gt, pred))
            fg_only.append(adjusted_rand_score(gt[fg], pred[fg]) if fg.any() else None)
            objects.append(len(np.unique(gt[fg])))
            whole.append(len(np.unique(pred[fg])) == 1)
        lone_rows.append((row, fg_only, objects, whole))
        region_rows.append(region_psnrs(data, renders, scene, views))
        novel_fg = [x for x in fg_only[1:] if x is not None]
        ref = {
            "ari": full[0],
            "fg_ari": fg_only[0],
            "nv_ari": float(np.mean(full[1:])),
            "nv_fg_ari": float(np.mean(novel_fg)) if novel_fg else None,
        }
        for name in names:
            check(f"{scene}", name, row[name], ref[name], failures)
            if ref[name] is not None:
                per_scene[name].append(ref[name])
    # The field's NV-ARI includes the background: on these renders it must differ from the
    # FG-ARI of the same views, or the check above could not tell the two definitions apart.
    if all(abs(r["nv_ari"] - r["nv_fg_ari"]) < 1e-3 for r in rows):
        failures.append("dataset: nv_ari equals nv_fg_ari on every scene (definitions not told apart)")
    for name in names:
        check("dataset-summary", name, doc[name], float(np.mean(per_scene[name])), failures)
        check("dataset-summary", f"{name}_std", doc[f"{name}_std"], float(np.std(per_scene[name])),
              failures)
    lone_check(doc, lone_rows, failures)
    region_check(doc, rows, region_rows, failures)


def region_psnrs(data, renders, scene, views):
    """One scene's novel views' PSNR over the ground-truth object pixels and over the rest
    (skimage on the masked values), each averaged over the views where its region has pixels."""
    regions = {"object_psnr": [], "background_psnr": []}
    for v, name in enumerate(views[1:], start=1):
        gt_mask = load_labels(os.path.join(data, scene, name))
        gt = load_rgb(os.path.join(data, scene, name.replace(".mask.png", ".png"))).reshape(-1, 3)
        pred = load_rgb(os.path.join(renders, f"{scene}_v{v}.png")).reshape(-1, 3)
        for key, pixels in (("object_psnr", gt_mask != 0), ("background_psnr", gt_mask == 0)):
            if pixels.any():
                regions[key].append(peak_signal_noise_ratio(gt[pixels], pred[pixels], data_range=1.0))
    return {k: float(np.mean(v)) if v else None for k, v in regions.items()}


def region_check(doc, rows, region_rows, failures):
    """object_psnr and background_psnr recomputed from the saved renders. Those are 8-bit, while
    colf-eval scores its renders before they are rounded, so the tolerance is 0.05 dB: a wrong
    region or a wrong average moves the numbers by far more."""
    tol = 0.05
    for key in ("object_psnr", "background_psnr"):
        means = []
        for row, ref in zip(rows, region_rows):
            check(row["scene"], key, row.get(key), ref[key], failures, tol)
            if ref[key] is not None:
                means.append(ref[key])
        check("dataset-summary", key, doc.get(key), float(np.mean(means)), failures, tol)


def lone_check(doc, lone_rows, failures):
    """The FG-ARI split by objects in view (view 0 the input, the rest novel): written only
    where some view shows one object, then each scene's and the summary's fields recomputed."""
    any_lone = any(n == 1 for _, _, objects, _ in lone_rows for n in objects)
    fields = ("fg_ari_multi", "lone_object_views", "lone_object_whole_share", "nv_fg_ari_multi",
              "nv_lone_object_views", "nv_lone_object_whole_share")
    if not any_lone:
        if any(f in doc for f in fields):
            failures.append("lone: split written though no view shows a lone object")
        return
    multi_means = {"fg_ari_multi": [], "nv_fg_ari_multi": []}
    totals = {"": [0, 0], "nv_": [0, 0]}
    for row, fg_only, objects, whole in lone_rows:
        # A scene row carries the split only where one of its scored views shows a lone object.
        scene_lone = any(n == 1 for n in objects)
        if not scene_lone and "lone_object_views" in row:
            failures.append(f"lone-{row['scene']}: split written though no view shows a lone object")
        for prefix, vs in (("", [0]), ("nv_", range(1, len(objects)))):
            multi = [fg_only[v] for v in vs if objects[v] >= 2]
            lone = [v for v in vs if objects[v] == 1]
            n_whole = sum(whole[v] for v in lone)
            ref_multi = float(np.mean(multi)) if multi else None
            if ref_multi is not None:
                multi_means[f"{prefix}fg_ari_multi"].append(ref_multi)
            totals[prefix][0] += len(lone)
            totals[prefix][1] += n_whole
            if not scene_lone:
                continue
            check(f"lone-{row['scene']}", f"{prefix}fg_ari_multi", row.get(f"{prefix}fg_ari_multi"),
                  ref_multi, failures)
            for name, ref in ((f"{prefix}lone_object_views", len(lone)),
                              (f"{prefix}lone_object_whole", n_whole)):
                check(f"lone-{row['scene']}", name, row[name], ref, failures)
    for prefix in ("", "nv_"):
        means = multi_means[f"{prefix}fg_ari_multi"]
        check("lone-summary", f"{prefix}fg_ari_multi", doc.get(f"{prefix}fg_ari_multi"),
              float(np.mean(means)) if means else None, failures)
        views, n_whole = totals[prefix]
        check("lone-summary", f"{prefix}lone_object_views", doc.get(f"{prefix}lone_object_views"),
              views, failures)
        check("lone-summary", f"{prefix}lone_object_whole_share",
              doc.get(f"{prefix}lone_object_whole_share"), n_whole / views if views else None,
              failures)


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
    for i, data in enumerate(sys.argv[3:]):
        work_i = os.path.join(work, f"dataset{i}")
        os.makedirs(work_i, exist_ok=True)
        dataset_check(binary, work_i, data, failures)
    if failures:
        sys.exit(f"colf-eval disagrees with scikit-image/scikit-learn on: {', '.join(failures)}")


if __name__ == "__main__":
    main()
