"""The layer table of tsslam_ref/__init__.py is true: every import of every module points to its own
layer or a lower one, every module file has a layer, and no two modules import each other, even
through other modules or inside functions.

Oracle: the modules' source, read with ``ast`` (nothing is imported, so lazy imports inside
functions count as imports too).
"""

import ast
from pathlib import Path

import pytest

import tsslam_ref

PACKAGE = Path(tsslam_ref.__file__).resolve().parent
LAYERS = tsslam_ref.LAYERS


def module_name(path: Path) -> str:
    """Dotted name below the package: tsslam_ref/datasets/images.py -> 'datasets.images'."""
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def module_file(name: str) -> Path:
    """File of a dotted module name (a package's __init__.py for a package)."""
    base = PACKAGE.joinpath(*name.split("."))
    return base / "__init__.py" if base.is_dir() else base.with_suffix(".py")


def all_modules():
    """Every module of the package except the package itself, by dotted name."""
    return sorted(module_name(p) for p in PACKAGE.rglob("*.py") if p != PACKAGE / "__init__.py")


def _resolve(target: str):
    """A dotted name below the package -> the module it names (a name inside a module -> that
    module), or None for the package itself."""
    while target and not module_file(target).exists():
        target = target.rpartition(".")[0]
    return target or None


def imports_of(name: str):
    """Package modules that module ``name`` imports anywhere in its source, as dotted names."""
    path = module_file(name)
    package_parts = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package_parts[: len(package_parts) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
                prefix = "tsslam_ref." + module if module else "tsslam_ref"
            else:
                prefix = node.module or ""
            candidates = [prefix] + [f"{prefix}.{alias.name}" for alias in node.names]
        else:
            continue
        for candidate in candidates:
            if candidate == "tsslam_ref" or not candidate.startswith("tsslam_ref."):
                continue
            target = _resolve(candidate[len("tsslam_ref."):])
            if target is not None and target != name:
                found.add(target)
    return found


def import_graph(ignore=()):
    """{module: set of modules it imports}, without the (importer, imported) pairs in ``ignore``."""
    return {name: {t for t in imports_of(name) if (name, t) not in ignore} for name in all_modules()}


def cycles(graph):
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_every_module_file_has_a_layer():
    missing = [name for name in all_modules() if name not in LAYERS]
    assert not missing, f"modules without an entry in tsslam_ref.LAYERS: {missing}"


def test_the_import_reader_sees_relative_absolute_and_lazy_imports():
    """Oracle: imports written in this package's own files, read by eye."""
    assert {"config", "geometry", "losses", "render"} <= imports_of("mapping")  # from .x import y
    assert "datasets.intrinsics" in imports_of("synthetic")  # from tsslam_ref.datasets.intrinsics import y
    assert "synthetic" in imports_of("data")  # inside a function
    assert "conformance" in imports_of("spline_kit")  # from tsslam_ref import conformance


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_imports_point_to_the_same_or_a_lower_layer(name):
    if not module_file(name).exists():
        pytest.skip(f"{name} has a layer but no file in this checkout")
    upward = sorted(f"{target} (layer {LAYERS.get(target, 'missing')})" for target in imports_of(name)
                    if LAYERS.get(target, float("inf")) > LAYERS[name])
    assert not upward, f"{name} (layer {LAYERS[name]}) imports {upward}"


def test_no_import_cycle():
    assert cycles(import_graph()) == []


def test_cycle_finder_finds_a_planted_cycle():
    """Oracle: a hand-made graph a -> b -> c -> a plus a tail d -> a."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
