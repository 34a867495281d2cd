#!/usr/bin/env python3
"""COCO training labels with the true visible masks for the first N photographs of a
BOP-layout dataset (LM-O): the full-extent box (bbox_obj) and the visible mask
(mask_visib, uncompressed RLE) of every instance of one object.

usage: lmo_masks_coco.py DATA --first N --object ID --name NAME --out FILE.json

The fully labelled counterpart of lmo_boxes_coco.py (the same photographs, by image
id); file_names are absolute. Instances under --min-visib visible are left out with
their photograph (neither a positive nor a negative). Train with
`sdhop-train train --coco FILE.json --images / --category NAME`.
"""
import argparse
import json
import os
import sys

import numpy as np
from PIL import Image


def rle(mask):
    """COCO uncompressed RLE (column-major run lengths, starting with zeros)."""
    flat = mask.T.reshape(-1).astype(np.uint8)
    counts, last, run = [], 0, 0
    for v in flat:
        if v != last:
            counts.append(run)
            run, last = 0, v
        run += 1
    counts.append(run)
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": counts}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data")
    ap.add_argument("--first", type=int, required=True)
    ap.add_argument("--object", type=int, required=True)
    ap.add_argument("--name", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--min-visib", type=float, default=0.1)
    a = ap.parse_args()
    test = os.path.join(a.data, "test")
    scenes = sorted(d for d in os.listdir(test) if os.path.isdir(os.path.join(test, d)))
    images, anns = [], []
    for scene in scenes:
        root = os.path.join(test, scene)
        gt = json.load(open(os.path.join(root, "scene_gt.json")))
        info = json.load(open(os.path.join(root, "scene_gt_info.json")))
        for im_id in sorted(gt, key=int)[: a.first]:
            path = os.path.abspath(os.path.join(root, "rgb", "%06d.png" % int(im_id)))
            w, h = Image.open(path).size
            skip, mine = False, []
            for k, (g, inf) in enumerate(zip(gt[im_id], info[im_id])):
                if g["obj_id"] != a.object:
                    continue
                if inf["visib_fract"] < a.min_visib:
                    skip = True
                    continue
                m = np.array(Image.open(os.path.join(root, "mask_visib", "%06d_%06d.png" % (int(im_id), k)))) > 0
                mine.append((inf["bbox_obj"], m))
            if skip:
                print("%s: %s under %.2f visible: left out" % (path, a.name, a.min_visib), file=sys.stderr)
                continue
            iid = len(images) + 1
            images.append({"id": iid, "file_name": path, "width": w, "height": h})
            for box, m in mine:
                anns.append({"id": len(anns) + 1, "image_id": iid, "category_id": 1, "bbox": box,
                             "segmentation": rle(m), "iscrowd": 0})
    json.dump({"images": images, "annotations": anns, "categories": [{"id": 1, "name": a.name}]},
              open(a.out, "w"))
    print("%s: %d photographs, %d instances of %s" % (a.out, len(images), len(anns), a.name))


if __name__ == "__main__":
    main()
