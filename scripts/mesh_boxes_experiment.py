#!/usr/bin/env python3
"""How the first figures of `mesh --photo-route boxes` were measured, before
the route was in the binary (docs/training.md, "Mesh plus boxes with learned
cells"): the box photographs with one object's boxes covered from beside
them (backgrounds for `sdhop-train mesh --renders 100 --components 1`), and a
COCO file that joins the photographs' boxes with the renders' boxes (box-only)
for `sdhop-train train --coco`.

    python3 scripts/mesh_boxes_experiment.py bg out/boxes50.json ape BGDIR
    sdhop-train mesh --mesh .../obj_000001.ply --name ape --backgrounds BGDIR \
        --renders 100 --components 1 --features hog --max-passes 1 --negatives 2 \
        --work RENDERS --out /tmp/unused.safetensors
    python3 scripts/mesh_boxes_experiment.py merge out/boxes50.json RENDERS/coco.json ape MERGED.json
    sdhop-train train --coco MERGED.json --images / --category ape --out OUT
"""
import json, sys, os
import numpy as np
from PIL import Image
cmd = sys.argv[1]
if cmd == 'bg':
    coco, obj, out = sys.argv[2:5]
    d = json.load(open(coco)); base = os.path.dirname(coco)
    cid = [c['id'] for c in d['categories'] if c['name'] == obj][0]
    os.makedirs(out, exist_ok=True)
    for im in d['images']:
        a = np.array(Image.open(os.path.join(base, im['file_name'])).convert('RGB'))
        H, W = a.shape[:2]
        for an in d['annotations']:
            if an['image_id'] != im['id'] or an['category_id'] != cid: continue
            x, y, w, h = an['bbox']
            x0 = int(max(0, x - 0.1*w)); y0 = int(max(0, y - 0.1*h)); x1 = int(min(W, x + 1.1*w)); y1 = int(min(H, y + 1.1*h))
            bw, bh = x1 - x0, y1 - y0
            if x0 - bw >= 0: src = a[y0:y1, x0-bw:x0][:, ::-1]
            elif x1 + bw <= W: src = a[y0:y1, x1:x1+bw][:, ::-1]
            elif y0 - bh >= 0: src = a[y0-bh:y0, x0:x1][::-1]
            else: src = a[y1:y1+bh, x0:x1][::-1]
            a[y0:y1, x0:x1] = src
        Image.fromarray(a).save(os.path.join(out, '%06d.png' % im['id']))
elif cmd == 'merge':
    coco, renders, obj, out = sys.argv[2:6]
    d = json.load(open(coco)); r = json.load(open(renders))
    base = os.path.dirname(os.path.abspath(coco)); rbase = os.path.dirname(os.path.abspath(renders))
    cid = [c['id'] for c in d['categories'] if c['name'] == obj][0]
    for im in d['images']: im['file_name'] = os.path.normpath(os.path.join(base, im['file_name']))
    nid = max(i['id'] for i in d['images']) + 1; aid = max(a['id'] for a in d['annotations']) + 1
    for im in r['images']:
        ans = [a for a in r['annotations'] if a['image_id'] == im['id']]
        d['images'].append({'id': nid, 'file_name': os.path.join(rbase, im['file_name']), 'width': im['width'], 'height': im['height']})
        for a in ans:
            x, y, w, h = a['bbox']
            d['annotations'].append({'id': aid, 'image_id': nid, 'category_id': cid, 'bbox': [x, y, w, h], 'area': w*h, 'iscrowd': 0}); aid += 1
        nid += 1
    json.dump(d, open(out, 'w'))
