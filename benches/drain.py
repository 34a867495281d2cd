#!/usr/bin/env python3
"""SIGTERM as Kubernetes sends it: starts the release server with the
shipped models on a loopback port (default drain; --grace-seconds as
given), starts an upload that trickles at --rate bytes per second (above
the server's --min-body-rate) and will not end, sends SIGTERM, and then
until the server exits: probes /health/ready every 100 ms and sends a
/detect every 300 ms (a photograph made here). Prints what the probes and
the detections got during the drain and after it, and the status the
slow upload got and when.

usage: benches/drain.py [--port 18093] [--grace-seconds 3] [--rate 20000]
       [--server target/release/sdhop-serve] [--models-dir models]
"""
import argparse
import os
import signal
import socket
import struct
import subprocess
import threading
import time
import zlib
from collections import Counter

from httpclient import request

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def png(width=320, height=240):
    rows = b"".join(b"\x00" + bytes((x * 5 + y * 3) % 256 for x in range(width) for _ in range(3))
                    for y in range(height))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--port", type=int, default=18093)
    ap.add_argument("--grace-seconds", type=int, default=3)
    ap.add_argument("--rate", type=int, default=20000, help="the slow upload's bytes per second")
    ap.add_argument("--server", default=os.path.join(ROOT, "target", "release", "sdhop-serve"))
    ap.add_argument("--models-dir", default=os.path.join(ROOT, "models"))
    a = ap.parse_args()
    base = f"http://127.0.0.1:{a.port}"
    srv = subprocess.Popen([a.server, "--addr", f"127.0.0.1:{a.port}", "--models-dir", a.models_dir,
                            "--grace-seconds", str(a.grace_seconds)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(1200):
        if request(base + "/health/ready", timeout=1)[0] == 200:
            break
        time.sleep(0.05)
    upload = socket.create_connection(("127.0.0.1", a.port))
    upload.sendall(b"POST /detect HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n"
                   b"Content-Length: 100000000\r\n\r\n")
    answer = {}

    def trickle():
        chunk = bytes(a.rate // 10)
        try:
            while "status" not in answer:
                upload.sendall(chunk)
                time.sleep(0.1)
        except OSError as e:
            answer.setdefault("send error", str(e))

    def read_status():
        upload.settimeout(120)
        try:
            data = upload.recv(200)
            answer["status"] = data.split(b"\r\n", 1)[0].decode(errors="replace") or "closed, no status"
        except OSError as e:
            answer["status"] = f"no status ({e})"
        answer["at"] = time.monotonic() - sent

    threads = [threading.Thread(target=trickle), threading.Thread(target=read_status)]
    for t in threads:
        t.start()
    time.sleep(1.0)
    image = png()
    sent = time.monotonic()
    srv.send_signal(signal.SIGTERM)
    probes, detects = [], []
    last_detect = 0.0
    while srv.poll() is None:
        now = time.monotonic() - sent
        probes.append((now, request(base + "/health/ready", timeout=2)[0]))
        if now - last_detect > 0.3:
            last_detect = now
            detects.append((now, request(base + "/detect?timeout_ms=2000", image, "image/png")[0]))
        time.sleep(0.1)
    exited = time.monotonic() - sent
    for t in threads:
        t.join(timeout=5)
    drain = 5.0  # the server's default --drain-seconds
    during = Counter(s for t, s in probes if t < drain - 0.2)
    after = Counter(s for t, s in probes if t >= drain + 0.2)
    print(f"SIGTERM; exited after {exited:.2f} s (drain {drain:.0f} s + grace {a.grace_seconds} s)")
    print(f"/health/ready during the drain: {dict(during)}; after it: {dict(after)}")
    print(f"/detect during the drain: {dict(Counter(s for t, s in detects if t < drain - 0.2))}; "
          f"after it: {dict(Counter(s for t, s in detects if t >= drain + 0.2))}")
    print(f"slow upload ({a.rate} B/s): {answer.get('status')!r} after {answer.get('at', float('nan')):.2f} s")


if __name__ == "__main__":
    main()
