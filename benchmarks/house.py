"""The shape of the package in figures (issue 26): sizes, layout, circles, private imports, test mirror.

    python benchmarks/house.py            # print the figures
    python benchmarks/house.py --check    # also exit 1 when a house rule is broken (tests/test_lint.py)

Rules checked: no module over MAX_LINES lines; at most MAX_TOP modules at the top level of the package (not
counting `__init__` and `__main__`); one `FloatArray`; no import cycle between modules or between the
subpackages of a package; no private name (`_x`) imported from, or read off, another magcal module; every module
has a test file where tests/ mirrors the package, or is named in a test module's docstring.
"""

from __future__ import annotations

import argparse
import ast
import re
import statistics
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "magcal_cli"
TESTS = ROOT / "tests"
MAX_LINES = 450
MAX_TOP = 18    # 17 core and orchestration modules, and `api`: the Python API users import by name (issue 40)


def modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package."""
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = list(f.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


def absolute(name: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module an `from X import ...` names, relative imports resolved against `name`'s package."""
    if not node.level:
        return node.module or ""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The package modules `name` imports (at any depth of the file: lazy imports count)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and absolute(name, path, node).startswith("magcal_cli"):
            module = absolute(name, path, node)
            out.add(module)
            out.update(f"{module}.{a.name}" for a in node.names if f"{module}.{a.name}" in known)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("magcal_cli"))
    return {m for m in out if m in known and m != name}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one member (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def knots(graph: dict[str, set[str]], packages: set[str]) -> list[list[str]]:
    """Cycles between the children (modules or subpackages, each with its descendants) of every package."""
    out = []
    for pkg in sorted(packages):
        def child(m: str, pkg: str = pkg) -> str | None:
            if not m.startswith(pkg + "."):
                return None
            return pkg + "." + m[len(pkg) + 1:].split(".")[0]
        sib: dict[str, set[str]] = defaultdict(set)
        for a, deps in graph.items():
            ca = child(a)
            if ca is None:
                continue
            sib[ca]
            for b in deps:
                cb = child(b)
                if cb is not None and cb != ca:
                    sib[ca].add(cb)
        out += [c for c in cycles(sib) if any(p in packages for p in c)]
    return out


def private_uses(name: str, path: Path, known: set[str]) -> list[str]:
    """`from magcal_cli.x import _y` and `x._y` where x names a magcal module, in one file."""
    tree = ast.parse(path.read_text())
    bound = {}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (module := absolute(name, path, node)).startswith("magcal_cli"):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    out.append(f"{name}: imports {module}.{a.name}")
                if f"{module}.{a.name}" in known:
                    bound[a.asname or a.name] = f"{module}.{a.name}"
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("magcal_cli") and a.asname:
                    bound[a.asname] = a.name
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in bound
                and node.attr.startswith("_") and not node.attr.startswith("__")):
            out.append(f"{name}: reads {bound[node.value.id]}.{node.attr}")
    return out


def untested(mods: dict[str, Path]) -> list[str]:
    """Modules with neither a mirrored test file nor a mention in a test module's docstring."""
    docs = ""
    for f in TESTS.rglob("*.py"):
        doc = ast.get_docstring(ast.parse(f.read_text())) or ""
        docs += doc + "\n"
    named = set(re.findall(r"magcal_cli(?:\.\w+)+", docs)) | {
        p.replace("/", ".").removesuffix(".py") for p in re.findall(r"magcal_cli/[\w/]+\.py", docs)}
    out = []
    for name, path in mods.items():
        if path.name in ("__init__.py", "__main__.py") or name in named:
            continue
        rel = path.relative_to(PACKAGE)
        mirrored = TESTS / rel.parent / f"test_{rel.stem}.py"
        if not mirrored.exists():
            out.append(name)
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the figures; with --check, exit 1 when a rule is broken."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    mods = modules()
    known = set(mods)
    packages = {n for n, p in mods.items() if p.name == "__init__.py"}
    lines = {n: len(p.read_text().splitlines()) for n, p in mods.items()}
    sizes = [v for n, v in lines.items() if mods[n].name != "__init__.py" or v > 5]
    graph = {n: imports(n, p, known) for n, p in mods.items()}
    # a package's own __init__ importing its children is not a circle between siblings
    sibling_graph = {n: {d for d in deps if not n.startswith(d + ".") and not d.startswith(n + ".")}
                     for n, deps in graph.items()}
    funcs = [f for p in mods.values() for f in ast.walk(ast.parse(p.read_text()))
             if isinstance(f, ast.FunctionDef | ast.AsyncFunctionDef)]
    top = [n for n, p in mods.items() if n.count(".") == 1 and p.name not in ("__init__.py", "__main__.py")
           and p.parent == PACKAGE]
    floatarray = [n for n, p in mods.items() if re.search(r"^FloatArray\s*(:[^=]*)?=", p.read_text(), re.M)]
    private = [u for n, p in mods.items() for u in private_uses(n, p, known)]
    big = sorted((v, n) for n, v in lines.items() if v > MAX_LINES)
    circles = cycles(sibling_graph)
    knotted = knots(sibling_graph, packages)
    missing = untested(mods)
    figures = {
        "modules": len(mods), "lines": sum(lines.values()), "median_module_lines": statistics.median(sizes),
        "largest_module": f"{max(lines, key=lines.__getitem__)} ({max(lines.values())} lines)",
        f"modules_over_{MAX_LINES}": len(big), "top_level_modules": len(top), "subpackages": len(packages) - 1,
        "functions_with_docstring_pct": round(100.0 * sum(bool(ast.get_docstring(f)) for f in funcs) / len(funcs), 1),
        "module_circles": len(circles), "package_knots": len(knotted), "FloatArray_definitions": len(floatarray),
        "private_names_across_modules": len(private), "modules_without_tests": len(missing),
    }
    width = max(map(len, figures))
    for k, v in figures.items():
        print(f"{k:{width}}  {v}")
    broken = ([f"{n}: {v} lines (limit {MAX_LINES})" for v, n in big]
              + ([f"{len(top)} top-level modules (limit {MAX_TOP}): {', '.join(top)}"] if len(top) > MAX_TOP else [])
              + [f"module circle: {' <-> '.join(c)}" for c in circles]
              + [f"package knot: {' <-> '.join(c)}" for c in knotted]
              + ([f"FloatArray defined in {', '.join(floatarray)}"] if len(floatarray) != 1 else [])
              + private + [f"{m}: no tests/<mirrored path>/test_<name>.py and no test docstring names it"
                           for m in missing])
    for b in broken:
        print(f"BROKEN  {b}")
    return 1 if args.check and broken else 0


if __name__ == "__main__":
    sys.exit(main())
