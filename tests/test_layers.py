"""The import graph of the installed package runs one way and has no cycle.

Layers, lowest first: the core (every `slamreloc.*` module outside the others), the SLAM backend
(`slamreloc.slam`), the wings (`slamreloc.plugins`, `slamreloc.pseudo_label`,
`slamreloc.viewer`), the applications (the command line `slamreloc.cli` and the service
`slamreloc.service`, which compose the wings). A module imports only from its own
layer or lower ones, and a wing imports no other wing (the viewer reads what the updater writes
through the core's readers). Every import counts, the function-local ones included, and so
does a string that names a module (`"slamreloc.x.y"`, `"slamreloc.x.y:Name"`: what
`import_module` or an entry point would load). Plugins are reached only through the entry-point
group `slamreloc.plugins`: no module outside them imports or names one. The modules
are found by walking the source folders that pyproject.toml's package-dir maps into the
`slamreloc` namespace, so files that move are checked where they land.

Below the command line (every module outside `slamreloc.cli`) no message names a flag: the
library names a setting `field` in backticks, and the CLI's error line shows its flag.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib", reason="reads pyproject.toml with Python 3.11's tomllib")

ROOT = Path(__file__).resolve().parents[1]
CORE, SLAM, WING, CLI = 0, 1, 2, 3
LAYER_NAMES = {CORE: "core", SLAM: "slam", WING: "wing", CLI: "application"}
APPLICATIONS = ("slamreloc.cli", "slamreloc.service")
WINGS = ("slamreloc.plugins", "slamreloc.pseudo_label", "slamreloc.viewer")
PLUGINS = "slamreloc.plugins"  # reached only through the entry-point group of that name
MODULE_STRING = re.compile(r"slamreloc(\.[A-Za-z_]\w*)+(:[A-Za-z_]\w*)?")


@dataclass(frozen=True)
class Import:
    source: str  # importing module
    target: str  # imported module (the deepest one of the package that exists)
    where: str  # file:line


def package_dirs() -> dict[str, Path]:
    """Top-level source folder of every package pyproject.toml maps (`slamreloc.viewer` ->
    viewer/)."""
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return {name: ROOT / folder for name, folder in setup["package-dir"].items()}


def discover_modules() -> dict[str, Path]:
    """Dotted name -> file of every module in the package (`__init__.py` is its package)."""
    dirs = package_dirs()
    modules: dict[str, Path] = {}
    for name, folder in dirs.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder).with_suffix("").parts
            dotted = ".".join((name, *rel))
            if dotted.endswith(".__init__"):
                dotted = dotted[: -len(".__init__")]
            # a subfolder that another package-dir entry owns is that package's, not this one's
            owner = max((n for n, d in dirs.items() if path.is_relative_to(d)),
                        key=lambda n: len(dirs[n].parts))
            if owner == name:
                modules[dotted] = path
    return modules


def resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The deepest module of `name` that exists in the package (None outside it)."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        candidate = ".".join(parts[:n])
        if candidate in modules:
            return candidate
    return None


def imports_of(module: str, path: Path, modules: dict[str, Path],
               root: Path = ROOT) -> list[Import]:
    """Every import statement of the module (any depth in the file), resolved to modules of
    the package; `from pkg import name` counts as `pkg.name` when that is a module."""
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and MODULE_STRING.fullmatch(node.value) and node.value != PLUGINS:
            names = [node.value.partition(":")[0]]  # import_module("slamreloc.x"), "m:Attr"
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".")
                anchor = anchor[: len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, *([base] if base else [])])
            names = [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        where = f"{path.relative_to(root)}:{node.lineno}"
        for name in names:
            target = resolve(name, modules)
            if target is not None and target != module:
                out.append(Import(module, target, where))
    return out


def layer(module: str) -> int:
    if any(module == a or module.startswith(a + ".") for a in APPLICATIONS):
        return CLI
    if any(module == w or module.startswith(w + ".") for w in WINGS):
        return WING
    if module == "slamreloc.slam" or module.startswith("slamreloc.slam."):
        return SLAM
    return CORE


def wing(module: str) -> str | None:
    return next((w for w in WINGS if module == w or module.startswith(w + ".")), None)


def layer_violations(imports: list[Import]) -> list[str]:
    bad = []
    for imp in imports:
        src, dst = layer(imp.source), layer(imp.target)
        if dst > src:
            bad.append(f"{imp.where}: {imp.source} ({LAYER_NAMES[src]}) imports {imp.target} "
                       f"({LAYER_NAMES[dst]})")
        elif src == dst == WING and wing(imp.source) != wing(imp.target):
            bad.append(f"{imp.where}: wing {imp.source} imports another wing's {imp.target}")
        elif wing(imp.target) == PLUGINS and wing(imp.source) != PLUGINS:
            bad.append(f"{imp.where}: {imp.source} names the plugin {imp.target} (plugins are "
                       f"loaded through the entry-point group {PLUGINS})")
    return bad


def cycles(imports: list[Import]) -> list[list[Import]]:
    """One cycle of imports (as its edges) per strongly connected component (Tarjan)."""
    graph: dict[str, list[Import]] = {}
    for imp in imports:
        graph.setdefault(imp.source, []).append(imp)
        graph.setdefault(imp.target, [])
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for imp in graph[v]:
            w = imp.target
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(component)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [cycle_in(component, graph) for component in components]


def cycle_in(component: set[str], graph: dict[str, list[Import]]) -> list[Import]:
    """A closed path of imports through a strongly connected component (breadth-first from its
    first module back to itself)."""
    start = min(component)
    came: dict[str, Import] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for imp in graph[v]:
                if imp.target not in component or imp.target in came:
                    continue
                came[imp.target] = imp
                if imp.target == start:
                    path, node = [], start
                    while True:
                        path.append(came[node])
                        node = came[node].source
                        if node == start:
                            return path[::-1]
                nxt.append(imp.target)
        frontier = nxt
    raise AssertionError(f"{sorted(component)} is not strongly connected")


def all_imports() -> list[Import]:
    modules = discover_modules()
    return sorted({imp for module, path in modules.items()
                   for imp in imports_of(module, path, modules)}, key=lambda i: i.where)


def test_the_walk_sees_every_layer():
    """The walk finds modules of every layer and the imports between them (the rules below are
    not checked on an empty graph)."""
    imports = all_imports()
    seen = {layer(m) for imp in imports for m in (imp.source, imp.target)}
    assert seen == {CORE, SLAM, WING, CLI}
    assert any(layer(i.source) == WING and layer(i.target) == SLAM for i in imports)


def test_imports_run_one_way():
    bad = layer_violations(all_imports())
    assert not bad, "imports against the layers (core <- slam <- wings <- cli):\n" + "\n".join(bad)


def test_no_import_cycle():
    found = cycles(all_imports())
    assert not found, "import cycles:\n" + "\n".join(
        " -> ".join([c[0].source, *(f"{i.target} ({i.where})" for i in c)]) for c in found)


def imports_in(sources: dict[str, str], tmp_path: Path) -> list[Import]:
    """The imports of modules written from `sources` (dotted name -> text) under tmp_path."""
    modules = {name: tmp_path / f"{name}.py" for name in sources}
    for name, text in sources.items():
        modules[name].write_text(text)
    return [imp for m, p in modules.items() for imp in imports_of(m, p, modules, root=tmp_path)]


def test_a_bad_import_is_reported_with_its_line(tmp_path):
    """The checks name the file and line of each import against the layers (a function-local
    one, a relative one, one wing into another, a wing into the CLI) and of a cycle."""
    sources = {"slamreloc.a": "import os\n\ndef f():\n    from slamreloc.slam import b\n",
               "slamreloc.slam.b": "from slamreloc.a import f\n",
               "slamreloc.viewer.c": "from ..pseudo_label import d\nimport slamreloc.cli\n",
               "slamreloc.pseudo_label.d": "from slamreloc.slam.b import x\n",
               "slamreloc.cli": ""}
    imports = imports_in(sources, tmp_path)
    assert layer_violations(imports) == [
        "slamreloc.a.py:4: slamreloc.a (core) imports slamreloc.slam.b (slam)",
        "slamreloc.viewer.c.py:1: wing slamreloc.viewer.c imports another wing's "
        "slamreloc.pseudo_label.d",
        "slamreloc.viewer.c.py:2: slamreloc.viewer.c (wing) imports slamreloc.cli "
        "(application)"]
    (cycle,) = cycles(imports)

    assert [(i.source, i.target, i.where) for i in cycle] == [
        ("slamreloc.a", "slamreloc.slam.b", "slamreloc.a.py:4"),
        ("slamreloc.slam.b", "slamreloc.a", "slamreloc.slam.b.py:1")]



def test_a_plugin_named_outside_plugins_is_reported(tmp_path):
    """A plugin named by module string (an upward import the graph would not see), or imported
    directly by the backend or the service."""
    sources = {"slamreloc.slam.e": 'BUILTIN = {"r": "slamreloc.plugins.p:Plugin"}\n',
               "slamreloc.service.s": "from slamreloc.plugins.p import Config\n",
               "slamreloc.plugins.p": "", "slamreloc.service": "",
               "slamreloc.slam": "", "slamreloc.plugins": ""}
    imports = imports_in(sources, tmp_path)
    assert layer_violations(imports) == [
        "slamreloc.slam.e.py:1: slamreloc.slam.e (slam) imports slamreloc.plugins.p (wing)",
        "slamreloc.service.s.py:1: slamreloc.service.s names the plugin slamreloc.plugins.p "
        "(plugins are loaded through the entry-point group slamreloc.plugins)"]


def test_the_command_line_loads_its_pipeline_only_when_a_command_runs():
    """Importing the CLI (what `slamreloc --help` and typer's argument checks need) imports none
    of the heavy libraries: each command imports its pipeline when it runs. The choices come
    from `slamreloc.registry`, plain data."""
    import subprocess
    import sys

    heavy = ("torch", "pycolmap", "gtsam", "open3d", "scipy", "kiss_icp", "viser", "grpc")
    code = ("import sys; import slamreloc.cli; "
            f"print(' '.join(m for m in {heavy!r} if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert res.stdout.split() == [], res.stdout
    # and a command still finds the names it acts on
    from slamreloc.cli.choices import Arch, Method, Precision, Update
    from slamreloc.regressor.model import RegressorConfig

    assert [a.value for a in Arch] == ["paper", "tiny", "wide"]
    assert RegressorConfig.preset("wide", 128).n_clusters == 1024
    assert {m.value for m in Method} == {"regressor", "matching"}
    assert {p.value for p in Precision} == {"auto", "fp32", "bf16"}
    assert {u.value for u in Update} == {"finetune", "retrain"}


# ---- no flag named below the command line ----------------------------------------------------
# A module below the CLI names a setting by its field in backticks (`port`, `scale_from_depth`);
# the CLI's error printer (`slamreloc.cli.with_flags`) shows it as its flag. A flag written out
# there (`--port`) would read wrong from Python and drift from the CLI's own options.
FLAG = re.compile(r"(?<![\w`-])--[a-z][a-z0-9-]*")
BUILT_FLAG = re.compile(r"(?<![\w`-])--$")  # f"--{name}": a flag made from a field's name
# Text that names a flag and is no message of the library, keyed by (file, flag): why.
FLAG_EXEMPT = {
    ("viewer/scene.py", "--trajectory"): "the viewer's web page tells its user which file of "
                                         "`slamreloc evaluate` to pass; no error or log line",
}


def docstrings(tree: ast.AST) -> set[int]:
    """ids of the docstring constants of the module, its classes and its functions."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) \
                and node.body and isinstance(node.body[0], ast.Expr) \
                and isinstance(node.body[0].value, ast.Constant) \
                and isinstance(node.body[0].value.value, str):
            out.add(id(node.body[0].value))
    return out


def flags_named(path: Path, root: Path = ROOT) -> list[str]:
    """`file:line: --flag` for each flag in a string constant or f-string part of the file,
    docstrings aside; a part ending in `--` before a formatted value counts as a flag built
    from a name."""
    tree = ast.parse(path.read_text(), str(path))
    skip = docstrings(tree)
    where = path.relative_to(root).as_posix()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):  # its parts, at its first line (as Python < 3.12)
            parts = [*node.values, None]
            skip.update(id(part) for part in node.values)
            for part, nxt in zip(parts, parts[1:]):
                if not isinstance(part, ast.Constant):
                    continue
                found += [(node.lineno, m[0]) for m in FLAG.finditer(part.value)]
                if isinstance(nxt, ast.FormattedValue) and BUILT_FLAG.search(part.value):
                    found.append((node.lineno, f"--{{{ast.unparse(nxt.value)}}}"))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and id(node) not in skip:
            found += [(node.lineno, m[0]) for m in FLAG.finditer(node.value)]
    return [f"{where}:{line}: {flag}" for line, flag in sorted(set(found))
            if (where, flag) not in FLAG_EXEMPT]


def below_the_cli() -> list[Path]:
    """The files of every module outside `slamreloc.cli` (core, backend, wings, service)."""
    return [path for module, path in sorted(discover_modules().items())
            if module != "slamreloc.cli" and not module.startswith("slamreloc.cli.")]


def test_no_flag_is_named_below_the_command_line():
    """Messages below the CLI name a setting `field` (backticks), never its `--flag`."""
    files = below_the_cli()
    assert any(p.parts[-2:] == ("service", "server.py") for p in files)  # the walk sees them
    assert any(p.parts[-2:] == ("viewer", "server.py") for p in files)
    assert not any("cli" in p.relative_to(ROOT).parts[:2] for p in files)
    bad = [line for path in files for line in flags_named(path)]
    assert not bad, ("a flag named below the command line (name the setting `field` instead; "
                     "the CLI shows it as its flag):\n" + "\n".join(bad))


def test_a_flag_named_below_the_cli_is_reported_with_its_line(tmp_path):
    """A flag in a message, in an f-string part, built from a name, or in a help line is
    reported; docstrings and a setting named `field` are not."""
    path = tmp_path / "m.py"
    path.write_text('"""Run `slamreloc serve --port 0`."""\n'
                    "def f(port, name):\n"
                    '    """--port: the port."""\n'
                    '    if port < 0:\n'
                    '        raise ValueError(f"--port {port}: not a TCP port")\n'
                    '    if port > 65535:\n'
                    '        raise ValueError(f"`port` {port}: not a TCP port")\n'
                    '    advice = ["a higher --max-points", "x--y", "a -- b"]\n'
                    '    raise ValueError(f"--{name} must be positive; or give "\n'
                    '                     f"{name} --scale-from-depth")\n')
    assert flags_named(path, tmp_path) == ["m.py:5: --port", "m.py:8: --max-points",
                                           "m.py:9: --scale-from-depth", "m.py:9: --{name}"]
