#!/usr/bin/env python3
"""Peak resident memory of one /detect request above idle, by image size
and model: what the admission's cost estimate (src/infer/budget.rs,
`request_bytes`, whose comment records these figures beside its
estimates) is calibrated against. Starts sdhop-serve with a budget too
large to bind (`--memory-budget-mb 1000000`) and each case's models alone,
sends one request at a time (a CMU_KO8 photograph scaled to the size),
samples /proc every 10 ms, and prints the peak above the idle process in
MiB and bytes per pixel. The idle process keeps the allocator's freed
pages after its first large request: a later size's peak counts from
there.

usage: benches/request_memory.py [--models DIR_OR_FILE ...] [--sides 2000,4000]
"""
import argparse
import glob
import io
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request

from PIL import Image

from httpclient import ready, rss_kb

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
SERVER = os.path.join(ROOT, "target/release/sdhop-serve")


def measure(files, sides, photo, port):
    with tempfile.TemporaryDirectory() as d:
        for f in files:
            shutil.copy(f, d)
        p = subprocess.Popen([SERVER, "--addr", f"127.0.0.1:{port}", "--models-dir", d,
                              "--memory-budget-mb", "1000000", "--max-pixels", "100000000"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        base = f"http://127.0.0.1:{port}"
        try:
            for _ in range(1200):
                if ready(base):
                    break
                time.sleep(0.1)
            for side in sides:
                out = io.BytesIO()
                Image.open(photo).convert("RGB").resize((side, side)).save(out, "JPEG", quality=85)
                body = out.getvalue()
                time.sleep(0.5)
                idle = rss_kb(p.pid)
                peak = [idle]
                done = threading.Event()

                def sample():
                    while not done.is_set():
                        peak[0] = max(peak[0], rss_kb(p.pid))
                        time.sleep(0.01)

                t = threading.Thread(target=sample)
                t.start()
                req = urllib.request.Request(f"{base}/detect?timeout_ms=300000&masks=none", data=body,
                                             headers={"Content-Type": "image/jpeg"})
                t0 = time.monotonic()
                try:
                    with urllib.request.urlopen(req, timeout=600) as r:
                        r.read()
                        status = r.status
                except urllib.error.HTTPError as e:
                    status = e.code
                took = time.monotonic() - t0
                done.set()
                t.join()
                above = (peak[0] - idle) * 1024
                px = side * side
                names = ",".join(os.path.basename(f).rsplit(".", 1)[0] for f in files)
                print(f"{names:40s} {side}x{side}: {status} in {took:5.1f} s, idle {idle / 1024:6.0f} MiB, "
                      f"peak above idle {above / 2**20:6.0f} MiB = {above / px:5.1f} B/px")
        finally:
            p.terminate()
            p.wait(timeout=120)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs="*", default=[os.path.join(ROOT, "models", "cup.safetensors"),
                                                    os.path.join(ROOT, "models")])
    ap.add_argument("--sides", default="2000,4000")
    ap.add_argument("--data", default=os.path.join(ROOT, "../shared/data/cmu_ko8"))
    ap.add_argument("--port", type=int, default=18094)
    a = ap.parse_args()
    photo = sorted(glob.glob(os.path.join(a.data, "single/test/*/*.jpg")))[0]
    sides = [int(s) for s in a.sides.split(",")]
    for m in a.models:
        files = sorted(glob.glob(os.path.join(m, "*.safetensors"))) if os.path.isdir(m) else [m]
        measure(files, sides, photo, a.port)
    return 0


if __name__ == "__main__":
    sys.exit(main())
