#!/usr/bin/env python3
"""Calibration of POST /pose's `score` on the LM-O development set: runs the
instances and starts of ../shared/tools/lmo_pose.py (its own functions, so
the same seeds) against a running server, and prints, for OR-IRLS and IRLS,
the share of BOP-style successes among the answers whose score is at least
each cut-off, and how many answers that keeps (with --verbose every answer
with the rotation std of its posterior covariance).

usage: benches/lmo_pose_score.py PORT [--visib 0.4,0.8] [--tools ../shared/tools]
"""
import argparse
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("port", type=int)
    ap.add_argument("--visib", default="0.4,0.8")
    ap.add_argument("--tools", default=os.path.join(ROOT, "../shared/tools"))
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--verbose", action="store_true", help="print every answer, by posterior rotation std")
    a = ap.parse_args()
    sys.path.insert(0, a.tools)
    import lmo_pose  # noqa: E402
    import render_lmo  # noqa: E402

    lmo = render_lmo.LMO()
    objects = sorted(lmo.models_info)
    lo, hi = (float(x) for x in a.visib.split(","))
    insts, _ = lmo_pose.select_instances(lmo, objects, 25, a.seed, 0.10, lo, hi)
    rows = {"OR-IRLS": [], "IRLS": []}
    for inst in insts:
        obj, im = inst["obj_id"], inst["im_id"]
        minfo = lmo.models_info[obj]
        R_gt, t_gt, R0, t0, params = lmo_pose.instance_request(lmo, inst, a.seed, 50)
        image = lmo.rgb_path(im).read_bytes()
        mask = lmo_pose.png_bytes((inst["vis"] * 255).astype("uint8"))
        for method, mode in (("IRLS", "none"), ("OR-IRLS", "provided")):
            st, js, err, _ = lmo_pose.post_pose(a.port, image, lmo.mesh_bytes(obj), dict(params, mask=mode),
                                                mask if mode == "provided" else None, 60)
            if err is not None:
                rows[method].append((-1.0, False, False, 99.0, 99.0, 99.0, -1.0))
                continue
            R, t, _ = lmo_pose.parse_pose(js)
            e = lmo_pose.pose_errors(R, t, R_gt, t_gt, minfo["diameter"], lmo_pose.sym_transforms(minfo))
            import math
            cov = js["covariance"]
            srot = math.degrees(math.sqrt(max(cov[3][3] + cov[4][4] + cov[5][5], 0.0) / 3))
            rows[method].append((js["score"], bool(e["success"]), bool(js["start_kept"]), srot, e["angle"], e["t"],
                                 js["score"] - js["start_score"]))
    for method, r in rows.items():
        n = len(r)
        kept = sum(1 for x in r if x[2])
        print(f"{method}: {n} answers, {sum(1 for x in r if x[1])} successes, start kept {kept}")
        for x in sorted(r, key=lambda x: x[3]) if a.verbose else []:
            print(f"    srot {x[3]:.3f} score {x[0]:.2f} success {x[1]} angle {x[4]:.2f} t {x[5]:.1f}")
        for cut in (0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9):
            sel = [x[1] for x in r if x[0] >= cut]
            if sel:
                print(f"  score >= {cut:.1f}: {len(sel):3d} answers, {100 * sum(sel) / len(sel):5.1f}% successes")
        for cut in (0.0, 0.1, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5):
            sel = [x[1] for x in r if x[6] >= cut]
            if sel:
                print(f"  score - start_score >= {cut:.2f}: {len(sel):3d} answers, {100 * sum(sel) / len(sel):5.1f}% successes")


if __name__ == "__main__":
    main()
