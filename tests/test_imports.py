"""The package's import graph, read from the source with ``ast``: every ``import`` and ``from ...
import`` of an mbavo_jax module (absolute or relative, at the top or inside a function) is an edge.
No module may import itself back through others (a circle), and none may import a module of a
higher layer than its own (:data:`LAYERS`)."""

from __future__ import annotations

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "mbavo_jax"

# The layers, lowest first, each a tuple of module or package names (relative to mbavo_jax; "__init__" is
# the package's own). A module sits in the layer of the longest name that is it or a package above it,
# and may import modules of its own layer (without a circle) or of a lower one, never of a higher one.
LAYERS = (
    ("errors", "progress", "names", "jaxenv", "lock"),  # error types, progress bar, safe folder names, JAX environment check, run-folder lock
    ("geometry",),  # quaternions, poses, the camera, exposure paths
    ("imu",),  # IMU data, noise figures and preintegration (on geometry's SO(3))
    ("image", "masked", "blur"),  # images and the blur model
    ("io",),  # file readers and writers (the camera files build a geometry.camera)
    ("config",),  # settings (a config file is read through io)
    ("runtime",),  # compilation cache, memory
    ("paper",),  # the paper's Jacobians, which tracking's residuals use
    ("evaluation",),  # association, alignment, ATE/RPE, run scores
    ("datasets",),  # sequence loaders (association of depth to images from evaluation)
    ("tracking",),
    ("deblur",),
    ("mono",),
    ("odometry",),
    ("synthetic",),
    ("peers", "methods"),  # one benchmark method's run over a sequence: ours, or a peer's
    ("sweep",),  # many runs at once; its workers call methods
    ("bench",),  # the benchmarks (the odometry benchmark is a sweep)
    ("viewer",),
    ("cli", "__init__"),
)


def module_files(package: pathlib.Path) -> dict[str, pathlib.Path]:
    """Dotted module name -> file, for every module of ``package`` (a package is its ``__init__.py``)."""
    out = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _known(name: str, modules) -> str:
    """``name``, or its longest prefix that is a module (``pkg.mod.function`` -> ``pkg.mod``)."""
    while name not in modules and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def _targets(node, module: str, is_package: bool, root: str, modules) -> list[str]:
    """The modules of ``root`` that one import statement in ``module`` imports."""
    if isinstance(node, ast.Import):
        return [_known(a.name, modules) for a in node.names if a.name.split(".")[0] == root]
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[: len(base) - node.level + 1]
        source = ".".join(base + (node.module.split(".") if node.module else []))
    else:
        source = node.module or ""
    if source.split(".")[0] != root:
        return []
    return [_known(f"{source}.{a.name}", modules) for a in node.names]


def import_graph(package: pathlib.Path = PACKAGE) -> dict[str, dict[str, int]]:
    """Module -> {imported module of the same package: line of its first import}."""
    modules = module_files(package)
    graph = {}
    for name, path in modules.items():
        edges = graph[name] = {}
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in _targets(node, name, path.name == "__init__.py", package.name, modules):
                    if target != name:
                        edges.setdefault(target, node.lineno)
    return graph


def circles(graph: dict[str, dict]) -> list[list[str]]:
    """One circle (``[a, b, ..., a]``) through each strongly connected group of modules (Tarjan)."""
    index, low, stack, on_stack, groups = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group, w = set(), None
            while w != v:
                w = stack.pop()
                on_stack.discard(w)
                group.add(w)
            if len(group) > 1:
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_circle_in(group, graph) for group in groups]


def _circle_in(group: set[str], graph: dict[str, dict]) -> list[str]:
    """A shortest path from the group's first module back to itself, inside the group."""
    start = min(group)
    paths, seen = [[start]], {start}
    while paths:
        path = paths.pop(0)
        for w in sorted(graph[path[-1]]):
            if w == start:
                return path + [start]
            if w in group and w not in seen:
                seen.add(w)
                paths.append(path + [w])
    raise AssertionError(f"no circle in {group}")


def layer_of(module: str, root: str = PACKAGE.name, layers=LAYERS) -> int | None:
    """The index in ``layers`` of the longest layer name that is ``module`` or a package above it."""
    rel = module[len(root) + 1:] if module != root else "__init__"
    best = None
    for i, names in enumerate(layers):
        for name in names:
            if (rel == name or rel.startswith(name + ".")) and (best is None or len(name) > len(best[1])):
                best = (i, name)
    return None if best is None else best[0]


def climbs(graph: dict[str, dict[str, int]], layers=LAYERS, root: str = PACKAGE.name) -> list[str]:
    """Each import from a lower layer to a higher one, as ``module:line imports target`` (modules
    outside every layer left to :func:`test_every_module_sits_in_a_layer`)."""
    level = {m: layer_of(m, root, layers) for m in graph}
    return [f"{m}:{line} imports {t} (layer {level[t]} above {level[m]})"
            for m, edges in sorted(graph.items()) for t, line in sorted(edges.items())
            if None not in (level[m], level[t]) and level[t] > level[m]]


def test_every_module_sits_in_a_layer():
    """A new module must be placed in LAYERS, or the other checks could not judge its imports."""
    outside = [m for m in import_graph() if layer_of(m) is None]
    assert not outside, f"modules in no layer of LAYERS: {', '.join(outside)}"


def test_the_package_has_no_import_circle():
    found = circles(import_graph())
    assert not found, "import circles:\n" + "\n".join(" -> ".join(c) for c in found)


def test_no_module_imports_from_a_higher_layer():
    found = climbs(import_graph())
    assert not found, "imports from a lower layer to a higher one:\n" + "\n".join(found)


def test_the_walk_sees_relative_absolute_and_function_level_imports(tmp_path):
    """On a made-up package: a circle through an import inside a function and an absolute one, an
    upward ``from .. import``, and ``from .sub import name`` read as the module ``sub`` imports."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {"__init__.py": "", "low.py": "def f():\n    from .high import g\n", "high.py": "import pkg.low\nimport numpy\n",
             "sub/__init__.py": "from .leaf import name\n", "sub/leaf.py": "from .. import high\nname = 1\n",
             "other.py": "from .sub import name\nfrom pkg.sub.leaf import name as n2\n"}
    for rel, text in files.items():
        (pkg / rel).write_text(text)
    graph = import_graph(pkg)
    assert graph == {"pkg": {}, "pkg.low": {"pkg.high": 2}, "pkg.high": {"pkg.low": 1}, "pkg.sub": {"pkg.sub.leaf": 1},
                     "pkg.sub.leaf": {"pkg.high": 1}, "pkg.other": {"pkg.sub": 1, "pkg.sub.leaf": 2}}
    assert circles(graph) == [["pkg.high", "pkg.low", "pkg.high"]]
    layers = (("low",), ("sub",), ("high", "other", "__init__"))
    assert climbs(graph, layers, "pkg") == ["pkg.low:2 imports pkg.high (layer 2 above 0)", "pkg.sub.leaf:1 imports pkg.high (layer 2 above 1)"]
