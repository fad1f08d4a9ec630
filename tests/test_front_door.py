"""The library's front door: ``sb3_divmorph`` exports what a user imports (policies, algorithms,
distillation, transfer, deployment, saved models) and nothing else, and what users read -- the
examples, the README and the documentation pages -- imports the library only through it.

A building block stays importable from its own module; it is just not on the front door, so that
``from sb3_divmorph import ...`` in a user's script names the things the library is for.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

import sb3_divmorph

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = "sb3_divmorph"

#: ``sb3_divmorph.__all__``: the front door, by role
FRONT_DOOR = {
    # policies
    "MetaMorphPolicy",
    "DivMorphPolicy",
    "ModuMorphPolicy",
    "HyperDistillPolicy",
    # algorithms
    "DevicePPO",
    "ImitationPPO",
    # distillation
    "DAggerCallback",
    "Teacher",
    "TeacherMixingVecEnv",
    # transfer with fixed gates, and its argument
    "prepare_transfer",
    "UnitSelection",
    # the compact actor, its export and the runner of the exported file
    "CompactActor",
    "export_onnx",
    "export_torchscript",
    "OnnxActor",
    # saved models and the shipped rl-zoo settings
    "load_model",
    "NormalizedModel",
    "zoo_hyperparams",
}


def python_blocks(page: Path) -> list[str]:
    """The ``python`` code blocks of a Markdown page, in order."""
    return [code for lang, code in re.findall(r"```(\w*)\n(.*?)```", page.read_text(), flags=re.S) if lang == "python"]


def user_sources() -> dict[str, str]:
    """``{where: Python source}`` of everything a user reads: the examples and every Python block of
    the README and the documentation pages."""
    sources = {str(path.relative_to(ROOT)): path.read_text() for path in sorted((ROOT / "examples").glob("*.py"))}
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    for page in pages:
        for index, code in enumerate(python_blocks(page)):
            sources[f"{page.relative_to(ROOT)}, python block {index}"] = code
    return sources


def leaf_imports(source: str, where: str) -> list[str]:
    """The imports of a module below the front door (``sb3_divmorph.<submodule>``) in ``source``,
    as ``"<where>, line <n>: <module>"``."""
    found = []
    for node in ast.walk(ast.parse(source, filename=where)):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            modules = [node.module or ""]
            if node.module == LIBRARY:  # ``from sb3_divmorph import nn`` reaches a submodule too
                modules = [f"{LIBRARY}.{alias.name}" for alias in node.names if alias.name not in FRONT_DOOR]
        else:
            continue
        found += [f"{where}, line {node.lineno}: {module}" for module in modules if module.startswith(f"{LIBRARY}.")]
    return found


def test_the_front_door_is_exactly_what_users_import():
    assert len(sb3_divmorph.__all__) == len(set(sb3_divmorph.__all__)), "a name is listed twice in sb3_divmorph.__all__"
    assert set(sb3_divmorph.__all__) == FRONT_DOOR, (
        f"sb3_divmorph.__all__ has {sorted(set(sb3_divmorph.__all__) - FRONT_DOOR)} beyond the front door and lacks "
        f"{sorted(FRONT_DOOR - set(sb3_divmorph.__all__))}"
    )
    namespace: dict = {}
    exec(f"from {LIBRARY} import *", namespace)  # noqa: S102  (the star import a user may write)
    assert FRONT_DOOR <= set(namespace)
    for name in FRONT_DOOR:
        # each one is the object of its defining module, not a copy
        value = getattr(sb3_divmorph, name)
        assert getattr(importlib.import_module(value.__module__), name) is value, name


def test_building_blocks_stay_importable_from_their_own_modules():
    from sb3_divmorph.deploy.hyperdistill_mlp import HyperDistillMLP
    from sb3_divmorph.deploy.modumorph_actor import ModuMorphActor
    from sb3_divmorph.nn.layers import DenseLinear, FactorizedLinear
    from sb3_divmorph.nn.transformer import MultiHeadSelfAttention
    from sb3_divmorph.policies.morphology_transformer import DIVMORPH_PRESETS, PRESETS

    assert all((HyperDistillMLP, ModuMorphActor, DenseLinear, FactorizedLinear, MultiHeadSelfAttention, PRESETS, DIVMORPH_PRESETS))
    assert not {"DenseLinear", "MultiHeadSelfAttention", "HyperDistillMLP", "PRESETS"} & set(sb3_divmorph.__all__)


def test_importing_the_library_registers_the_policy_aliases():
    from stable_baselines3 import A2C, PPO, SAC

    for algo in (PPO, A2C):
        assert algo.policy_aliases["DivMorphPolicy"] is sb3_divmorph.DivMorphPolicy
    with pytest.raises(TypeError, match="on-policy"):
        SAC.policy_aliases["DivMorphPolicy"]()


def test_examples_and_pages_import_the_library_through_its_front_door():
    sources = user_sources()
    assert any(where.startswith("examples/") for where in sources) and any("README.md" in where for where in sources)
    leaves = [leaf for where, source in sources.items() for leaf in leaf_imports(source, where)]
    assert not leaves, "imports below sb3_divmorph's front door (import these from sb3_divmorph):\n" + "\n".join(leaves)


def test_the_leaf_import_check_sees_one():
    # the parser itself: each form of an import below the front door is found, the front door is not
    source = (
        "import sb3_divmorph\nfrom sb3_divmorph import DivMorphPolicy\n"
        "from sb3_divmorph.nn.layers import DenseLinear\nimport sb3_divmorph.zoo\nfrom sb3_divmorph import nn\n"
    )
    assert leaf_imports(source, "x.py") == [
        "x.py, line 3: sb3_divmorph.nn.layers",
        "x.py, line 4: sb3_divmorph.zoo",
        "x.py, line 5: sb3_divmorph.nn",
    ]


def test_the_api_reference_lists_the_front_door():
    api = (ROOT / "docs" / "api.md").read_text()
    section = api.split("## The library (`sb3_divmorph`)", 1)[1].split("\n## ", 1)[0]
    listed = re.findall(r"^::: ([\w.]+)$", section, flags=re.M)
    assert sorted(listed) == sorted(f"{LIBRARY}.{name}" for name in FRONT_DOOR), listed
