"""The package's import graph has no cycle, lazy (function-level) imports included: every
``import``/``from ... import`` of a ``clod_adapter`` module, at any depth of any module, is an
edge (a lazy import only hides a cycle, it does not remove it)."""
from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "clod_adapter"


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(mod: str, node: ast.ImportFrom, is_pkg: bool) -> list[str]:
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    if node.level:
        base = base[: len(base) - (node.level - 1)]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    out = [target]
    for alias in node.names:  # ``from . import lod`` names a module
        out.append(f"{target}.{alias.name}")
    return out


def import_graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in PKG.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in files}
    for mod, path in files.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                targets = _resolve(mod, node, is_pkg)
            for t in targets:
                # the deepest module of the package that the name refers to
                while t and t not in files:
                    t = t.rpartition(".")[0]
                if t and t != mod and t != "clod_adapter":
                    graph[mod].add(t)
    return graph


def find_cycle(graph: dict[str, set[str]]):
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state:
                c = visit(n)
                if c:
                    return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            c = visit(m)
            if c:
                return c
    return None


def test_no_import_cycle():
    graph = import_graph()
    assert "clod_adapter.lod.draw" in graph and graph["clod_adapter.lod.hook"] >= {"clod_adapter.lod.draw"}
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_cycle_finder_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def private_imports() -> list[str]:
    """``from M import _name`` of a ``clod_adapter`` module's private name, from another module."""
    files = {_module_name(p): p for p in PKG.rglob("*.py")}
    out = []
    for mod, path in files.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            target = _resolve(mod, node, is_pkg)[0]
            if not (target == "clod_adapter" or target.startswith("clod_adapter.")):
                continue
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__") and target != mod:
                    out.append(f"{mod}: from {target} import {alias.name}")
    return out


def test_no_private_name_imported_across_modules():
    """What another module needs is public (named without a leading underscore)."""
    assert private_imports() == []


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _self_attributes(tree: ast.AST) -> set[str]:
    """The attributes a module assigns on ``self`` / ``cls``."""
    return {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store)
            and isinstance(n.value, ast.Name) and n.value.id in ("self", "cls")}


def attribute_names(tree: ast.AST) -> set[str]:
    """The names a module gives its module, classes and objects: functions, classes and names
    assigned outside any function (module globals, class attributes and fields), and what it
    assigns on ``self`` / ``cls`` (a function's locals and an import's alias are nobody's
    attribute)."""
    out = _self_attributes(tree)

    def visit(node):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                out.add(child.name)
            elif isinstance(child, ast.Name) and isinstance(child.ctx, ast.Store):
                out.add(child.id)
            if not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child)

    visit(tree)
    return out


def own_names(tree: ast.AST) -> set[str]:
    """Every name a module defines: :func:`attribute_names`, locals, parameters, import aliases."""
    out = attribute_names(tree)
    for n in ast.walk(tree):
        if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
            out.add(n.id)
        elif isinstance(n, ast.arg):
            out.add(n.arg)
        elif isinstance(n, ast.alias):
            out.add(n.asname or n.name.split(".")[0])
    return out


def private_attributes() -> list[str]:
    """``X._name`` in a ``clod_adapter`` module where ``_name`` is a private attribute another
    module of the package defines (:func:`attribute_names`) and this one does not
    (:func:`own_names`): a private read (or written) across modules. Private names of other
    libraries (``argparse._HelpAction``, ``Tensor._version``, a namedtuple's ``_replace``) are not
    the package's to rename, so only the package's own private attributes count."""
    trees = {_module_name(p): ast.parse(p.read_text(), str(p)) for p in PKG.rglob("*.py")}
    package_private = {name for t in trees.values() for name in attribute_names(t) if _is_private(name)}
    out = []
    for mod, tree in trees.items():
        own = own_names(tree)
        for n in ast.walk(tree):
            if isinstance(n, ast.Attribute) and _is_private(n.attr) and n.attr in package_private \
                    and n.attr not in own:
                out.append(f"{mod}:{n.lineno}: {ast.unparse(n)}")
    return sorted(set(out))


def test_no_private_attribute_used_across_modules():
    """An object's or module's private attribute is read (or written) only by the module that
    defines it: what another module needs is public."""
    assert private_attributes() == []


def test_private_attribute_check_finds_one():
    a = ast.parse("import os as _os\nclass A:\n    _n = 0\n    def __init__(self):\n        self._x = 1\n"
                  "    def _f(self):\n        _local = 2\n")
    assert attribute_names(a) == {"A", "_n", "_x", "_f", "__init__"}
    b = ast.parse("def f(a):\n    a._x = 2\n    return a._x, a.__class__\n")
    assert "_x" not in own_names(b) and "_x" in own_names(a) and {"_os", "_local", "self"} <= own_names(a)


#: the longest a function body may be (lines, its docstring not counted; issue 20).
MAX_BODY_LINES = 80
#: the functions allowed over the limit, each with the length it may not grow past: the CPU
#: rasteriser mirrors gsplat.rasterization's signature and steps.
OVER_LIMIT = {
    "clod_adapter.render.cpu:rasterization_cpu": 84,  # gsplat.rasterization's signature and steps
}


def functions():
    """Every function of the package: ``(module:function, its ast node)``."""
    for path in PKG.rglob("*.py"):
        mod = _module_name(path)
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield f"{mod}:{node.name}", node


def body_lengths() -> dict[str, int]:
    """``module:function`` -> lines from its first statement after the docstring to its last."""
    out = {}
    for key, node in functions():
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
                and isinstance(body[0].value.value, str):
            body = body[1:]
        if body:
            out[key] = max(out.get(key, 0), body[-1].end_lineno - body[0].lineno + 1)
    return out


def over_limit(values: dict[str, int], limit: int, allowed: dict[str, int]) -> tuple[dict, list]:
    """``(the values over limit that the allow-list does not cover, the allow-list's entries now
    within the limit)``: both must be empty."""
    over = {k: n for k, n in values.items() if n > limit and n > allowed.get(k, 0)}
    return over, [k for k in allowed if values.get(k, 0) <= limit]


def test_no_function_over_the_length_limit():
    over, stale = over_limit(body_lengths(), MAX_BODY_LINES, OVER_LIMIT)
    assert over == {}, f"functions over {MAX_BODY_LINES} lines (split them into named steps): {over}"
    assert stale == [], f"now within the limit, drop from OVER_LIMIT: {stale}"


#: the longest a whole function may be, its signature and docstring counted (issue 63's goal)
MAX_FUNCTION_LINES = 100
#: allowed over it: the gsplat-mirroring signatures (gsplat.rasterization's parameters and their
#: documentation), each with the length it may not grow past
OVER_FUNCTION_LINES = {
    "clod_adapter.render.cpu:rasterization_cpu": 120, "clod_adapter.lod.hook:clod_rasterization": 146,
}


def function_lengths() -> dict[str, int]:
    """``module:function`` -> lines from its ``def`` (or first decorator) to its last line."""
    out = {}
    for key, node in functions():
        first = min([node.lineno] + [d.lineno for d in node.decorator_list])
        out[key] = max(out.get(key, 0), node.end_lineno - first + 1)
    return out


def test_no_whole_function_over_100_lines():
    over, stale = over_limit(function_lengths(), MAX_FUNCTION_LINES, OVER_FUNCTION_LINES)
    assert over == {}, f"functions over {MAX_FUNCTION_LINES} lines with their docstrings: {over}"
    assert stale == [], f"now within the limit, drop from OVER_FUNCTION_LINES: {stale}"


def test_no_root_export_shadowed_by_a_submodule():
    """A lazily exported name equal to a submodule's would turn into the module once that module
    is imported (``from clod_adapter import adapt`` giving the module, not the function)."""
    import clod_adapter

    submodules = {p.stem for p in PKG.glob("*.py")} | {p.name for p in PKG.iterdir() if (p / "__init__.py").is_file()}
    assert sorted(set(clod_adapter._EXPORTS) & submodules) == []


#: the package's folders from the bottom layer up (docs/guide.md "How the code is laid out"): a module's
#: layer is its folder's (the package root's modules, ``""``, are the model, its settings, the
#: image metrics and progress, which everything uses); no module imports one of a higher layer.
LAYERS = ["", "render", "io", "lod", "train", "evaluate", "export", "viewer", "jobs", "cli"]


def layer(module: str) -> int:
    """The index in :data:`LAYERS` of the module's folder (``clod_adapter.lod.tree`` -> ``lod``)."""
    parts = module.split(".")
    folder = parts[1] if len(parts) > 2 or (len(parts) == 2 and (PKG / parts[1]).is_dir()) else ""
    return LAYERS.index(folder)


def test_every_folder_has_a_layer():
    folders = sorted(p.name for p in PKG.iterdir() if (p / "__init__.py").is_file())
    assert sorted(set(LAYERS) - {""}) == folders


def test_layers_import_downwards_only():
    up = sorted(f"{a} -> {b}" for a, bs in import_graph().items() for b in bs if layer(b) > layer(a))
    assert up == []


#: at most this many modules at the top of the package (issue 63): the rest live in stage folders
MAX_TOP_MODULES = 10


def test_the_top_of_the_package_stays_small():
    top = sorted(p.name for p in PKG.glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, top


#: the longest a module may be, in lines (issue 63)
MAX_MODULE_LINES = 800


def test_no_module_over_the_length_limit():
    long = {str(p.relative_to(PKG)): n for p in PKG.rglob("*.py") if (n := len(p.read_text().splitlines())) >
            MAX_MODULE_LINES}
    assert long == {}, f"modules over {MAX_MODULE_LINES} lines (split them by what they hold): {long}"


#: the most parameters a function may take (issue 63), ``self`` not counted
MAX_PARAMETERS = 12
#: the functions allowed more: gsplat's ``rasterization`` signature and the functions mirroring it
#: (the renderer hook adds the level of detail's keywords to it), each with the count it may not
#: grow past
OVER_PARAMETERS = {
    "clod_adapter.render.dispatch:rasterization": 17, "clod_adapter.render.cpu:rasterization_cpu": 16,
    "clod_adapter.render.gsplat_backend:rasterization_gsplat": 16, "clod_adapter.lod.hook:clod_rasterization": 34,
}


def parameter_counts() -> dict[str, int]:
    """``module:function`` -> its parameters (``self`` / ``cls`` not counted)."""
    out = {}
    for key, node in functions():
        a = node.args
        n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + bool(a.vararg) + bool(a.kwarg)
        out[key] = max(out.get(key, 0), n - (bool(a.args) and a.args[0].arg in ("self", "cls")))
    return out


def test_no_function_takes_too_many_parameters():
    over, stale = over_limit(parameter_counts(), MAX_PARAMETERS, OVER_PARAMETERS)
    assert over == {}, f"functions over {MAX_PARAMETERS} parameters (group them in an options object): {over}"
    assert stale == [], f"now within the limit, drop from OVER_PARAMETERS: {stale}"
