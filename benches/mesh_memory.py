#!/usr/bin/env python3
"""Memory and time of hostile and large meshes sent to POST /pose, and of
slow pose requests beside /detect. Starts the release server on a
loopback port with the manifest's settings (deploy/sdhop.yaml), samples
its resident memory every 20 ms from /proc, and prints one row per case:
status, latency against the deadline, peak resident memory above idle,
and idle memory after the case.

Cases (each mesh is made here, nothing is read from ../shared):
  junk-element   the 8-vertex cube and `element junk 10000000` (one uchar
                 each) in a 10 MB binary PLY: the count the bytes cannot
                 hold (422 at once)
  over-limit     a binary PLY of 3.4 M triangles, near the 64 MiB body
                 limit (413 from the header)
  polygon-bomb   an OBJ of 4 vertices and one face line of 30 M indices
                 (413 from the counting pass)
  at-limit       a UV sphere of 1 M triangles (the default limit), a real
                 pose request with a 2 s deadline (and with 30 s)
  six-at-limit   six of those at once, 8 s deadlines
  spin           216 bytes: `element junk 18446744073709551615` without
                 properties before a triangle (422 from the header; it spun
                 a core until its deadline)
  long-face      a binary PLY of one face of 60 M uchar indices (60 MB;
                 413 from the list's count before an index is kept)
  eight-long     eight of those at once (the pose lane's size)
  long-ascii     the ASCII form: one face declaring 60 M indices, 6 MB of
                 them present (422 from the bytes left)

Each row also gives the server's CPU seconds for the case (from /proc).

usage: benches/mesh_memory.py [--port 18090] [--models-dir models]
       [--server target/release/sdhop-serve]
"""
import argparse
import io
import json
import os
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

from httpclient import multipart, request

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
# deploy/sdhop.yaml's settings that matter here.
MANIFEST_ENV = {
    "SDHOP_QUEUE_SIZE": "16",
    "SDHOP_MAX_PIXELS": "4000000",
    "SDHOP_TIMEOUT_MS": "30000",
    "SDHOP_MAX_TIMEOUT_MS": "60000",
}
K = {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0}


def rss_mb(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return 0.0


class Sampler:
    """Peak resident memory of `pid` between start() and stop()."""

    def __init__(self, pid):
        self.pid, self.peak, self.run = pid, 0.0, False

    def start(self):
        self.peak, self.run = rss_mb(self.pid), True
        self.t = threading.Thread(target=self._loop, daemon=True)
        self.t.start()

    def _loop(self):
        while self.run:
            self.peak = max(self.peak, rss_mb(self.pid))
            time.sleep(0.02)

    def stop(self):
        self.run = False
        self.t.join()
        return max(self.peak, rss_mb(self.pid))


def cpu_s(pid):
    """User and system CPU seconds of `pid` so far."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


SPIN = (b"ply\nformat ascii 1.0\nelement junk 18446744073709551615\nelement vertex 3\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        b"end_header\n0 0 0\n10 0 0\n0 10 0\n3 0 1 2\n")


def long_face(n):
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uint uchar vertex_indices\nend_header\n")
    v = np.array([[0, 0, 500], [50, 0, 500], [0, 50, 500]], "<f4").tobytes()
    return head + v + np.uint32(n).tobytes() + (np.arange(n, dtype=np.uint32) % 3).astype(np.uint8).tobytes()


def png_640x480():
    from PIL import Image
    rng = np.random.default_rng(1)
    img = (rng.random((480, 640, 3)) * 60 + 90).astype(np.uint8)
    # The sphere of the at-limit case (radius 50 at 500, f = 600), a
    # little off the start, so that the refinement has edges to fit.
    y, x = np.mgrid[0:480, 0:640]
    img[(x - 324) ** 2 + (y - 238) ** 2 < 60 ** 2] = 220
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def ply_binary(vertices, faces, extra=b""):
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
    ).encode() + extra + b"end_header\n"
    v = np.asarray(vertices, "<f4").tobytes()
    f = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", 3)])
    f["n"], f["i"] = 3, faces
    return head + v + f.tobytes()


def uv_sphere(triangles, radius=50.0):
    """A closed UV sphere of about `triangles` triangles."""
    n_lat = int(np.sqrt(triangles / 4))
    n_lon = 2 * n_lat
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    v = np.vstack([[0, 0, 1], v, [0, 0, -1]]) * radius
    idx = 1 + np.arange((n_lat - 1) * n_lon).reshape(n_lat - 1, n_lon)
    a, b = idx[:-1], np.roll(idx[:-1], -1, 1)
    c, d = idx[1:], np.roll(idx[1:], -1, 1)
    quads = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    top = np.stack([np.zeros(n_lon, int), idx[0], np.roll(idx[0], -1)], -1)
    last = len(v) - 1
    bot = np.stack([np.full(n_lon, last), np.roll(idx[-1], -1), idx[-1]], -1)
    return v, np.concatenate([top, quads, bot])


def post_pose(port, image, mesh, timeout_ms):
    params = {"intrinsics": K,
              "initial_pose": {"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "translation": [0, 0, 500]},
              "max_iterations": 10}
    body, ctype = multipart([("image", "image/png", image), ("mesh", "application/octet-stream", mesh),
                             ("params", "application/json", json.dumps(params).encode())])
    return request(f"http://127.0.0.1:{port}/pose?timeout_ms={timeout_ms}", body, ctype)


def wait_ready(port):
    for _ in range(1200):
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/health/ready", timeout=1) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.05)
    sys.exit("the server never became ready")


def settle(pid, seconds=2.0):
    time.sleep(seconds)
    return rss_mb(pid)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--port", type=int, default=18090)
    ap.add_argument("--models-dir", default=os.path.join(ROOT, "models"))
    ap.add_argument("--server", default=os.path.join(ROOT, "target", "release", "sdhop-serve"))
    a = ap.parse_args()
    env = dict(os.environ, **MANIFEST_ENV)
    srv = subprocess.Popen([a.server, "--addr", f"127.0.0.1:{a.port}", "--models-dir", a.models_dir],
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_ready(a.port)
        image = png_640x480()
        cube = np.array([[x, y, z] for x in (-50, 50) for y in (-50, 50) for z in (-50, 50)], float)
        junk = ply_binary(cube, [[0, 1, 2]], b"element junk 10000000\nproperty uchar a\n")
        junk = junk + bytes(10 ** 7 - 10)
        big_v, big_f = uv_sphere(3_400_000)
        over = ply_binary(big_v, big_f)
        bomb = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf " + b"1 2 3 4 " * 7_500_000 + b"\n"
        v, f = uv_sphere(1_000_000)
        at_limit = ply_binary(v, f)
        face = long_face(60_000_000)
        ascii_face = (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                      b"property float z\nelement face 1\nproperty list uint uchar vertex_indices\nend_header\n"
                      b"0 0 500\n50 0 500\n0 50 500\n60000000" + b" 0 1 2" * 1_000_000 + b"\n")
        print(f"meshes: junk {len(junk) / 1e6:.1f} MB, over-limit {len(over) / 1e6:.1f} MB "
              f"({len(big_f)} triangles), polygon bomb {len(bomb) / 1e6:.1f} MB, "
              f"at-limit {len(at_limit) / 1e6:.1f} MB ({len(f)} triangles)")
        idle = settle(srv.pid)
        print(f"idle resident memory {idle:.0f} MB")
        print(f"{'case':14s} {'status':>8s} {'latency s':>10s} {'deadline s':>10s} {'peak above idle MB':>19s} "
              f"{'idle after MB':>13s} {'CPU s':>6s}  message")
        for name, mesh, deadline_ms, n in [("junk-element", junk, 2000, 1), ("over-limit", over, 2000, 1),
                                           ("polygon-bomb", bomb, 2000, 1), ("at-limit", at_limit, 2000, 1),
                                           ("at-limit-30s", at_limit, 30000, 1),
                                           ("six-at-limit", at_limit, 8000, 6),
                                           ("spin", SPIN, 3000, 1), ("long-face", face, 20000, 1),
                                           ("eight-long", face, 20000, 8), ("long-ascii", ascii_face, 20000, 1)]:
            before = rss_mb(srv.pid)
            cpu0 = cpu_s(srv.pid)
            s = Sampler(srv.pid)
            s.start()
            results = [None] * n
            ts = [threading.Thread(target=lambda i=i: results.__setitem__(i, post_pose(a.port, image, mesh, deadline_ms)))
                  for i in range(n)]
            for t in ts:
                t.start()
            for t in ts:
                t.join()
            peak = s.stop()
            cpu = cpu_s(srv.pid) - cpu0
            after = settle(srv.pid)
            statuses = ",".join(str(r[0]) for r in results)
            lat = max(r[1] for r in results)
            if len(set(r[0] for r in results)) == 1:
                statuses = f"{results[0][0]}x{n}" if n > 1 else str(results[0][0])
            print(f"{name:14s} {statuses:>8s} {lat:10.2f} {deadline_ms / 1000:10.1f} {peak - before:19.0f} "
                  f"{after:13.0f} {cpu:6.2f}  {results[0][2][:90]}")
    finally:
        srv.terminate()
        srv.wait()


if __name__ == "__main__":
    main()
