"""The import graph keeps the shape that docs/architecture.md draws: no circle, no import of a module in a
later layer, and pipeline stages that do not import each other.

The layers are read from the table of ``docs/architecture.md``, so the page and the code cannot
drift apart: a new module must be placed in the table, and an import that breaks the shape fails
here with the file and the names involved.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("unimal_envs", "sb3_divmorph", "divmorph")
ARCHITECTURE = ROOT / "docs" / "architecture.md"
STAGE_LAYER = "stages"


def package_modules() -> dict[str, Path]:
    """``{dotted module name: file}`` for every module of the three packages (a package is its ``__init__``)."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


def _known(name: str, modules: dict[str, Path]) -> str | None:
    """The longest prefix of ``name`` that is one of our modules (``None``: a third-party import)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> dict[str, int]:
    """``{imported module of ours: first line}``, from every import statement anywhere in the file."""
    found: dict[str, int] = {}
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against this module's package
                package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            # ``from package import module`` imports the module; ``from module import name`` the module
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        for target in targets:
            module = _known(target, modules)
            if module is not None and module != name:
                found.setdefault(module, node.lineno)
    return found


def read_layers() -> list[tuple[str, list[str]]]:
    """``[(layer name, module patterns)]`` from the table of docs/architecture.md, lowest first."""
    layers = []
    for line in ARCHITECTURE.read_text().splitlines():
        match = re.match(r"^\|\s*(\d+)\s+([^|]+?)\s*\|(.*)\|\s*$", line)
        if match:
            layers.append((match.group(2), re.findall(r"`([\w.*]+)`", match.group(3))))
    return layers


def layer_of(module: str, layers: list[tuple[str, list[str]]]) -> int | None:
    """Index of the layer naming ``module`` exactly, else the one whose ``prefix.*`` pattern fits best."""
    for index, (_, patterns) in enumerate(layers):
        if module in patterns:
            return index
    best: tuple[int, int] | None = None
    for index, (_, patterns) in enumerate(layers):
        for pattern in patterns:
            if pattern.endswith(".*") and module.startswith(pattern[:-1]):
                if best is None or len(pattern) > best[0]:
                    best = (len(pattern), index)
    return None if best is None else best[1]


@pytest.fixture(scope="module")
def graph() -> dict[str, dict[str, int]]:
    modules = package_modules()
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


@pytest.fixture(scope="module")
def layers() -> list[tuple[str, list[str]]]:
    found = read_layers()
    assert len(found) >= 5, f"the layer table of {ARCHITECTURE} was not found (rows like '| 1 environments | `unimal_envs.*` |')"
    return found


def test_every_module_has_a_layer_and_pipeline_modules_are_named(graph, layers):
    named = {pattern for _, patterns in layers for pattern in patterns}
    unplaced = [m for m in graph if layer_of(m, layers) is None]
    # a pipeline module must be named: the wildcard of layer 2 would otherwise hide where it stands
    unnamed = [m for m in graph if m.startswith("divmorph.pipeline") and m not in named]
    stale = [p for p in named if not p.endswith(".*") and p not in graph]
    assert not unplaced, f"modules in no layer of {ARCHITECTURE.name}: {unplaced}"
    assert not unnamed, f"pipeline modules not named in the layer table of {ARCHITECTURE.name}: {unnamed}"
    assert not stale, f"the layer table of {ARCHITECTURE.name} names modules that do not exist: {stale}"


def test_no_import_reaches_a_later_layer(graph, layers):
    upward = [
        f"{module} (layer {layers[layer_of(module, layers)][0]}) imports {target} (layer {layers[layer_of(target, layers)][0]}), line {line}"
        for module, targets in graph.items()
        for target, line in targets.items()
        if layer_of(target, layers) > layer_of(module, layers)
    ]
    assert not upward, "imports of a module in a later layer (a layer builds only on the layers before it):\n" + "\n".join(upward)


def test_stages_do_not_import_each_other(graph, layers):
    stages = next(patterns for name, patterns in layers if name == STAGE_LAYER)
    crossing = [
        f"{module} imports {target}, line {line}" for module in stages for target, line in graph[module].items() if target in stages
    ]
    assert not crossing, "pipeline stages that import another stage (read its outputs through pipeline.folders instead):\n" + "\n".join(
        crossing
    )


def test_the_import_graph_has_no_circle(graph):
    # depth-first search; a back edge closes a circle, reported with every module on it
    state: dict[str, str] = {}
    circles: list[list[str]] = []

    def visit(module: str, path: list[str]) -> None:
        state[module] = "open"
        for target in graph[module]:
            if state.get(target) == "open":
                circles.append(path[path.index(target) :] + [target])
            elif target not in state:
                visit(target, [*path, target])
        state[module] = "closed"

    for module in graph:
        if module not in state:
            visit(module, [module])
    assert not circles, "import circles:\n" + "\n".join(" -> ".join(c) for c in circles)


def test_the_check_sees_a_circle_and_an_upward_import(tmp_path):
    # the parser itself: an upward import and a circle written into fake modules are found
    modules = {"pkg.a": tmp_path / "a.py", "pkg.b": tmp_path / "b.py"}
    modules["pkg.a"].write_text("def f():\n    from pkg import b\n")
    modules["pkg.b"].write_text("from .a import f\n")
    assert imports_of("pkg.a", modules["pkg.a"], modules) == {"pkg.b": 2}
    assert imports_of("pkg.b", modules["pkg.b"], modules) == {"pkg.a": 1}


#: The old paths of the application's modules, kept one version with a DeprecationWarning: each
#: forwards to the module of ``divmorph`` and holds nothing else (CHANGELOG, 0.2.0).
DEPRECATED_PATHS = {
    "sb3_divmorph.pipeline": "divmorph.pipeline",
    "sb3_divmorph.pretrained": "divmorph.pretrained",
    "sb3_divmorph.record": "divmorph.record",
    "sb3_divmorph.plot": "divmorph.plot",
    "sb3_divmorph.shipped": "divmorph.shipped",
}


def test_the_library_imports_nothing_of_the_application(graph):
    """``sb3_divmorph`` (the SB3 extension) builds on ``unimal_envs`` alone: no module of it imports
    ``divmorph`` (the application: command line, pipeline, run folders), by any import statement or
    by ``importlib`` -- except the deprecated forwarding paths, which are nothing but that."""
    library = {name: targets for name, targets in graph.items() if name.split(".")[0] == "sb3_divmorph"}
    by_statement = [
        f"{name} imports {target}, line {line}"
        for name, targets in library.items()
        for target, line in targets.items()
        if target.split(".")[0] == "divmorph"
    ]
    modules = package_modules()
    by_name = [
        name
        for name in library
        if name not in DEPRECATED_PATHS and re.search(r"import_module\(\s*[\"']divmorph", modules[name].read_text())
    ]
    assert not by_statement and not by_name, "the library imports the application:\n" + "\n".join(by_statement + by_name)
    for old, new in DEPRECATED_PATHS.items():
        text = modules[old].read_text()
        assert f'"{new}"' in text and "DeprecationWarning" in text, f"{old} should forward to {new} with a DeprecationWarning"


def test_old_paths_of_the_application_warn_and_give_the_moved_module():
    """A script written against 0.1 (``from sb3_divmorph.pipeline.config import ConfigError``) keeps
    working for one version: it is warned, and it gets the very objects of ``divmorph``."""
    import importlib
    import subprocess
    import sys

    code = (
        "import warnings\nwarnings.simplefilter('error', DeprecationWarning)\n"
        "import divmorph.pipeline.config as new\n"
        "try:\n    import sb3_divmorph.pipeline.config\nexcept DeprecationWarning as w:\n    print('warned:', w)\n"
        "warnings.simplefilter('ignore', DeprecationWarning)\n"
        "from sb3_divmorph.pipeline.config import ConfigError\n"
        "from sb3_divmorph.pretrained import load_pretrained\n"
        "import divmorph.pretrained\n"
        "print(ConfigError is new.ConfigError, load_pretrained is divmorph.pretrained.load_pretrained)\n"
    )
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout
    assert "warned: sb3_divmorph.pipeline moved to divmorph.pipeline" in shown, shown
    assert shown.strip().endswith("True True"), shown
    assert importlib.import_module("divmorph.pipeline.config")


@pytest.mark.shipped_results
def test_every_shipped_model_loads_from_the_library_alone():
    """The shipped models name their policy class by its module today (``sb3_divmorph.policies.*``):
    they load with ``PPO.load`` and nothing of the application imported."""
    import subprocess
    import sys

    tracked = subprocess.run(["git", "ls-files", "results/*model.zip"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    if not tracked:
        pytest.skip("not a git checkout")
    code = (
        "import sys\nfrom stable_baselines3 import PPO\nimport sb3_divmorph\n"
        "for path in sys.argv[1:]:\n"
        "    model = PPO.load(path, device='cpu')\n"
        "    assert type(model.policy).__module__.startswith('sb3_divmorph.policies.'), path\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'divmorph'))\n"
    )
    shown = subprocess.run([sys.executable, "-c", code, *tracked], capture_output=True, text=True, check=True, cwd=ROOT).stdout
    assert shown.strip() == "[]", shown
