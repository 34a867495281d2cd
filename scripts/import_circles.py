#!/usr/bin/env python3
"""Import circles among the crate's modules: exit status 1 if there is one.

usage: scripts/import_circles.py [SRC]   (default: src)

Reads every `crate::...` and `super::...` path of the library's code
(comments and `#[cfg(test)] mod tests` left out; `cli` and the binaries are
the top and may use anything), resolves it to the module it names, and
looks for circles in two graphs: between the top-level modules (`train ->
vision -> train` is one), and between the modules one level down within a
top-level module (`train/ko8 -> train/multiview -> train/ko8`). A module
using its parent or its child is Rust's ordinary nesting, not a circle.
Prints each graph's circles, or that there are none. CI runs it.
"""
import collections, os, re, sys

ROOT = sys.argv[1] if len(sys.argv) > 1 else "src"


def module_of(path):
    rel = os.path.relpath(path, ROOT)[:-3].split(os.sep)
    return rel[:-1] if rel[-1] in ("mod", "lib") else rel


def library_code(path):
    lines = [l for l in open(path).read().split("\n") if not l.strip().startswith("//")]
    return re.split(r"#\[cfg\(test\)\]\s*mod tests\s*\{", "\n".join(lines))[0]


files = {}
for d, _, names in os.walk(ROOT):
    for n in names:
        if n.endswith(".rs"):
            p = os.path.join(d, n)
            files["/".join(module_of(p))] = p


def resolve(current, path):
    parts = path.split("::")
    if parts[0] == "crate":
        base, parts = [], parts[1:]
    else:
        base = current[:-1]
        parts = parts[1:]
        while parts and parts[0] == "super":
            base, parts = base[:-1], parts[1:]
    found = None
    for i in range(len(parts) + 1):
        cand = "/".join(base + parts[:i])
        if cand in files:
            found = cand
    return found


edges = collections.defaultdict(set)
for m, p in files.items():
    cur = m.split("/")
    if not m or cur[0] in ("bin", "cli") or cur[-1] == "tests" or p.endswith("_tests.rs"):
        continue
    for hit in re.finditer(r"\b((?:crate|super)(?:::[A-Za-z_0-9]+)+)", library_code(p)):
        t = resolve(cur, hit.group(1))
        if t is not None and t != m and not m.startswith(t + "/") and not t.startswith(m + "/"):
            edges[m].add(t)


def graph(depth):
    g = collections.defaultdict(set)
    for a, targets in edges.items():
        for b in targets:
            ta, tb = "/".join(a.split("/")[:depth]), "/".join(b.split("/")[:depth])
            nested = ta.startswith(tb + "/") or tb.startswith(ta + "/")
            same_parent = depth == 1 or ta.split("/")[0] == tb.split("/")[0]
            if ta != tb and not nested and same_parent and ta and tb:
                g[ta].add(tb)
    return g


def circles(g):
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, n = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in list(g):
        if v not in index:
            visit(v)
    return out


bad = 0
for depth, what in ((1, "top-level modules"), (2, "modules within each top-level module")):
    g = graph(depth)
    found = circles(g)
    bad += len(found)
    if not found:
        print(f"no import circle among the {what}")
    for comp in found:
        print(f"import circle among the {what}: " + ", ".join(
            f"{a} -> {sorted(x for x in g[a] if x in comp)}" for a in comp))
sys.exit(1 if bad else 0)
