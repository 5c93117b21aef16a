"""The package's shape: one-way layers, no cycles, one installed namespace, a public API.

Layers (lowest first): foundations (``knee.foundations``) <- models (``knee.models``) <- fitting
(``knee.fitting``) <- application (``knee.app`` and the namespace root ``knee``). A module may import
its own layer or a lower one, never a higher one, and the modules' import graph has no cycle. Imports
inside functions are kept for third-party modules whose cost or absence is worth deferring, each with a
comment saying why; never for the toolkit's own modules.
"""

from __future__ import annotations

import ast
import importlib
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
FOLDERS = {"toolkit": "knee", "models": "knee.models", "fitting": "knee.fitting"}
LAYERS = ("foundations", "models", "fitting", "application")


def module_files() -> dict[str, pathlib.Path]:
    """Every module of the package, by its installed name."""
    out = {}
    for folder, prefix in FOLDERS.items():
        for p in sorted((ROOT / folder).rglob("*.py")):
            parts = p.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join((prefix, *parts))] = p
    return out


MODULES = module_files()


def layer(name: str) -> int:
    if name.startswith("knee.foundations"):
        return 0
    if name.startswith("knee.models"):
        return 1
    if name.startswith("knee.fitting"):
        return 2
    if name == "knee" or name.startswith("knee.app"):
        return 3
    raise AssertionError(f"module {name} belongs to no layer")


def _target(name: str, node: ast.AST, is_package: bool) -> list[str]:
    """The toolkit modules an import statement loads (the deepest existing module of each name)."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        if node.level:
            base = name.split(".") if is_package else name.split(".")[:-1]
            base = base[: len(base) - node.level + 1]
            mod = ".".join(base + ([node.module] if node.module else []))
        else:
            mod = node.module
        names = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod for a in node.names]
    out = []
    for n in names:
        while n and n not in MODULES and "." in n:
            n = n.rsplit(".", 1)[0]
        if n in MODULES:
            out.append(n)
    return out


def imports(name: str):
    """(module-level targets, [(line, modules, of the toolkit, has a comment)] of imports inside functions)."""
    path = MODULES[name]
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    tree = ast.parse(text)
    nested = []
    top = set()

    def walk(node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                ours = _target(name, child, path.name == "__init__.py")
                if not in_function:
                    top.update(ours)
                else:
                    mods = [a.name for a in child.names] if isinstance(child, ast.Import) else [child.module or "."]
                    comment = "#" in lines[child.lineno - 1] or lines[child.lineno - 2].strip().startswith("#")
                    nested.append((child.lineno, ours or mods, bool(ours), comment))
            walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(tree, False)
    return top, nested


GRAPH = {n: imports(n) for n in MODULES}


def test_every_module_is_in_a_layer_and_the_tree_shows_them():
    for n in MODULES:
        layer(n)
    # the application layer is in one place
    app = [n for n in MODULES if layer(n) == 3]
    assert all(n == "knee" or n.startswith("knee.app") for n in app)


def test_no_import_runs_back_up():
    bad = [f"{src} ({LAYERS[layer(src)]}) imports {dst} ({LAYERS[layer(dst)]})"
           for src, (top, nested) in GRAPH.items()
           for dst in top | {m for _, ms, ours, _ in nested if ours for m in ms}
           if layer(dst) > layer(src)]
    assert not bad, "\n".join(bad)


def test_no_import_cycle():
    edges = {src: sorted(d for d in top if d != src) for src, (top, _) in GRAPH.items()}
    state, stack, cycles = {}, [], []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for d in edges.get(n, ()):
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d):] + [d]))
            elif d not in state:
                visit(d)
        stack.pop()
        state[n] = 2

    for n in sorted(edges):
        if n not in state:
            visit(n)
    assert not cycles, "\n".join(cycles)


def test_imports_inside_functions_are_third_party_and_explained():
    bad = []
    for src, (_, nested) in GRAPH.items():
        for line, mods, ours, comment in nested:
            if ours:
                bad.append(f"{MODULES[src].relative_to(ROOT)}:{line} imports the toolkit's {mods} inside a function")
            elif not comment:
                bad.append(f"{MODULES[src].relative_to(ROOT)}:{line} imports {mods} inside a function without a "
                           f"comment saying why")
    assert not bad, "\n".join(bad)


def test_the_namespace_root_loads_nothing_eagerly():
    top, nested = GRAPH["knee"]
    assert not top and not nested


def test_installed_distribution_has_one_top_level_name():
    # run outside the source tree, so that only the installation is seen
    code = ("import importlib.metadata as m, importlib.util, sys; "
            "sys.path = [p for p in sys.path if p not in ('', '.', %r)]; "
            "print((m.distribution('knee-toolkit').read_text('top_level.txt') or '').split()); "
            "print([n for n in ('toolkit', 'models', 'fitting') if importlib.util.find_spec(n)]); "
            "print(importlib.util.find_spec('knee') is not None)" % str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/", timeout=60)
    assert out.stdout.split("\n")[:3] == ["['knee']", "[]", "True"], out.stdout + out.stderr


def test_public_api_is_listed_and_documented():
    import knee

    assert knee.__all__ and len(set(knee.__all__)) == len(knee.__all__)
    missing_doc = []
    for name in knee.__all__:
        obj = getattr(knee, name)
        if callable(obj) and not (obj.__doc__ or "").strip():
            missing_doc.append(name)
    assert not missing_doc, missing_doc
    assert set(knee.__all__) <= set(dir(knee))


def test_help_lists_the_api():
    out = subprocess.run([sys.executable, "-c", "import knee, pydoc; print(pydoc.render_doc(knee, renderer=pydoc.plaintext))"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    import knee

    for name in knee.__all__:
        assert name in out.stdout, name


@pytest.mark.parametrize("name", sorted(n for n in MODULES if n != "knee"))
def test_every_module_imports(name):
    importlib.import_module(name)
