"""Where the ground-truth cars' pixels go in a city evaluation's renders.

Usage: city_car_pixels.py DATA RENDERS [CONTEXT_VIEWS]

DATA is a colf-synth city folder (scene_*/view_00V.png and .mask.png), RENDERS the folder
`colf-eval --renders` wrote for it (SCENE_vV.mask.png, one colour a slot, black the background);
CONTEXT_VIEWS (default 2) views 0.. are the encoded ones, the rest novel. For every car (a
ground-truth mask colour) with 4 pixels or more in a view: the share of its pixels the
background wins, the share its best slot wins and the rest (other slots); whether several cars
of that view share a best slot; and whether a novel view's best slot is the car's best slot in
the first context view that shows it. Prints one line per kind of view.
"""

import glob
import os
import sys

import numpy as np
from PIL import Image


def labels(path):
    rgb = np.asarray(Image.open(path).convert("RGB")).reshape(-1, 3).astype(np.int64)
    return rgb[:, 0] * 65536 + rgb[:, 1] * 256 + rgb[:, 2]


def main(data, renders, context_views=2):
    shares = {"context": np.zeros(3), "novel": np.zeros(3)}
    cars = {"context": 0, "novel": 0}
    sharing = {"context": 0, "novel": 0}
    same_slot = [0, 0]
    for scene in sorted(glob.glob(os.path.join(data, "scene_*"))):
        name = os.path.basename(scene)
        context_slot = {}
        for v in range(len(glob.glob(f"{scene}/view_*.mask.png"))):
            truth = labels(f"{scene}/view_{v:03d}.mask.png")
            drawn = labels(f"{renders}/{name}_v{v}.mask.png")
            kind = "context" if v < context_views else "novel"
            best = {}
            for car in np.unique(truth):
                pixels = drawn[truth == car]
                if car == 0 or len(pixels) < 4:
                    continue
                background = np.mean(pixels == 0)
                slots, counts = np.unique(pixels[pixels != 0], return_counts=True)
                top = counts.max() / len(pixels) if len(slots) else 0.0
                shares[kind] += np.array([background, top, 1 - background - top]) * len(pixels)
                cars[kind] += 1
                best[car] = slots[counts.argmax()] if len(slots) else None
            winners = [s for s in best.values() if s is not None]
            sharing[kind] += sum(winners.count(s) > 1 for s in winners)
            for car, slot in best.items():
                if kind == "context":
                    context_slot.setdefault(car, slot)
                elif slot is not None and context_slot.get(car) is not None:
                    same_slot[0] += slot == context_slot[car]
                    same_slot[1] += 1
    for kind in shares:
        s = shares[kind] / max(shares[kind].sum(), 1)
        print(
            f"{kind} views: {cars[kind]} car appearances; pixels: background {s[0]:.3f}, "
            f"best slot {s[1]:.3f}, other slots {s[2]:.3f}; "
            f"{sharing[kind]} cars share their best slot with another car"
        )
    print(f"novel views: the best slot is the car's context-view slot in {same_slot[0]} of {same_slot[1]}")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) == 4 else 2)
