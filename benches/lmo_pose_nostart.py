#!/usr/bin/env python3
"""Pose from no start on LM-O through a running server: POST /pose without
`initial_pose`, with `model` naming the object's detector (trained from its
mesh by `sdhop-train mesh`), for every instance of the objects with a
loaded detector whose visib_fract is in --visib and whose oracle mask agrees
with BOP's (the instance selection of ../shared/tools/lmo_pose.py, its own
functions). Per object and overall: the share of instances whose ADD(-S)
is below 10% of the diameter (ADD-S for objects with symmetries in
models_info.json), the BOP-style success of lmo_pose.py (|t| < 10% d and
angle < 5 deg), how often the answer's detection is the instance (box IoU
>= 0.5), refusals (422: nothing detected) and latency.

usage: benches/lmo_pose_nostart.py PORT --models ape=1,cat=6,duck=9,glue=11
           [--visib 0.4,1.0] [--per-object 0 (all)] [--tools ../shared/tools] [--dump FILE.jsonl]
"""
import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def add_error(pts, R, t, R_gt, t_gt, symmetric):
    """ADD (mean distance of the model's points) or ADD-S (mean distance to the closest point)."""
    est = pts @ R.T + t
    gt = pts @ R_gt.T + t_gt
    if not symmetric:
        return float(np.linalg.norm(est - gt, axis=1).mean())
    best = np.full(len(est), np.inf)
    for i in range(0, len(gt), 512):
        d = np.linalg.norm(est[:, None, :] - gt[None, i:i + 512, :], axis=2).min(axis=1)
        best = np.minimum(best, d)
    return float(best.mean())


def box_iou(a, b):
    ax2, ay2, bx2, by2 = a[0] + a[2], a[1] + a[3], b[0] + b[2], b[1] + b[3]
    iw = max(0.0, min(ax2, bx2) - max(a[0], b[0]))
    ih = max(0.0, min(ay2, by2) - max(a[1], b[1]))
    inter = iw * ih
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("port", type=int)
    ap.add_argument("--models", required=True, help="NAME=OBJ_ID,... the loaded detectors and their BOP objects")
    ap.add_argument("--visib", default="0.4,1.0")
    ap.add_argument("--per-object", type=int, default=0, help="at most this many instances per object (0: all)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--max-oracle-gap", type=float, default=0.10)
    ap.add_argument("--points", type=int, default=1000, help="model points used for ADD(-S)")
    ap.add_argument("--tools", default=os.path.join(ROOT, "../shared/tools"))
    ap.add_argument("--dump", default=None)
    a = ap.parse_args()
    sys.path.insert(0, a.tools)
    import lmo_pose  # noqa: E402
    import render_lmo  # noqa: E402

    lmo = render_lmo.LMO()
    models = {}
    for item in a.models.split(","):
        name, obj = item.split("=")
        models[int(obj)] = name
    lo, hi = (float(v) for v in a.visib.split(","))
    per = a.per_object or 10 ** 9
    chosen, stats = lmo_pose.select_instances(lmo, list(models), per, a.seed, a.max_oracle_gap, lo, hi)
    dump = open(a.dump, "w") if a.dump else None
    rows = []
    rng = np.random.default_rng(0)
    pts_cache = {}
    for n, inst in enumerate(chosen):
        obj, im, k = inst["obj_id"], inst["im_id"], inst["k"]
        info = lmo.models_info[obj]
        symmetric = bool(info.get("symmetries_discrete") or info.get("symmetries_continuous"))
        if obj not in pts_cache:
            v = np.asarray(lmo.mesh(obj)[0], float)
            pts_cache[obj] = v[rng.choice(len(v), min(a.points, len(v)), replace=False)]
        R_gt, t_gt = lmo.pose_so3(im, k)
        K = lmo.K(im)
        params = {"intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]},
                  "model": models[obj]}
        with open(lmo.rgb_path(im), "rb") as f:
            image = f.read()
        st, js, err, secs = lmo_pose.post_pose(a.port, image, lmo.mesh_bytes(obj), params)
        row = {"obj": obj, "im": im, "k": k, "status": st, "seconds": secs, "error": err,
               "visib_fract": inst["visib_fract"], "add": None, "success": False, "add_ok": False,
               "on_instance": False}
        if st == 200:
            try:
                R, t, _ = lmo_pose.parse_pose(js)
                add = add_error(pts_cache[obj], R, t, R_gt, t_gt, symmetric)
                e = lmo_pose.pose_errors(R, t, R_gt, t_gt, info["diameter"], lmo_pose.sym_transforms(info))
                b = (js.get("detection") or {}).get("box") or {}
                gt_box = lmo.info[im][k]["bbox_obj"]
                row.update(add=add, add_ok=add < 0.1 * info["diameter"], success=e["success"],
                           t=e["t"], angle=e["angle"], score=js.get("score"),
                           on_instance=bool(b) and box_iou((b["x"], b["y"], b["width"], b["height"]), gt_box) >= 0.5)
            except ValueError as ex:
                row["error"] = str(ex)
        rows.append(row)
        if dump:
            dump.write(json.dumps(row) + "\n")
        sys.stderr.write(f"\r{n + 1}/{len(chosen)}")
    sys.stderr.write("\n")
    print(f"{'object':<10} {'n':>4} {'ADD<10%d':>9} {'BOP succ':>9} {'on inst':>8} {'422':>5} {'lat med':>8} {'lat max':>8}")
    for obj in list(models) + [None]:
        rs = [r for r in rows if obj is None or r["obj"] == obj]
        if not rs:
            continue
        lat = sorted(r["seconds"] for r in rs)
        name = models[obj] if obj else "all"
        print(f"{name:<10} {len(rs):>4} {np.mean([r['add_ok'] for r in rs]):>9.3f} "
              f"{np.mean([r['success'] for r in rs]):>9.3f} {np.mean([r['on_instance'] for r in rs]):>8.3f} "
              f"{sum(r['status'] == 422 for r in rs):>5} {lat[len(lat) // 2]:>7.2f}s {lat[-1]:>7.2f}s")
    per_obj = [np.mean([r["add_ok"] for r in rows if r["obj"] == o]) for o in models if any(r["obj"] == o for r in rows)]
    print(f"ADD10={np.mean([r['add_ok'] for r in rows]):.3f} ADD10_MEAN_OBJ={np.mean(per_obj):.3f} "
          f"N={len(rows)} ON_INSTANCE={np.mean([r['on_instance'] for r in rows]):.3f}")
    return 0


if __name__ == "__main__":
    start = time.time()
    rc = main()
    sys.stderr.write(f"{time.time() - start:.0f} s\n")
    sys.exit(rc)
