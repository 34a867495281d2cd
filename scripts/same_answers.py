#!/usr/bin/env python3
"""Whether two builds of the server answer the same on the development photographs.

usage: same_answers.py OLD_SERVE NEW_SERVE [--models DIR] [--images GLOB]... [--every N] [--query Q]

Starts each `sdhop-serve` binary in turn with the same models (default
`models`) on a free port, posts every N-th photograph of the globs
(default: the CMU_KO8 single-pose test photographs and the LM-O
development photographs, the latter with `models/lmo`) to `/detect` with
the query (default `masks=refined&max_detections=20`), and compares the
answers: every detection's label, score, box, component and mask, and the
answer's other fields, apart from timings. Prints one line per differing
photograph and a summary; exit status 0 when every answer is the same.
"""
import argparse, glob, json, os, socket, subprocess, sys, time, urllib.request

KO8 = "../shared/data/cmu_ko8/single/test/*/*.jpg"
LMO = "../shared/data/lmo_dev/test/000002/rgb/*.png"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def strip(x):
    """The answer without the fields that record time."""
    if isinstance(x, dict):
        return {k: strip(v) for k, v in x.items() if "ms" not in k.split("_") and k != "timing_ms"}
    if isinstance(x, list):
        return [strip(v) for v in x]
    return x


def answers(binary, models, files, query):
    port = free_port()
    env = dict(os.environ, SDHOP_LOG="warn")
    proc = subprocess.Popen([binary, "--models-dir", models, "--addr", f"127.0.0.1:{port}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    base = f"http://127.0.0.1:{port}"
    try:
        for _ in range(600):
            try:
                with urllib.request.urlopen(base + "/health/ready", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                time.sleep(0.5)
        else:
            sys.exit(f"{binary}: not ready after 5 minutes")
        out = {}
        for i, f in enumerate(files):
            ctype = "image/png" if f.endswith(".png") else "image/jpeg"
            req = urllib.request.Request(f"{base}/detect?{query}", data=open(f, "rb").read(),
                                         headers={"Content-Type": ctype})
            try:
                with urllib.request.urlopen(req, timeout=300) as r:
                    out[f] = strip(json.loads(r.read()))
            except urllib.error.HTTPError as e:
                out[f] = {"status": e.code, "body": e.read().decode(errors="replace")}
            print(f"\r{os.path.basename(binary)}: {i + 1}/{len(files)}", end="", file=sys.stderr)
        print(file=sys.stderr)
        return out
    finally:
        proc.terminate()
        proc.wait(timeout=60)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("old")
    ap.add_argument("new")
    ap.add_argument("--models", default=None, help="models folder (default: models for CMU_KO8, models/lmo for LM-O)")
    ap.add_argument("--images", action="append", help="a glob of photographs (repeatable)")
    ap.add_argument("--every", type=int, default=1, help="every N-th photograph of each glob")
    ap.add_argument("--query", default="masks=refined&max_detections=20")
    a = ap.parse_args()
    sets = ([(a.models or "models", g) for g in a.images] if a.images
            else [(a.models or "models", KO8), (a.models or "models/lmo", LMO)])
    same = total = 0
    for models, pattern in sets:
        files = sorted(glob.glob(pattern))[::a.every]
        if not files:
            sys.exit(f"{pattern}: no photographs")
        old, new = answers(a.old, models, files, a.query), answers(a.new, models, files, a.query)
        for f in files:
            total += 1
            if old[f] == new[f]:
                same += 1
            else:
                n_old = len(old[f].get("detections", [])) if isinstance(old[f], dict) else "?"
                n_new = len(new[f].get("detections", [])) if isinstance(new[f], dict) else "?"
                print(f"{f}: DIFFERENT ({n_old} detections before, {n_new} after)")
        print(f"{pattern} with {models}: {sum(old[f] == new[f] for f in files)} of {len(files)} answers the same")
    print(f"{same} of {total} answers the same")
    sys.exit(0 if same == total else 1)


if __name__ == "__main__":
    main()
