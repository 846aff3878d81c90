"""Codes written by Python's safetensors package, edited by colf-edit, read back by Python.

Usage: python3 codes_interop.py COLF_EDIT_BINARY WORKDIR
Exits non-zero (with a message) on any mismatch. Matrices must agree to 1e-5.
"""
import json
import math
import os
import subprocess
import sys

import numpy as np
from safetensors.numpy import load_file, save_file

colf_edit, work = sys.argv[1], sys.argv[2]
rng = np.random.default_rng(7)


def rot_z(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def rot_axis(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    x, y, z = axis
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    C = 1 - c
    m = np.eye(4)
    m[:3, :3] = [[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                 [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                 [z * x * C - y * s, z * y * C + x * s, c + z * z * C]]
    return m


def trans(v):
    m = np.eye(4)
    m[:3, 3] = v
    return m


def write_codes(path, k, d, model, tag):
    frames = np.stack([trans(rng.uniform(-3, 3, 3)) @ rot_z(rng.uniform(0, 360)) for _ in range(k)])
    tensors = {
        "slots": rng.normal(size=(k, d)).astype(np.float32),
        "slot_to_world": frames.astype(np.float32).reshape(k, 4, 4),
        "slot_mass": rng.uniform(0.01, 0.3, k).astype(np.float32),
        "background": rng.normal(size=(d,)).astype(np.float32),
        "extra_tensor_colf_ignores": np.zeros(3, np.float32),
    }
    meta = {"format": "colf-codes/1", "model": model,
            "sources": json.dumps([f"{tag}#{i}" for i in range(k)]), "writer": "python"}
    save_file(tensors, path, metadata=meta)
    return tensors


a_path, b_path = os.path.join(work, "a.codes"), os.path.join(work, "b.codes")
a = write_codes(a_path, 5, 16, "m1", "a.png")
b = write_codes(b_path, 3, 16, "m1", "b.png")
a["slot_mass"][4] = 0.001
save_file({k: v for k, v in a.items()}, a_path,
          metadata={"format": "colf-codes/1", "model": "m1",
                    "sources": json.dumps([f"a.png#{i}" for i in range(5)])})

ops = [
    {"op": "translate", "slots": [0], "by": [1.5, -2.0, 0.25]},
    {"op": "rotate", "slots": [1, 2], "axis": [0.2, 0.3, 1.0], "degrees": 37.5, "pivot": [1, 2, 0]},
    {"op": "duplicate", "slots": [3], "by": [0, 2, 0]},
    {"op": "prune", "min_mass": 0.002},
    {"op": "delete", "slots": [2]},
    {"op": "keep", "slots": [0, 1, 2, 3]},
    {"op": "merge", "from": b_path, "slots": [0, 2]},
    {"op": "background", "from": b_path},
]
edits = os.path.join(work, "edits.json")
with open(edits, "w") as f:
    json.dump({"ops": ops}, f)
out = os.path.join(work, "out.codes")
subprocess.run([colf_edit, edits, a_path, "-o", out], check=True)

# Expected result, computed here in float64 from the float32 inputs.
F = a["slot_to_world"].astype(np.float64)
L = a["slots"]
expect = [
    (trans([1.5, -2.0, 0.25]) @ F[0], L[0], "a.png#0"),
    (trans([1, 2, 0]) @ rot_axis([0.2, 0.3, 1.0], 37.5) @ trans([-1, -2, 0]) @ F[1], L[1], "a.png#1"),
    # slot 2 rotated then deleted
    (F[3], L[3], "a.png#3"),
    # slot 4 pruned (mass 0.001); the duplicate of 3 follows
    (trans([0, 2, 0]) @ F[3], L[3], "a.png#3"),
    (b["slot_to_world"][0].astype(np.float64), b["slots"][0], "b.png#0"),
    (b["slot_to_world"][2].astype(np.float64), b["slots"][2], "b.png#2"),
]
got = load_file(out)
with open(out, "rb") as f:
    n = int.from_bytes(f.read(8), "little")
    header = json.loads(f.read(n))
meta = header["__metadata__"]
assert meta["format"] == "colf-codes/1", meta
assert meta["model"] == "m1", meta
sources = json.loads(meta["sources"])
assert got["slots"].shape == (len(expect), 16), got["slots"].shape
assert got["slot_to_world"].shape == (len(expect), 4, 4)
assert got["slot_mass"].shape == (len(expect),)
assert got["background"].shape == (16,)
for key in ("slots", "slot_to_world", "slot_mass", "background"):
    assert got[key].dtype == np.float32, (key, got[key].dtype)
for i, (frame, latent, source) in enumerate(expect):
    err = np.abs(got["slot_to_world"][i] - frame).max()
    assert err < 1e-5, f"slot {i}: matrix error {err}"
    assert np.array_equal(got["slots"][i], latent), f"slot {i}: latent differs"
    assert sources[i] == source, (i, sources[i], source)
assert np.array_equal(got["background"], b["background"])
print(f"python interop ok: {len(expect)} slots, matrices within 1e-5")
