#!/usr/bin/env python3
"""COCO AP of a BOP detection-results file by pycocotools, as BOP's eval_bop22_coco.py computes it.

usage: bop_coco_check.py DATA RESULTS.json [--train-photos N] [--every N] [--objects 1,6,9,11]

DATA is a BOP-layout folder with one test scene (e.g. ../shared/data/lmo_dev);
RESULTS.json what `sdhop-train bop-eval` writes (METHOD_lmo-test.json). The
ground truth is made as BOP's calc_gt_coco.py makes it: every instance with a
visible pixel, its amodal box (`bbox_obj`) and its visible mask (`mask_visib`),
over the photographs bop-eval scored (by image id, the first N left out, every
n-th). Prints AP, AP50 and AP75 for boxes and masks, to set beside bop-eval's
own figures (they should agree) and the leaderboard's.
"""
import argparse, json, sys
from pathlib import Path

import numpy as np
from PIL import Image
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data")
    ap.add_argument("results")
    ap.add_argument("--train-photos", type=int, default=0)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--objects", default=None, help="obj ids scored (default: those with detections)")
    a = ap.parse_args()
    scene = sorted((Path(a.data) / "test").iterdir())[0]
    gt = json.loads((scene / "scene_gt.json").read_text())
    ids = sorted(int(k) for k in gt)[a.train_photos::a.every]
    results = json.loads(Path(a.results).read_text())
    objects = ({int(x) for x in a.objects.split(",")} if a.objects
               else {r["category_id"] for r in results})
    images, annotations = [], []
    for im in ids:
        w, h = Image.open(next((scene / "rgb").glob(f"{im:06d}.*"))).size
        images.append({"id": im, "width": w, "height": h, "file_name": f"{im:06d}"})
        info = json.loads((scene / "scene_gt_info.json").read_text())[str(im)]
        for k, inst in enumerate(gt[str(im)]):
            if inst["obj_id"] not in objects:
                continue
            m = np.array(Image.open(scene / "mask_visib" / f"{im:06d}_{k:06d}.png")) > 0
            rle = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
            area = float(mask_utils.area(rle))
            if area < 1:
                continue
            rle["counts"] = rle["counts"].decode("ascii")
            annotations.append({"id": len(annotations) + 1, "image_id": im, "category_id": inst["obj_id"],
                                "bbox": info[k]["bbox_obj"], "segmentation": rle, "area": area, "iscrowd": 0})
    coco = COCO()
    coco.dataset = {"images": images, "annotations": annotations,
                    "categories": [{"id": o, "name": str(o)} for o in sorted(objects)]}
    coco.createIndex()
    scored = [r for r in results if r["image_id"] in set(ids) and r["category_id"] in objects]
    if not scored:
        sys.exit("no detection of the scored objects on the scored photographs")
    for kind in ("bbox", "segm"):
        dt = coco.loadRes(scored)
        e = COCOeval(coco, dt, kind)
        e.params.imgIds = ids
        e.evaluate()
        e.accumulate()
        e.summarize()
        print(f"{'boxes' if kind == 'bbox' else 'masks'}: AP {100 * e.stats[0]:.1f} AP50 {100 * e.stats[1]:.1f} AP75 {100 * e.stats[2]:.1f}")


if __name__ == "__main__":
    main()
