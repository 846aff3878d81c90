"""FG-ARI view by view, split by how many objects each view shows.

Usage: per_view_fg_ari.py DATA RENDERS [VIEWS]

DATA is a colf-synth folder (scene_*/view_00V.mask.png), RENDERS the folder `colf-eval --renders`
wrote for it (SCENE_vV.mask.png, one colour a slot, black the background); VIEWS (default 0,1)
the views to score, comma-separated. For every scene and view: the ground-truth objects in view,
the predicted labels over their pixels, FG-ARI (scikit-learn's adjusted_rand_score over the
object pixels, as colf-eval computes it) and the share of object pixels the background wins.
Then the mean FG-ARI of the views with two objects or more, and the scores of the views with one:
with one ground-truth segment the ARI is 1 when one label covers it and 0 as soon as two do, so
those views score all or nothing (docs/eval.md).
"""

import glob
import os
import sys

import numpy as np
from PIL import Image
from sklearn.metrics import adjusted_rand_score


def labels(path):
    rgb = np.asarray(Image.open(path).convert("RGB")).reshape(-1, 3).astype(np.int64)
    return rgb[:, 0] * 65536 + rgb[:, 1] * 256 + rgb[:, 2]


def main(data, renders, views=(0, 1)):
    several, lone = [], []
    for scene_dir in sorted(glob.glob(os.path.join(data, "scene_*"))):
        scene = os.path.basename(scene_dir)
        parts = []
        for v in views:
            render = os.path.join(renders, f"{scene}_v{v}.mask.png")
            if not os.path.exists(render):
                continue
            truth = labels(os.path.join(scene_dir, f"view_{v:03d}.mask.png"))
            predicted = labels(render)
            objects = truth > 0
            if not objects.any():
                parts.append(f"v{v}: no objects")
                continue
            count = len(np.unique(truth[objects]))
            score = adjusted_rand_score(truth[objects], predicted[objects])
            to_background = float((predicted[objects] == 0).mean())
            (lone if count == 1 else several).append(score)
            parts.append(
                f"v{v}: {count} object{'s' * (count > 1)}, {len(np.unique(predicted[objects]))} labels, "
                f"FG-ARI {score:.3f}, {to_background:.0%} to the background"
            )
        if parts:
            print(f"{scene}  " + " | ".join(parts))
    if several:
        print(
            f"views with two objects or more: {len(several)}, FG-ARI "
            f"{min(several):.3f}-{max(several):.3f}, mean {np.mean(several):.3f}"
        )
    if lone:
        print(
            f"views with one object: {len(lone)}, FG-ARI "
            + ", ".join(f"{s:.0f}" for s in lone)
        )


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    chosen = tuple(int(v) for v in sys.argv[3].split(",")) if len(sys.argv) == 4 else (0, 1)
    main(sys.argv[1], sys.argv[2], chosen)
