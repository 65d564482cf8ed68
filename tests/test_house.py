"""Sizes a reader can hold in mind: no package module over 520 lines, no function over 60.

Oracle: the modules' source, read with ``ast`` (a function's length runs from its ``def`` line to
its last line, docstring included, decorators not; nested functions count on their own too).  The
counters are checked on a hand-written snippet whose lengths are counted by eye.
"""

import ast
import textwrap
from pathlib import Path

import tsslam_ref

PACKAGE = Path(tsslam_ref.__file__).resolve().parent
MAX_MODULE_LINES = 520
MAX_FUNCTION_LINES = 60

# Functions allowed over the limit while they are being split (none today); an entry that is no
# longer long is reported by test_allowed_long_functions_are_still_long.
ALLOWED_LONG_FUNCTIONS: set = set()


def module_name(path: Path) -> str:
    """Dotted name below the package: tsslam_ref/datasets/images.py -> 'datasets.images'."""
    return ".".join(path.relative_to(PACKAGE).with_suffix("").parts)


def function_lengths(source: str):
    """{qualified name: lines from ``def`` to its last line} of every function in ``source``."""
    lengths = {}

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = prefix + child.name
                lengths[name] = child.end_lineno - child.lineno + 1
                visit(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return lengths


def package_sources():
    """{dotted module name: source} of every module file of the package."""
    return {module_name(path): path.read_text(encoding="utf-8") for path in sorted(PACKAGE.rglob("*.py"))}


def long_functions():
    """{"module.function": lines} of every function over :data:`MAX_FUNCTION_LINES`."""
    found = {}
    for module, source in package_sources().items():
        for name, lines in function_lengths(source).items():
            if lines > MAX_FUNCTION_LINES:
                found[f"{module}.{name}"] = lines
    return found


def test_counters_on_a_snippet_counted_by_eye():
    snippet = textwrap.dedent('''\
        import os


        @staticmethod
        def three():
            """Doc."""
            return 3


        class Box:
            def two(self):
                return 2

            async def outer(self):
                def inner():
                    return 1

                return inner()
        ''')
    assert function_lengths(snippet) == {"three": 3, "Box.two": 2, "Box.outer": 5, "Box.outer.inner": 2}
    assert len(snippet.splitlines()) == 18


def test_the_package_is_read_whole():
    """The scan sees nested packages and the modules split out of config and run (guards against an empty scan)."""
    names = set(package_sources())
    assert {"config", "presets", "config_io", "run", "run_outputs", "datasets.layouts"} <= names


def test_no_module_over_520_lines():
    long_modules = {name: len(source.splitlines()) for name, source in package_sources().items()
                    if len(source.splitlines()) > MAX_MODULE_LINES}
    assert not long_modules, f"modules over {MAX_MODULE_LINES} lines (split them by concept): {long_modules}"


def test_no_function_over_60_lines():
    offenders = {name: lines for name, lines in long_functions().items() if name not in ALLOWED_LONG_FUNCTIONS}
    assert not offenders, (f"functions over {MAX_FUNCTION_LINES} lines (split them into named steps): "
                           f"{offenders}")


def test_allowed_long_functions_are_still_long():
    """An allow-list entry that has been split meanwhile is stale: remove it from the list."""
    stale = sorted(ALLOWED_LONG_FUNCTIONS - set(long_functions()))
    assert not stale, f"remove from ALLOWED_LONG_FUNCTIONS, these are {MAX_FUNCTION_LINES} lines or less now: {stale}"


def test_no_code_calls_a_method_on_a_docstring():
    """``python -OO`` sets every ``__doc__`` to None: a command-line parser built from
    ``__doc__.split(...)`` failed before printing its --help (the eval command and the scripts)."""
    roots = [PACKAGE, PACKAGE.parent / "benchmarks", PACKAGE.parent / "data_scripts"]
    calls = []
    for path in sorted(p for root in roots if root.is_dir() for p in root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "__doc__":
                calls.append(f"{path.name}:{node.lineno}")
    assert calls == [], f"methods called on __doc__ (None under python -OO): {calls}"
