"""Where a model's novel-view error lies: on objects, in the band around them, or on the floor.

Reads the renders `colf-eval --renders DIR` wrote (scene_NNNNN_vV.png) and the ground-truth
views and masks of the same scenes, and splits the squared error of the novel views (1-3) into
regions of the ground-truth mask: object pixels, background pixels within 3 pixels of an object
("near": edges and most contact shadows), other background pixels more than 0.04 darker than the
view's median background ("shadow": the farther parts of cast shadows), and the rest ("far").

    python3 error_by_region.py --data out/unsup/data/test --scenes 20 f4=/tmp/rend_f4 default=/tmp/rend_def

Needs numpy, pillow and scipy (the project venv has them).
"""

import argparse

import numpy as np
from PIL import Image
from scipy import ndimage


def load_rgb(path):
    return np.asarray(Image.open(path).convert("RGB"), float) / 255


def regions(mask, truth):
    obj = mask > 0
    near = ndimage.binary_dilation(obj, iterations=3) & ~obj
    rest = ~obj & ~near
    median = np.median(truth[rest], axis=0).mean()
    shadow = rest & ((median - truth.mean(-1)) > 0.04)
    return {"obj": obj, "near": near, "shadow": shadow, "far": rest & ~shadow}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("renders", nargs="+", help="NAME=DIR of colf-eval --renders")
    args = ap.parse_args()
    print("| model | PSNR | objects: MSE, share | near: MSE, share | shadow: MSE, share | far: MSE, share |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for spec in args.renders:
        name, folder = spec.split("=", 1)
        sums = {k: [0.0, 0] for k in ("obj", "near", "shadow", "far")}
        for s in range(args.scenes):
            for v in (1, 2, 3):
                view = f"{args.data}/scene_{s:05d}/view_{v:03d}"
                truth = load_rgb(view + ".png")
                mask = np.asarray(Image.open(view + ".mask.png"))
                if mask.ndim == 3:
                    mask = mask[..., 0]
                error = ((truth - load_rgb(f"{folder}/scene_{s:05d}_v{v}.png")) ** 2).mean(-1)
                for key, region in regions(mask, truth).items():
                    sums[key][0] += error[region].sum()
                    sums[key][1] += region.sum()
        total = sum(e for e, _ in sums.values())
        pixels = sum(n for _, n in sums.values())
        cells = [f"{e / max(n, 1):.4f}, {100 * e / total:.0f} %" for e, n in sums.values()]
        print(f"| {name} | {-10 * np.log10(total / pixels):.2f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
