"""Opens a colf EXR with the OpenEXR Python package and checks the channel contract.

Usage: python3 exr_check.py FILE.exr NUM_SLOTS WIDTH HEIGHT
"""
import sys

import numpy as np
import OpenEXR

path, k, w, h = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
channels = OpenEXR.File(path).channels()
rgb = np.asarray(channels["RGB"].pixels)
assert rgb.shape == (h, w, 3), rgb.shape
assert np.isfinite(rgb).all(), "non-finite RGB"
names = {"bg.weight", "bg.order"} | {f"slot{i}.{c}" for i in range(k) for c in ("weight", "order")}
missing = names - set(channels)
assert not missing, f"missing channels {missing}"
weights = np.stack([np.asarray(channels["bg.weight"].pixels)]
                   + [np.asarray(channels[f"slot{i}.weight"].pixels) for i in range(k)])
assert np.isfinite(weights).all()
assert np.allclose(weights.sum(0), 1.0, atol=1e-4), "weights do not sum to 1"
print(f"exr ok: {w}x{h}, {k} slots")
