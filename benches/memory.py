#!/usr/bin/env python3
"""Resident memory of sdhop-serve under load, to size a pod's memory
request and limit (deploy/sdhop.yaml). Starts the server with the
manifest's limits on a loopback port, then, bounded in time:

1. steady: CLIENTS concurrent clients POST CMU_KO8 development photos
   (640x480, every tenth of each object) to /detect with all models;
2. burst: BURST concurrent clients POST a 4-megapixel image (a photo
   scaled up) against the full queue;
3. stall: as many stalled uploads as the per-client connection limit.

RSS is sampled every 50 ms from /proc; prints idle, steady and burst peaks
and the status counts. Needs python3 with pillow and the KO8 data.

usage: benches/memory.py [--seconds 20] [--clients 32] [--burst 200]
"""
import argparse
import glob
import io
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections import Counter

from PIL import Image

from httpclient import rss_kb

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
MANIFEST_ENV = {
    "SDHOP_QUEUE_SIZE": "16",
    "SDHOP_MAX_PIXELS": "4000000",
    "SDHOP_MAX_CONNECTIONS": "256",
    "SDHOP_MAX_CONNECTIONS_PER_CLIENT": "64",
    "SDHOP_TIMEOUT_MS": "30000",
    "SDHOP_MAX_TIMEOUT_MS": "60000",
}


def post(url, body, ctype):
    req = urllib.request.Request(url, data=body, headers={"Content-Type": ctype})
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            r.read()
            return r.status
    except urllib.error.HTTPError as e:
        return e.code
    except OSError:
        return "error"


def hammer(url, bodies, ctype, seconds, clients):
    counts = Counter()
    lock = threading.Lock()
    stop = time.time() + seconds

    def run(i):
        k = i
        while time.time() < stop:
            s = post(url, bodies[k % len(bodies)], ctype)
            k += clients
            with lock:
                counts[s] += 1

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return counts


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20)
    ap.add_argument("--clients", type=int, default=32)
    ap.add_argument("--burst", type=int, default=200)
    ap.add_argument("--data", default=os.path.join(ROOT, "../shared/data/cmu_ko8"))
    ap.add_argument("--port", type=int, default=18091)
    a = ap.parse_args()
    photos = sorted(glob.glob(os.path.join(a.data, "single/test/*/*.jpg")))[::10]
    if not photos:
        sys.exit(f"no photos under {a.data}/single/test")
    bodies = [open(p, "rb").read() for p in photos]
    big = io.BytesIO()
    Image.open(photos[0]).convert("RGB").resize((2300, 1730)).save(big, "JPEG", quality=90)
    big = big.getvalue()

    server = os.path.join(ROOT, "target/release/sdhop-serve")
    env = dict(os.environ, **MANIFEST_ENV)
    p = subprocess.Popen([server, "--addr", f"127.0.0.1:{a.port}", "--models-dir", os.path.join(ROOT, "models")],
                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{a.port}"
    try:
        for _ in range(600):
            try:
                if urllib.request.urlopen(base + "/health/ready", timeout=1).status == 200:
                    break
            except OSError:
                time.sleep(0.1)
        peaks = {}
        phase = ["idle"]
        done = threading.Event()

        def sample():
            while not done.is_set():
                peaks[phase[0]] = max(peaks.get(phase[0], 0), rss_kb(p.pid))
                time.sleep(0.05)

        sampler = threading.Thread(target=sample)
        sampler.start()
        time.sleep(1)
        phase[0] = "steady"
        steady = hammer(base + "/detect", bodies, "image/jpeg", a.seconds, a.clients)
        phase[0] = "burst"
        burst = hammer(base + "/detect", [big], "image/jpeg", a.seconds / 2, a.burst)
        phase[0] = "stall"
        socks = []
        for _ in range(int(MANIFEST_ENV["SDHOP_MAX_CONNECTIONS_PER_CLIENT"])):
            s = socket.create_connection(("127.0.0.1", a.port))
            s.sendall(b"POST /detect HTTP/1.1\r\nHost: x\r\nContent-Type: image/jpeg\r\n"
                      b"Content-Length: 4000000\r\n\r\n" + big[:2_000_000])
            socks.append(s)
        time.sleep(2)
        for s in socks:
            s.close()
        done.set()
        sampler.join()
        for k in ["idle", "steady", "burst", "stall"]:
            print(f"{k:7s} peak RSS {peaks.get(k, 0) / 1024:7.0f} MB")
        print(f"steady ({a.clients} clients, all models, 640x480): {dict(steady)}")
        print(f"burst ({a.burst} clients, 4 MP): {dict(burst)}")
    finally:
        p.terminate()
        p.wait(timeout=120)


if __name__ == "__main__":
    main()
