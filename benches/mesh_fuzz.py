#!/usr/bin/env python3
"""A bounded fuzz loop over the mesh readers through POST /pose.

Starts the release server (the shipped models, or --models-dir) on a
loopback port, then sends mutated meshes until --cases requests or
--seconds have passed, whichever comes first, and checks every answer:

  - a status the API documents for a mesh (200, 400, 413, 422, 503), never
    a 5xx other than 503, never a closed connection;
  - an error message of one line, without a Rust debug dump (`{ ... }`);
  - the answer within the request's deadline (plus --slack seconds);
  - the server's CPU time for the request within --cpu-factor times the
    wall time a request may take (a spin shows as CPU time at the deadline);
  - the server still live (every 100 requests, and at the end).

The seeds are made here: a cube and a subdivided box as ASCII,
little-endian and big-endian PLY (with colours, normals, extra elements,
every count and index type) and OBJ (with `v/vt/vn`, negative indices,
comments, groups, CRLF). The mutations: bytes flipped, inserted, deleted
or repeated; a number token replaced by a hostile one (2^64-1, -1, 1e39,
nan, +7, 300, 0x10); a header count replaced; a type name swapped; a
UTF-8 BOM, a no-break space or a zero-width space inserted; lines
duplicated, swapped or cut; the file truncated; and two or three of these
at once. Failing cases are written to --out (one file each, with the
answer beside it), and the run exits 1.

usage: benches/mesh_fuzz.py [--seed 1] [--cases 3000] [--seconds 300]
       [--port 18095] [--models-dir models] [--out out/mesh_fuzz]
"""
import argparse
import json
import os
import random
import re
import struct
import subprocess
import sys
import time
import urllib.request
import zlib

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from httpclient import multipart, request  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
K = {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0}
ALLOWED = {200, 400, 413, 422, 503}
# A Rust struct's debug form, `Name { field: ... }` (an echoed `\u{a0}` is not).
DEBUG_DUMP = re.compile(r"[A-Z][A-Za-z]+ \{ ?[a-z_]+: ")
HOSTILE = [b"18446744073709551615", b"4294967295", b"2147483648", b"-1", b"-0", b"1e39", b"nan",
           b"inf", b"+7", b"300", b"0x10", b"1.5", b"", b"00000000000000000000001", b"65536",
           b"\xc2\xa07", b"7\xe2\x80\x8b"]
TYPES = [b"char", b"uchar", b"short", b"ushort", b"int", b"uint", b"float", b"double", b"int8",
         b"uint8", b"int16", b"uint16", b"int32", b"uint32", b"float32", b"float64", b"list", b"quux"]


def png(width=640, height=480):
    """A grey image with a bright square where the cube projects."""
    rows = []
    for y in range(height):
        row = bytearray([0])
        for x in range(width):
            v = 220 if 260 <= x < 380 and 180 <= y < 300 else 90 + (x * 7 + y * 3) % 23
            row += bytes((v, v, v))
        rows.append(bytes(row))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    head = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head) + chunk(b"IDAT", zlib.compress(b"".join(rows), 6))
            + chunk(b"IEND", b""))


def box(subdivide=0, size=100.0):
    """A closed box of half-size `size`/2, each face split in 4^subdivide."""
    h = size / 2
    verts = [(x, y, z) for x in (-h, h) for y in (-h, h) for z in (-h, h)]
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    for _ in range(subdivide):
        mid, out = {}, []

        def m(i, j):
            k = (min(i, j), max(i, j))
            if k not in mid:
                verts.append(tuple((verts[i][c] + verts[j][c]) / 2 for c in range(3)))
                mid[k] = len(verts) - 1
            return mid[k]
        for a, b, c in tris:
            ab, bc, ca = m(a, b), m(b, c), m(c, a)
            out += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
        tris = out
    return verts, tris


def ply_ascii(verts, tris, extras=True):
    head = ["ply", "format ascii 1.0", "comment made by mesh_fuzz", f"element vertex {len(verts)}",
            "property float x", "property float y", "property float z"]
    if extras:
        head += ["property float nx", "property uchar red", "property uchar green", "property uchar blue"]
    head += [f"element face {len(tris)}", "property list uchar int vertex_indices"]
    if extras:
        head += ["element material 1", "property list uchar float rgba"]
    head.append("end_header")
    lines = [" ".join(f"{c:g}" for c in v) + (" 0.5 200 100 50" if extras else "") for v in verts]
    lines += ["3 " + " ".join(map(str, t)) for t in tris]
    if extras:
        lines.append("4 1 0.5 0.25 1")
    return ("\n".join(head + lines) + "\n").encode()


def ply_binary(verts, tris, big=False, count="uchar", index="int"):
    e = ">" if big else "<"
    fmt = {"uchar": "B", "ushort": "H", "uint": "I", "int": "i", "short": "h", "char": "b"}
    head = (f"ply\nformat binary_{'big' if big else 'little'}_endian 1.0\nelement vertex {len(verts)}\n"
            "property float x\nproperty float y\nproperty float z\nproperty uchar flags\n"
            f"element face {len(tris)}\nproperty list {count} {index} vertex_indices\n"
            "element junk 2\nproperty double a\nend_header\n").encode()
    body = b"".join(struct.pack(e + "fffB", *v, 7) for v in verts)
    body += b"".join(struct.pack(e + fmt[count] + fmt[index] * 3, 3, *t) for t in tris)
    body += struct.pack(e + "dd", 1.0, 2.0)
    return head + body


def obj(verts, tris, crlf=False, negative=False):
    nl = "\r\n" if crlf else "\n"
    out = ["# made by mesh_fuzz", "mtllib none.mtl", "o box", "g side"]
    out += [f"v {x:g} {y:g} {z:g}" for x, y, z in verts]
    out += ["vt 0 0", "vn 0 0 1", "s off"]
    n = len(verts)
    for a, b, c in tris:
        if negative:
            out.append(f"f {a - n} {b - n} {c - n}")
        else:
            out.append(f"f {a + 1}/1/1 {b + 1}//1 {c + 1}/1")
    return (nl.join(out) + nl).encode()


def seeds():
    small, dense = box(0), box(2)
    return [ply_ascii(*small), ply_ascii(*dense, extras=False), ply_binary(*small),
            ply_binary(*dense, big=True), ply_binary(*small, count="ushort", index="uint"),
            ply_binary(*small, big=True, count="uint", index="short"), obj(*small), obj(*dense, crlf=True),
            obj(*small, negative=True)]


def mutate(data, rng):
    """One mutation of `data`."""
    b = bytearray(data)
    kind = rng.randrange(12)
    if kind == 0 and b:  # flip bytes
        for _ in range(rng.randint(1, 8)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    elif kind == 1:  # insert bytes
        at = rng.randrange(len(b) + 1)
        b[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    elif kind == 2 and b:  # delete a run
        at = rng.randrange(len(b))
        del b[at:at + rng.randint(1, 64)]
    elif kind == 3 and b:  # repeat a run
        at = rng.randrange(len(b))
        run = b[at:at + rng.randint(1, 256)]
        b[at:at] = run * rng.randint(1, 50)
    elif kind in (4, 5):  # a number token replaced
        tokens = [i for i in range(1, len(b)) if chr(b[i]).isdigit() and not chr(b[i - 1]).isalnum()]
        if tokens:
            at = rng.choice(tokens)
            end = at
            while end < len(b) and (chr(b[end]).isalnum() or b[end] in b".-+"):
                end += 1
            b[at:end] = rng.choice(HOSTILE)
    elif kind == 6:  # a header count replaced
        i = b.find(b"element ", rng.randrange(max(1, min(len(b), 400))))
        if i < 0:
            i = b.find(b"element ")
        if i >= 0:
            eol = b.find(b"\n", i)
            sp = b.rfind(b" ", i, eol)
            if sp > 0:
                b[sp + 1:eol] = rng.choice(HOSTILE)
    elif kind == 7:  # a type swapped
        for t in rng.sample(TYPES, len(TYPES)):
            i = b.find(b" " + t + b" ")
            if i >= 0:
                b[i + 1:i + 1 + len(t)] = rng.choice(TYPES)
                break
    elif kind == 8:  # invisible characters
        mark = rng.choice([b"\xef\xbb\xbf", b"\xc2\xa0", b"\xe2\x80\x8b", b"\t", b"\r", b"\x00"])
        at = 0 if rng.random() < 0.3 else rng.randrange(len(b) + 1)
        b[at:at] = mark
    elif kind == 9:  # lines duplicated or swapped
        lines = bytes(b).split(b"\n")
        if len(lines) > 2:
            i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
            if rng.random() < 0.5:
                lines.insert(j, lines[i])
            else:
                lines[i], lines[j] = lines[j], lines[i]
        b = bytearray(b"\n".join(lines))
    elif kind == 10 and b:  # truncated
        del b[rng.randrange(len(b)):]
    else:  # every face twice, or a huge declared list
        if rng.random() < 0.5:
            b += b[len(b) // 2:]
        else:
            b += rng.choice([b"4294967295 1 2 3\n", struct.pack("<BI", 255, 0xFFFFFFFF)])
    return bytes(b)


def cpu_seconds(pid):
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def live(port):
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/health/live", timeout=5) as r:
            return r.status == 200
    except OSError:
        return False


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=1, help="random seed of the mutations (default 1)")
    ap.add_argument("--cases", type=int, default=3000, help="requests at most (default 3000)")
    ap.add_argument("--seconds", type=float, default=300, help="time at most (default 300)")
    ap.add_argument("--timeout-ms", type=int, default=2000, help="each request's deadline (default 2000)")
    ap.add_argument("--slack", type=float, default=0.5, help="seconds past the deadline allowed (default 0.5)")
    ap.add_argument("--cpu-factor", type=float, default=2.5,
                    help="server CPU seconds allowed per wall second of a request (default 2.5: 2 cores)")
    ap.add_argument("--port", type=int, default=18095)
    ap.add_argument("--models-dir", default=os.path.join(ROOT, "models"))
    ap.add_argument("--server", default=os.path.join(ROOT, "target", "release", "sdhop-serve"))
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "mesh_fuzz"), help="where failing cases go")
    a = ap.parse_args()
    rng = random.Random(a.seed)
    srv = subprocess.Popen([a.server, "--addr", f"127.0.0.1:{a.port}", "--models-dir", a.models_dir,
                            "--drain-seconds", "0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    failures, statuses, worst_cpu, worst_wall = [], {}, (0.0, ""), (0.0, "")
    try:
        for _ in range(1200):
            if live(a.port) or srv.poll() is not None:
                break
            time.sleep(0.05)
        if not live(a.port):
            sys.exit(f"the server did not start on port {a.port}")
        image, pool = png(), seeds()
        params = json.dumps({"intrinsics": K, "max_iterations": 10, "initial_pose": {
            "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "translation": [0, 0, 500]}}).encode()
        start, n = time.monotonic(), 0
        while n < a.cases and time.monotonic() - start < a.seconds:
            mesh = rng.choice(pool)
            for _ in range(rng.choice([1, 1, 1, 2, 3])):
                mesh = mutate(mesh, rng)
            body, ctype = multipart([("image", "image/png", image), ("mesh", "application/octet-stream", mesh),
                                     ("params", "application/json", params)])
            cpu0 = cpu_seconds(srv.pid)
            status, took, msg = request(f"http://127.0.0.1:{a.port}/pose?timeout_ms={a.timeout_ms}", body, ctype,
                                        timeout=a.timeout_ms / 1000 + 30)
            cpu = cpu_seconds(srv.pid) - cpu0
            n += 1
            statuses[status] = statuses.get(status, 0) + 1
            worst_cpu = max(worst_cpu, (cpu, msg[:80]))
            worst_wall = max(worst_wall, (took, msg[:80]))
            why = []
            if status not in ALLOWED:
                why.append(f"status {status}")
            if "\n" in msg or DEBUG_DUMP.search(msg):
                why.append("a message of several lines or a debug dump")
            limit = a.timeout_ms / 1000 + a.slack
            if took > limit:
                why.append(f"answered after {took:.2f} s (deadline {a.timeout_ms} ms)")
            if cpu > a.cpu_factor * limit:
                why.append(f"{cpu:.2f} CPU-seconds")
            if n % 100 == 0 and not live(a.port):
                why.append("the server is not live afterwards")
            if why:
                os.makedirs(a.out, exist_ok=True)
                name = os.path.join(a.out, f"seed{a.seed}-case{n}")
                with open(name + ".mesh", "wb") as f:
                    f.write(mesh)
                with open(name + ".txt", "w") as f:
                    f.write(f"{'; '.join(why)}\nstatus {status}, {took:.3f} s, {cpu:.3f} CPU-s\n{msg}\n")
                failures.append((n, why, msg[:120]))
                print(f"case {n}: {'; '.join(why)}: {msg[:120]!r}", flush=True)
            if n % 500 == 0:
                print(f"{n} cases, {time.monotonic() - start:.0f} s, statuses {statuses}", flush=True)
        alive = live(a.port)
        print(f"seed {a.seed}: {n} cases in {time.monotonic() - start:.0f} s; statuses "
              f"{dict(sorted(statuses.items(), key=str))}; slowest {worst_wall[0]:.3f} s ({worst_wall[1]!r}); "
              f"most server CPU {worst_cpu[0]:.3f} s ({worst_cpu[1]!r}); failures {len(failures)}; "
              f"server live at the end: {alive}")
        if failures or not alive:
            sys.exit(1)
    finally:
        srv.terminate()
        srv.wait()


if __name__ == "__main__":
    main()
