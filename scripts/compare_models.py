#!/usr/bin/env python3
"""Whether two folders (or files) of sdhop weights hold the same models.

usage: compare_models.py A B

Each `*.safetensors` of A is compared with the file of the same name in B:
every tensor byte for byte (name, dtype, shape, data), and the metadata
JSON equal apart from the fields that record when, where or by which build
a model was made (time, commit, paths of the run). Prints one line a file
and a summary; exit status 0 when every file matches, 1 otherwise.
"""
import json, struct, sys
from pathlib import Path

# Metadata fields that record a run rather than the model.
VOLATILE = {"created", "commit", "version", "git", "time", "seconds", "trained_at",
            "build", "host", "command", "duration_s", "elapsed_s", "train_seconds"}


def read(path):
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + n])
    data = raw[8 + n:]
    meta = header.pop("__metadata__", {}) or {}
    tensors = {k: (v["dtype"], v["shape"], data[v["data_offsets"][0]:v["data_offsets"][1]])
               for k, v in header.items()}
    parsed = {}
    for k, v in meta.items():
        try:
            parsed[k] = json.loads(v)
        except (ValueError, TypeError):
            parsed[k] = v
    # The digest covers the metadata as stored, times included.
    parsed.pop("sdhop.sha256", None)
    return tensors, parsed


def strip(x):
    if isinstance(x, dict):
        return {k: strip(v) for k, v in x.items() if k not in VOLATILE and not k.endswith("_seconds")}
    if isinstance(x, list):
        return [strip(v) for v in x]
    return x


def diff(a, b, where=""):
    """The first few paths where a and b differ."""
    out = []
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{where}/{k}: only in {'B' if k not in a else 'A'}")
            else:
                out += diff(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            out += diff(x, y, f"{where}[{i}]")
    elif a != b:
        out.append(f"{where}: {str(a)[:60]} != {str(b)[:60]}")
    return out[:5]


def files(p):
    p = Path(p)
    return {p.name: p} if p.is_file() else {f.name: f for f in sorted(p.glob("*.safetensors"))}


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    a, b = files(sys.argv[1]), files(sys.argv[2])
    if not a:
        sys.exit(f"{sys.argv[1]}: no weights files")
    bad = 0
    for name, pa in a.items():
        if name not in b:
            print(f"{name}: missing in {sys.argv[2]}")
            bad += 1
            continue
        (ta, ma), (tb, mb) = read(pa), read(b[name])
        problems = []
        if ta.keys() != tb.keys():
            problems.append(f"tensor names differ: {sorted(set(ta) ^ set(tb))}")
        for k in sorted(set(ta) & set(tb)):
            if ta[k] != tb[k]:
                problems.append(f"tensor {k} differs")
        problems += diff(strip(ma), strip(mb))
        bad += bool(problems)
        print(f"{name}: {'same tensors and metadata' if not problems else 'DIFFERENT: ' + '; '.join(problems[:6])}")
    print(f"{len(a) - bad} of {len(a)} models the same")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
