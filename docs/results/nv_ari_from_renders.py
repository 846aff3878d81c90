"""uORF's NV-ARI from the renders `colf-eval --data DIR --renders OUT` writes.

NV-ARI as uORF's evaluation code defines it: scikit-learn's adjusted_rand_score of the full label
maps (background included) of each novel view, averaged over a scene's novel views, then over the
scenes. Also prints the FG-ARI of the novel views (ground-truth object pixels only), which is a
different number.

    python nv_ari_from_renders.py RENDERS DATA [SCENES]
"""
import sys

import numpy as np
from PIL import Image
from sklearn.metrics import adjusted_rand_score

renders, data = sys.argv[1], sys.argv[2]
scenes = int(sys.argv[3]) if len(sys.argv) > 3 else 100
per_scene, fg = [], []
for s in range(scenes):
    full = []
    for v in (1, 2, 3):
        pred = np.array(Image.open(f"{renders}/scene_{s:05d}_v{v}.mask.png")).reshape(-1)
        gt = np.array(Image.open(f"{data}/scene_{s:05d}/view_{v:03d}.mask.png")).reshape(-1)
        full.append(adjusted_rand_score(gt, pred))
        objects = gt > 0
        if objects.any():
            fg.append(adjusted_rand_score(gt[objects], pred[objects]))
    per_scene.append(np.mean(full))
print(f"nv_ari {np.mean(per_scene):.4f} ± {np.std(per_scene):.4f} (over scenes)  "
      f"novel-view fg_ari {np.mean(fg):.4f}")
