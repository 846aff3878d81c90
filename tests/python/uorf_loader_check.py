"""Reads a `colf-synth --layout uorf` folder the way uORF's own loaders do and checks each
convention against colf's ground truth (run by tests/uorf_layout.rs and tests/blender_synth.rs).

uORF (KovenYu/uORF) is not imported: torch is not needed for what its loaders compute, so the
steps of `data/multiscenes_dataset.py` and `data/multiscenes_manip_dataset.py` are redone here
with numpy and Pillow, step by step (file selection, PIL grey conversion, nearest resize to
`mask_size`, `greyscale_dict = unique(sorted)`, `bg_color = greyscale_dict[1]` or `[0]`,
`fg_idx`, `mask_idx`, `obj_idxs`, `np.loadtxt` of `_RT.txt`, `_azi_rot.txt` and the movement
file), with the options of `scripts/eval_nvs_seg_clevr.sh` / `eval_scene_manip.sh`
(`--n_img_each_scene` = the views, `mask_size` 128, no `--fixed_locality`).

usage: uorf_loader_check.py DIR N_SCENES N_VIEWS [--gt GT_DIR] [--move K DX DY]

GT_DIR (optional) holds colf's ids of every view, rendered by colf for the written cameras:
`{stem}_ids.png` (0 = background, k = object k of scNNNN_scene.json) and, with a move,
`{stem}_providing_ids.png` (the providing scene's objects seen from this view's camera).
Without it the ids come from the written masks through scene.json's `uorf_mask_levels`, and
are checked against the objects' `visible_pixels` and projected centres.
Prints one `... ok` line per check; exits 1 at the first failure.
"""

import glob
import json
import math
import os
import sys

import numpy as np
from PIL import Image

MASK_SIZE = 128  # uORF's --mask_size default (the eval scripts' frustum size)
SUFFIXES = ["_mask.png", "_mask_for_moving.png", "_moved.png", "_mask_for_bg.png",
            "_mask_for_providing_bg.png", "_changed.png", "_providing_bg.png"]


def fail(msg):
    print("FAIL: " + msg)
    sys.exit(1)


def check(cond, msg):
    if not cond:
        fail(msg)


def ok(msg):
    print(msg + " ok")


def scene_files(root, n_scenes, n_views):
    """uORF's file selection: every png minus the suffix sets, sorted, then per scene the
    names containing `sc{:04d}`, the first n_img_each_scene of them."""
    images = set(glob.glob(os.path.join(root, "*.png")))
    for suffix in SUFFIXES:
        images -= set(glob.glob(os.path.join(root, "*" + suffix)))
    names = sorted(images)
    return [[x for x in names if "sc{:04d}".format(i) in x][:n_views] for i in range(n_scenes)]


def grey_for_uorf(path):
    """`Image.open(p).convert('RGB').convert('L')`, resized NEAREST to mask_size."""
    img = Image.open(path).convert("RGB").convert("L")
    img = img.resize((MASK_SIZE, MASK_SIZE), Image.NEAREST)
    return np.asarray(img)


def upsample(ids):
    """Ground-truth ids at mask_size, as PIL's nearest resize maps pixels."""
    h, w = ids.shape
    img = Image.fromarray(ids).resize((MASK_SIZE, MASK_SIZE), Image.NEAREST)
    return np.asarray(img)


def uorf_mask(path):
    """What multiscenes_dataset.py derives from `_mask.png`: (grey, fg_idx, mask_idx, levels)."""
    grey = grey_for_uorf(path)
    flat = grey.reshape(-1)
    levels = np.unique(flat)  # greyscale_dict, sorted
    check(len(levels) >= 2, f"{path}: one grey level: uORF's greyscale_dict[1] fails")
    bg_color = levels[1]
    fg_idx = flat != bg_color
    mask_idx = (flat[:, None] == levels[None, :]).astype(np.uint8).argmax(axis=1)
    obj_idxs = [grey == lv for lv in levels]
    check(all((o.reshape(-1) == (mask_idx == i)).all() for i, o in enumerate(obj_idxs)),
          f"{path}: obj_idxs and mask_idx disagree")
    return grey, fg_idx, mask_idx, levels


def two_level(path, background_true):
    """multiscenes_manip_dataset.py on a two-level mask: greyscale_dict[0] is the
    background; returns fg (mask != bg) or bg (mask == bg) per pixel."""
    grey = grey_for_uorf(path)
    bg_color = np.unique(grey.reshape(-1))[0]
    return (grey == bg_color) if background_true else (grey != bg_color)


def same_partition(a, b):
    """Whether label maps a and b split the pixels identically (one-to-one labels)."""
    pairs = set(zip(a.tolist(), b.tolist()))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


def azimuth_rotation(rt):
    """`_azi_rot.txt` as colf defines it: about world +Z by the camera centre's azimuth."""
    phi = math.atan2(rt[1, 3], rt[0, 3])
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def project(rt, point, w, h):
    """uORF's Projection: fx = 350/320·W, fy = 350/240·H, bias (size − 1)/2, OpenCV axes."""
    p = np.linalg.inv(rt) @ np.append(point, 1.0)
    if p[2] <= 0:
        return None
    u = 350.0 / 320.0 * w * p[0] / p[2] + (w - 1) / 2.0
    v = 350.0 / 240.0 * h * p[1] / p[2] + (h - 1) / 2.0
    return int(round(u)), int(round(v))


def main():
    args = sys.argv[1:]
    root, n_scenes, n_views = args[0], int(args[1]), int(args[2])
    gt = args[args.index("--gt") + 1] if "--gt" in args else None
    move = None
    if "--move" in args:
        i = args.index("--move")
        move = (int(args[i + 1]), float(args[i + 2]), float(args[i + 3]))
    scenes = scene_files(root, n_scenes, n_views)
    centres_hit = centres_total = 0
    for s, files in enumerate(scenes):
        check(len(files) == n_views, f"scene {s}: uORF's loader finds {len(files)} views")
        doc = json.load(open(os.path.join(root, f"sc{s:04d}_scene.json")))
        objects = doc["objects"]
        table = doc["uorf_mask_levels"]
        for v, path in enumerate(files):
            stem = path[: -len(".png")]
            check(stem.endswith(f"_sc{s:04d}_az{v:02d}"), f"{path}: not view {v} of scene {s}")
            img = np.asarray(Image.open(path).convert("RGB"))
            h, w = img.shape[:2]
            # Cameras: _RT.txt and _azi_rot.txt, as np.loadtxt reads them.
            rt = np.loadtxt(stem + "_RT.txt")
            check(rt.shape == (4, 4) and np.allclose(rt[3], [0, 0, 0, 1]), f"{stem}_RT.txt")
            check(np.allclose(rt[:3, :3] @ rt[:3, :3].T, np.eye(3), atol=1e-9), f"{stem}_RT.txt")
            azi = np.loadtxt(stem + "_azi_rot.txt")
            check(azi.shape == (3, 3), f"{stem}_azi_rot.txt: shape {azi.shape}")
            check(np.abs(azi - azimuth_rotation(rt)).max() < 1e-12, f"{stem}_azi_rot.txt")
            # The model's nss2cam0 = inverse(azi_rot): a rotation about +Z that puts the
            # camera at azimuth 0 (on +X), leaving heights alone.
            nss2cam0 = np.linalg.inv(azi)
            local = nss2cam0 @ rt[:3, 3]
            check(abs(local[1]) < 1e-9 and local[0] > 0, f"{stem}: camera at {local}")
            check(abs(local[2] - rt[2, 3]) < 1e-12, f"{stem}: azi_rot is not about +Z")
            check(abs(np.linalg.det(azi) - 1) < 1e-12, f"{stem}: azi_rot is not a rotation")
            # Masks as uORF's loader reads them, against colf's ids.
            grey, fg_idx, mask_idx, levels = uorf_mask(stem + "_mask.png")
            lv = np.array(table[v], dtype=np.uint8)
            check(levels[1] == lv[0], f"{stem}_mask.png: background level {lv[0]} is not "
                  f"uORF's bg_color {levels[1]}")
            native = np.asarray(Image.open(stem + "_mask.png").convert("L"))
            ids = np.full(native.shape, 255, dtype=np.int32)
            for k, level in enumerate(lv):
                ids[native == level] = k
            check((ids != 255).all(), f"{stem}_mask.png: a grey level no id has")
            if gt is not None:
                name = os.path.join(gt, os.path.basename(stem) + "_ids.png")
                truth = np.asarray(Image.open(name))
                check((truth == ids).all(), f"{stem}_mask.png: ids differ from colf's render")
            for k, o in enumerate(objects):
                n = int((ids == k + 1).sum())
                check(n == o["visible_pixels"][v], f"{stem}: object {k + 1} has {n} pixels, "
                      f"scene.json says {o['visible_pixels'][v]}")
                if n > 0:
                    uv = project(rt, np.array(o["position"]), w, h)
                    centres_total += 1
                    if uv and 0 <= uv[0] < w and 0 <= uv[1] < h and ids[uv[1], uv[0]] == k + 1:
                        centres_hit += 1
            big = upsample(ids.astype(np.uint8)).reshape(-1)
            check((fg_idx == (big != 0)).all(), f"{stem}_mask.png: uORF's fg_idx is not colf's "
                  f"foreground ({int((fg_idx != (big != 0)).sum())} pixels differ)")
            check(same_partition(mask_idx, big), f"{stem}_mask.png: uORF's mask_idx does not "
                  "split the pixels as colf's ids do")
            if move is None:
                continue
            # Scene manipulation, as multiscenes_manip_dataset.py reads it.
            obj, dx, dy = move
            for suffix in ["_moved.png", "_changed.png", "_providing_bg.png"]:
                other = np.asarray(Image.open(stem + suffix).convert("RGB"))
                check(other.shape == img.shape, f"{stem}{suffix}: shape {other.shape}")
            small = ids
            fg = two_level(stem + "_mask_for_moving.png", False).reshape(-1)
            check((fg == (big == obj)).all(), f"{stem}_mask_for_moving.png: not object {obj}")
            bg = two_level(stem + "_mask_for_bg.png", True).reshape(-1)
            check((bg == (big == 0)).all(), f"{stem}_mask_for_bg.png: not the background")
            pbg = two_level(stem + "_mask_for_providing_bg.png", True)
            if gt is not None:
                name = os.path.join(gt, os.path.basename(stem) + "_providing_ids.png")
                ptruth = upsample(np.asarray(Image.open(name)))
                check((pbg == (ptruth == 0)).all(),
                      f"{stem}_mask_for_providing_bg.png: not the providing view's background")
            # The changed view shows the providing scene's background: where neither scene
            # has an object, it is much closer to the providing image than to this one.
            changed = np.asarray(Image.open(stem + "_changed.png").convert("RGB")).astype(float)
            provider = np.asarray(Image.open(stem + "_providing_bg.png").convert("RGB"))
            pbg_small = np.asarray(Image.fromarray(pbg.astype(np.uint8)).resize((w, h),
                                                                                Image.NEAREST))
            if doc["uorf_providing_bg_scene"] == s:
                # A single scene provides its own background.
                diff = np.abs(changed - provider).mean()
                check(diff < 2.0, f"{stem}_changed.png: differs from its own scene by {diff}")
                continue
            both = (small == 0) & (pbg_small > 0)
            check(both.sum() > 0.3 * w * h, f"{stem}: too little shared background")
            d_provider = np.abs(changed - provider)[both].mean()
            d_own = np.abs(changed - img)[both].mean()
            check(d_provider < d_own, f"{stem}_changed.png: background closer to its own scene "
                  f"({d_own:.2f}) than to the providing scene ({d_provider:.2f})")
            on_objects = np.abs(changed - img)[small != 0].mean()
            check(on_objects < np.abs(changed - provider)[small != 0].mean(),
                  f"{stem}_changed.png: objects are not this scene's")
        if move is not None:
            with open(os.path.join(os.path.dirname(files[0]), f"{s:03d}_movement.txt")) as f:
                x, y = float(f.readline()), float(f.readline())
            check((x, y) == (move[1], move[2]), f"{s:03d}_movement.txt: {x}, {y}")
        ok(f"scene {s}: files, cameras, azi_rot, masks" + (", manipulation" if move else ""))
    check(centres_hit >= 0.75 * centres_total,
          f"only {centres_hit} of {centres_total} visible centres land on their object")
    ok(f"projection: {centres_hit} of {centres_total} visible object centres")


if __name__ == "__main__":
    main()
