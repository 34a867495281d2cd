#!/usr/bin/env python3
"""Whether a running server's answers are true to their threshold: for each
photograph, the default answer (each model's own threshold) against the
answer at a low threshold (`--low`, with `max_detections` at the server's
limit), cut at each model's threshold. Counts the detections at or above
their model's threshold that the default answer misses, and those in the
default answer below it. A detection is the same when its model, box
(to 0.5 px) and score (to 1e-6) agree.

usage: benches/threshold_consistency.py PORT [--images DIR ...] [--every N]
       [--low -5] [--max-detections 100] [--verbose]

Default images: every 10th CMU_KO8 single-pose test photograph per object
(../shared/data/cmu_ko8/single/test/*/). Exit status 1 when any differ.
"""
import argparse
import glob
import json
import os
import sys
import urllib.request

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def post(port, path, query):
    with open(path, "rb") as f:
        body = f.read()
    ctype = "image/png" if path.lower().endswith(".png") else "image/jpeg"
    req = urllib.request.Request(f"http://127.0.0.1:{port}/detect?{query}", data=body,
                                 headers={"Content-Type": ctype})
    with urllib.request.urlopen(req, timeout=600) as r:
        return json.load(r)["detections"]


def key(d):
    b = d["box"]
    return (d["model"], round(b["x"] * 2), round(b["y"] * 2), round(b["width"] * 2),
            round(b["height"] * 2))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("port", type=int)
    ap.add_argument("--images", nargs="*")
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--low", type=float, default=-5.0)
    ap.add_argument("--max-detections", type=int, default=100)
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args()
    if a.images:
        paths = [p for d in a.images for p in sorted(glob.glob(os.path.join(d, "*.jpg")) +
                                                     glob.glob(os.path.join(d, "*.png")))]
    else:
        base = os.path.join(ROOT, "..", "shared", "data", "cmu_ko8", "single", "test")
        paths = []
        for obj in sorted(os.listdir(base)):
            d = os.path.join(base, obj)
            if os.path.isdir(d):
                paths += sorted(glob.glob(os.path.join(d, "*.jpg")))[::a.every]
    with urllib.request.urlopen(f"http://127.0.0.1:{a.port}/models") as r:
        thresholds = {m["name"]: m["threshold"] for m in json.load(r)}
    missing = below = above = 0
    for p in paths:
        default = post(a.port, p, "masks=none")
        low = post(a.port, p, f"masks=none&threshold={a.low}&max_detections={a.max_detections}")
        got = {key(d): d["score"] for d in default}
        for d in default:
            if d["score"] < thresholds[d["model"]] - 1e-9:
                below += 1
                if a.verbose:
                    print(f"{os.path.basename(p)}: {d['model']} {d['score']:.3f} below {thresholds[d['model']]}")
        for d in low:
            if d["score"] >= thresholds[d["model"]]:
                above += 1
                k = key(d)
                if k not in got or abs(got[k] - d["score"]) > 1e-6:
                    missing += 1
                    if a.verbose:
                        print(f"{os.path.basename(p)}: {d['model']} {d['score']:.3f} missing")
    print(f"{len(paths)} photographs: {above} detections at or above their model's threshold "
          f"at threshold {a.low}; {missing} missing from the default answer; "
          f"{below} in the default answer below their threshold")
    return 1 if missing or below else 0


if __name__ == "__main__":
    sys.exit(main())
