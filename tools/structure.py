"""How the package is built: sizes, import cycles and private cross-module reads.

Run ``python -m tools.structure`` from the repository root for a report, or
``python -m tools.structure --json`` for the figures as JSON. The limits the
project keeps (``tests/test_structure.py`` asserts them):

* no class over 400 lines, no module over 600 lines, no function over 80 lines
  in ``torchrl_robotmem/``;
* no import cycle inside the package, counting function-local imports;
* nothing in ``torchrl_robotmem/storage/`` imports the package root;
* no module reads a private name (``obj._name`` or ``from m import _name``)
  that another module of the package defines, and no module imports a private
  module (``_backend``) from outside the package that holds it.

Everything is read with :mod:`ast`; nothing is imported or executed.
"""
from __future__ import annotations

import argparse
import ast
import json
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "torchrl_robotmem"

MAX_CLASS = 400
MAX_MODULE = 600
MAX_FUNCTION = 80


@dataclass
class Module:
    name: str
    path: Path
    tree: ast.Module
    lines: int
    is_package: bool
    imports: set[str] = field(default_factory=set)
    defined_private: set[str] = field(default_factory=set)


def _module_name(path: Path, root: Path) -> tuple[str, bool]:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join(parts), is_package


def load(root: Path = ROOT, package: str = PACKAGE) -> dict[str, Module]:
    """Parse every module of ``package`` under ``root``."""
    modules = {}
    for path in sorted((root / package).rglob("*.py")):
        text = path.read_text()
        name, is_package = _module_name(path, root)
        tree = ast.parse(text, filename=str(path))
        modules[name] = Module(name, path, tree, len(text.splitlines()), is_package)
    for mod in modules.values():
        mod.imports = _imports(mod, modules)
        mod.defined_private = _defined_private(mod.tree)
    return modules


def _resolve(mod: Module, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = mod.name.split(".")
    if not mod.is_package:
        base = base[:-1]
    if node.level > 1:
        base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(mod: Module, modules: dict[str, Module]) -> set[str]:
    """Modules of the package that ``mod`` imports anywhere (also inside functions)."""
    out = set()
    for node in ast.walk(mod.tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == PACKAGE:
                    target = alias.name
                    while target not in modules and "." in target:
                        target = target.rsplit(".", 1)[0]
                    out.add(target)
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(mod, node)
            if target.split(".")[0] != PACKAGE:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                out.add(sub if sub in modules else target)
    out.discard(mod.name)
    return {m for m in out if m in modules}


def _defined_private(tree: ast.Module) -> set[str]:
    """Private names a module defines: functions, classes, attributes it assigns."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
    return {n for n in names if n.startswith("_") and not n.startswith("__")}


def sizes(modules: dict[str, Module]):
    """(kind, qualified name, lines) for every class and function, and every module."""
    rows = []
    for mod in modules.values():
        rows.append(("module", mod.name, mod.lines))

        def visit(node, prefix):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    kind = "class" if isinstance(child, ast.ClassDef) else "function"
                    qual = f"{prefix}.{child.name}"
                    rows.append((kind, qual, child.end_lineno - child.lineno + 1))
                    visit(child, qual)
                else:
                    visit(child, prefix)

        visit(mod.tree, mod.name)
    return rows


def cycles(modules: dict[str, Module]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []
    counter = [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(modules[v].imports):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(modules):
        if v not in index:
            strong(v)
    return out


def root_imports(modules: dict[str, Module], subpackage: str = f"{PACKAGE}.storage"):
    """Modules of ``subpackage`` that import the package root."""
    return sorted(m.name for m in modules.values()
                  if m.name.startswith(subpackage) and PACKAGE in m.imports)


def private_reads(modules: dict[str, Module]) -> list[tuple[str, int, str]]:
    """(module, line, name): private names another module of the package defines,
    read here as ``obj._name`` (``obj`` not ``self``/``cls``) or imported by name."""
    owners: dict[str, set[str]] = {}
    for mod in modules.values():
        for name in mod.defined_private:
            owners.setdefault(name, set()).add(mod.name)
    out = []
    for mod in modules.values():
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") \
                    and not node.attr.startswith("__"):
                base = node.value
                if isinstance(base, ast.Name) and base.id in ("self", "cls"):
                    continue
                if isinstance(base, ast.Name) and base.id == "super":
                    continue
                if isinstance(base, ast.Call) and isinstance(base.func, ast.Name) \
                        and base.func.id == "super":
                    continue
                where = owners.get(node.attr, set())
                if where and mod.name not in where:
                    out.append((mod.name, node.lineno, node.attr))
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(mod, node)
                if target.split(".")[0] != PACKAGE:
                    continue
                for alias in node.names:
                    full = f"{target}.{alias.name}"
                    if not alias.name.startswith("_") or alias.name.startswith("__"):
                        continue
                    if full not in modules or not _inside(mod.name, target):
                        # a private name, or a private module imported from outside its package
                        out.append((mod.name, node.lineno, alias.name))
                if target in modules and not _inside(mod.name, target.rsplit(".", 1)[0]) \
                        and target.rsplit(".", 1)[-1].startswith("_") \
                        and not target.rsplit(".", 1)[-1].startswith("__"):
                    out.append((mod.name, node.lineno, target.rsplit(".", 1)[-1]))
    return sorted(out)


def _inside(module: str, package: str) -> bool:
    """Whether ``module`` lives in ``package`` (its private modules are its own business)."""
    return module == package or module.startswith(package + ".")


def report(root: Path = ROOT) -> dict:
    modules = load(root)
    rows = sizes(modules)
    over = [r for r in rows if r[2] > {"class": MAX_CLASS, "module": MAX_MODULE,
                                       "function": MAX_FUNCTION}[r[0]]]
    return {
        "largest": {kind: max((r for r in rows if r[0] == kind), key=lambda r: r[2])[1:]
                    for kind in ("module", "class", "function") if any(r[0] == kind for r in rows)},
        "over_limits": over,
        "cycles": cycles(modules),
        "storage_imports_root": root_imports(modules),
        "private_reads": private_reads(modules),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    rep = report()
    if args.json:
        print(json.dumps(rep, indent=1))
        return
    print("largest:", ", ".join(f"{k} {n} ({lines} lines)" for k, (n, lines)
                                 in rep["largest"].items()))
    print(f"over limits (class {MAX_CLASS}, module {MAX_MODULE}, function {MAX_FUNCTION}):"
          f" {len(rep['over_limits'])}")
    for kind, name, lines in sorted(rep["over_limits"], key=lambda r: -r[2]):
        print(f"  {kind:8} {lines:5}  {name}")
    print(f"import cycles: {len(rep['cycles'])}")
    for comp in rep["cycles"]:
        print("  " + " <-> ".join(c.removeprefix(PACKAGE + ".") for c in comp))
    print(f"storage modules importing the package root: {rep['storage_imports_root']}")
    print(f"private cross-module reads: {len(rep['private_reads'])}")
    for mod, line, name in rep["private_reads"]:
        print(f"  {mod.removeprefix(PACKAGE + '.')}:{line}  {name}")


if __name__ == "__main__":
    main()
