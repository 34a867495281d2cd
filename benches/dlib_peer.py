#!/usr/bin/env python3
"""Issue 22's peer, measured on this machine: dlib's plain HOG detector
(`scan_fhog_pyramid` through `dlib.train_simple_object_detector`) against
sdhop on the same CMU_KO8 development photographs, in one run.

1. Trains one dlib detector per object on the development images that are
   not timed (every image of the object but the first --images), the
   object's full-extent boxes (`.bbox` is [cx, cy, w, h]), dlib's default
   80x80 window, C=5, one thread.
2. Times dlib on the first --images cup images (decoded beforehand), one
   thread: the cup detector alone, and all eight detectors together with
   `run_multiple` (which computes the feature pyramid once).
3. With --port, times `POST /detect?model=cup&masks=refined` and the
   default `/detect` (all models) of a running sdhop-serve on the same
   images, one request at a time (JPEG bytes as sent by a client, so
   decoding is included on sdhop's side only).

Prints median ms per image and the ratios. Needs python3 with numpy, pillow
and dlib (`pip install dlib-bin`).

usage: benches/dlib_peer.py [--data ../shared/data/cmu_ko8] [--images 20]
                            [--iters 3] [--port 18080] [--cache out/dlib]
"""
import argparse
import os
import statistics
import sys
import time
import urllib.request

import numpy as np
from PIL import Image

OBJECTS = ["bakingpan", "colander", "cup", "pitcher", "saucepan",
           "scissors", "shaker", "thermos"]


def read_bbox(path):
    with open(path) as f:
        vals = [float(v) for v in f.read().replace(",", " ").split()]
    cx, cy, w, h = vals[:4]
    return cx, cy, w, h


def files(data, obj):
    d = os.path.join(data, "single", "test", obj)
    return sorted(os.path.join(d, f) for f in os.listdir(d) if f.endswith(".jpg"))


def train(dlib, data, obj, skip, cache):
    out = os.path.join(cache, f"{obj}.svm")
    if os.path.exists(out):
        return dlib.simple_object_detector(out)
    imgs, boxes = [], []
    for p in files(data, obj)[skip:]:
        cx, cy, w, h = read_bbox(p[:-4] + ".bbox")
        imgs.append(np.asarray(Image.open(p).convert("RGB")))
        boxes.append([dlib.rectangle(int(round(cx - w / 2)), int(round(cy - h / 2)),
                                     int(round(cx + w / 2)), int(round(cy + h / 2)))])
    opts = dlib.simple_object_detector_training_options()
    opts.C = 5
    opts.num_threads = 1
    opts.be_verbose = False
    t = time.time()
    det = dlib.train_simple_object_detector(imgs, boxes, opts)
    det.save(out)
    print(f"  trained dlib {obj} on {len(imgs)} images in {time.time() - t:.1f} s",
          file=sys.stderr)
    return det


def median_ms(fn, items, iters):
    times = []
    for _ in range(iters):
        for it in items:
            t = time.perf_counter()
            fn(it)
            times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def post(port, query, body):
    req = urllib.request.Request(
        f"http://127.0.0.1:{port}/detect?{query}", data=body,
        headers={"Content-Type": "image/jpeg"}, method="POST")
    with urllib.request.urlopen(req, timeout=60) as r:
        r.read()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="../shared/data/cmu_ko8")
    ap.add_argument("--images", type=int, default=20)
    ap.add_argument("--iters", type=int, default=3)
    ap.add_argument("--port", type=int)
    ap.add_argument("--cache", default="out/dlib")
    a = ap.parse_args()
    try:
        import dlib
    except ImportError:
        print("skipped: dlib is not installed (pip install dlib-bin)")
        return 0
    if not os.path.isdir(os.path.join(a.data, "single", "test", "cup")):
        print(f"skipped: {a.data} has no CMU_KO8 development data")
        return 0
    os.makedirs(a.cache, exist_ok=True)
    dets = {o: train(dlib, a.data, o, a.images, a.cache) for o in OBJECTS}
    timed = files(a.data, "cup")[:a.images]
    arrays = [np.asarray(Image.open(p).convert("RGB")) for p in timed]
    jpegs = [open(p, "rb").read() for p in timed]
    # One thread: dlib's Python detectors run single-threaded.
    d1 = median_ms(lambda im: dets["cup"](im, 0), arrays, a.iters)
    all_dets = [dets[o] for o in OBJECTS]
    d8 = median_ms(lambda im: dlib.fhog_object_detector.run_multiple(all_dets, im, 0),
                   arrays, a.iters)
    print(f"{len(timed)} cup development images, median ms per image, {a.iters} passes")
    print(f"dlib, cup detector, 1 thread          {d1:7.1f}")
    print(f"dlib, 8 detectors (run_multiple), 1 t {d8:7.1f}")
    if a.port:
        s1 = median_ms(lambda b: post(a.port, "model=cup&masks=refined", b), jpegs, a.iters)
        s8 = median_ms(lambda b: post(a.port, "masks=refined", b), jpegs, a.iters)
        print(f"sdhop service, cup, refined masks     {s1:7.1f}  ({s1 / d1:.2f}x dlib)")
        print(f"sdhop service, 8 models, refined      {s8:7.1f}  ({s8 / d8:.2f}x dlib's 8)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
