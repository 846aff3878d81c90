"""Where each view's object pixels go, for two encodings of the same scenes side by side.

Usage: object_pixels.py DATA RENDERS_A RENDERS_B [VIEWS]

DATA is a colf-synth folder (scene_*/view_00V.mask.png); RENDERS_A and RENDERS_B are folders
`colf-eval --renders` wrote for it (SCENE_vV.mask.png, one colour a slot, black the background),
for example a three-view encoding and a one-view one; VIEWS (default 0,1,2) the views to score.
For every scene and view, and each encoding: FG-ARI (scikit-learn's adjusted_rand_score over the
object pixels, as colf-eval computes it), merges (ground-truth objects whose largest share goes
to a slot that is already the largest share of another object), splits (objects whose second
largest share, a slot's, holds at least a fifth of them) and the share of object pixels the
background wins. Then the means over all scored views. A scene whose RENDERS_B files are missing
for a view is skipped for that view.
"""

import glob
import os
import sys

import numpy as np
from sklearn.metrics import adjusted_rand_score

# The label maps are read as per_view_fg_ari.py reads them (one id per colour, black 0).
from per_view_fg_ari import labels


def where_pixels_go(truth, predicted):
    """(FG-ARI, merges, splits, share of object pixels the background wins)."""
    objects = truth > 0
    largest = []
    splits = 0
    for g in np.unique(truth[objects]):
        ids, counts = np.unique(predicted[truth == g], return_counts=True)
        order = np.argsort(-counts)
        largest.append(ids[order[0]])
        if len(counts) > 1 and ids[order[1]] != 0 and counts[order[1]] >= 0.2 * counts.sum():
            splits += 1
    slots = [i for i in largest if i != 0]
    merges = len(slots) - len(set(slots))
    score = adjusted_rand_score(truth[objects], predicted[objects])
    return score, merges, splits, float((predicted[objects] == 0).mean())


def main(data, renders_a, renders_b, views=(0, 1, 2)):
    totals = {renders_a: [], renders_b: []}
    for scene_dir in sorted(glob.glob(os.path.join(data, "scene_*"))):
        scene = os.path.basename(scene_dir)
        parts = []
        for v in views:
            paths = [os.path.join(r, f"{scene}_v{v}.mask.png") for r in (renders_a, renders_b)]
            if not all(os.path.exists(p) for p in paths):
                continue
            truth = labels(os.path.join(scene_dir, f"view_{v:03d}.mask.png"))
            if not (truth > 0).any():
                continue
            cells = []
            for renders, path in zip((renders_a, renders_b), paths):
                row = where_pixels_go(truth, labels(path))
                totals[renders].append(row)
                cells.append(f"{row[0]:.2f} m{row[1]} s{row[2]} bg {row[3]:.2f}")
            parts.append(f"v{v} " + " | ".join(cells))
        if parts:
            print(f"{scene}  " + "   ".join(parts))
    for renders, rows in totals.items():
        if rows:
            a = np.array(rows)
            print(
                f"{renders}: {len(rows)} views, FG-ARI {a[:, 0].mean():.3f}, merges "
                f"{int(a[:, 1].sum())}, splits {int(a[:, 2].sum())}, background wins "
                f"{a[:, 3].mean():.1%} of the object pixels"
            )


if __name__ == "__main__":
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__)
    chosen = tuple(int(v) for v in sys.argv[4].split(",")) if len(sys.argv) == 5 else (0, 1, 2)
    main(sys.argv[1], sys.argv[2], sys.argv[3], chosen)
