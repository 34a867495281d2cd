#!/usr/bin/env python3
"""Fair admission between request kinds, on LM-O development photographs:
starts the release server with the detectors trained from the LM-O meshes
(models/lmo) on a loopback port, keeps POSES pose requests without a
start pose in flight (the duck's mesh; each costs seconds) and meanwhile
sends DETECTS /detect requests (duck, 5 s deadline, one at a time). Prints
the status counts and latencies of both kinds, and what /health/ready
answered meanwhile. Then the cheap refusals: a pose whose label the model
lacks, a label on a single-object model, a mask of the wrong size, each
timed (they must not wait for a detection).

With --seconds S the detections go on for S seconds instead of
--detects requests, and the pose lane's occupancy is sampled from
/metrics meanwhile (the share of samples with every place taken).

usage: benches/lanes.py [--poses 8] [--detects 30] [--seconds S] [--port 18091]
       [--data ../shared/data/lmo_dev] [--server target/release/sdhop-serve]
"""
import argparse
import io
import json
import os
import subprocess
import threading
import time
import urllib.request
from collections import Counter

from httpclient import multipart, request

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--detects", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=0,
                    help="send /detect for this long instead of --detects requests")
    ap.add_argument("--port", type=int, default=18091)
    ap.add_argument("--data", default=os.path.join(ROOT, "..", "shared", "data", "lmo_dev"))
    ap.add_argument("--server", default=os.path.join(ROOT, "target", "release", "sdhop-serve"))
    a = ap.parse_args()
    cam = json.load(open(os.path.join(a.data, "test", "000002", "scene_camera.json")))
    first = sorted(cam, key=int)[0]
    k = cam[first]["cam_K"]
    photo = open(os.path.join(a.data, "test", "000002", "rgb", f"{int(first):06d}.png"), "rb").read()
    mesh = open(os.path.join(a.data, "models", "obj_000009.ply"), "rb").read()
    intr = {"fx": k[0], "fy": k[4], "cx": k[2], "cy": k[5]}
    base = f"http://127.0.0.1:{a.port}"
    srv = subprocess.Popen([a.server, "--addr", f"127.0.0.1:{a.port}", "--models-dir",
                            os.path.join(ROOT, "models", "lmo")],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(1200):
            if request(base + "/health/ready", timeout=1)[0] == 200:
                break
            time.sleep(0.05)
        info = json.loads(urllib.request.urlopen(base + "/info").read())["limits"]
        print(f"pose lane: {info.get('pose_queue_size', 'none')} places, "
              f"{info.get('pose_threads', 'no')} threads; detect lane: {info['queue_size']} places")

        def pose(params, mask=None, query="?timeout_ms=30000"):
            parts = [("image", "image/png", photo), ("mesh", "application/octet-stream", mesh),
                     ("params", "application/json", json.dumps(params).encode())]
            if mask is not None:
                parts.append(("mask", "image/png", mask))
            body, ctype = multipart(parts)
            return request(base + "/pose" + query, body, ctype)

        stop = threading.Event()
        pose_results, ready = [], Counter()

        def pose_loop():
            while not stop.is_set():
                pose_results.append(pose({"intrinsics": intr, "model": "duck"}))

        occupancy = Counter()

        def ready_loop():
            while not stop.is_set():
                ready[request(base + "/health/ready", timeout=2)[0]] += 1
                try:
                    text = urllib.request.urlopen(base + "/metrics", timeout=2).read().decode()
                    full = 'sdhop_lane_occupancy{lane="pose"} 1\n' in text
                    occupancy["full" if full else "not full"] += 1
                except OSError:
                    occupancy["no answer"] += 1
                time.sleep(0.1)

        threads = [threading.Thread(target=pose_loop) for _ in range(a.poses)]
        threads.append(threading.Thread(target=ready_loop))
        for t in threads:
            t.start()
        time.sleep(1.0)
        detects, t0 = [], time.monotonic()
        while (time.monotonic() - t0 < a.seconds) if a.seconds > 0 else len(detects) < a.detects:
            detects.append(request(base + "/detect?model=duck&timeout_ms=5000", photo, "image/png"))
        stop.set()
        for t in threads:
            t.join()

        def summary(rs):
            c = Counter(r[0] for r in rs)
            lat = sorted(r[1] for r in rs)
            return (f"{dict(c)}, latency median {lat[len(lat) // 2]:.2f} s, max {lat[-1]:.2f} s"
                    if lat else "none")

        print(f"/detect (5 s deadline), {a.poses} no-start poses in flight: {summary(detects)}")
        print(f"/pose without a start pose: {summary(pose_results)}")
        probes = sum(ready.values())
        print(f"/health/ready meanwhile: {dict(ready)} ({ready[503] / max(probes, 1):.0%} answered 503); "
              f"pose lane sampled from /metrics: {dict(occupancy)}")
        from PIL import Image
        buf = io.BytesIO()
        Image.new("L", (4000, 4000)).save(buf, format="PNG")
        for name, params, mask in [
            ("label the model lacks", {"intrinsics": intr, "model": "duck", "label": "ape"}, None),
            ("empty label", {"intrinsics": intr, "model": "duck", "label": ""}, None),
            ("mask 4000x4000 for 640x480", {"intrinsics": intr, "model": "duck", "mask": "provided"},
             buf.getvalue()),
        ]:
            status, t, msg = pose(params, mask)
            print(f"cheap refusal, {name}: {status} in {t * 1000:.0f} ms: {msg[:100]}")
    finally:
        srv.terminate()
        srv.wait()


if __name__ == "__main__":
    main()
