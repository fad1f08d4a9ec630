"""Packaging glue that ``pyproject.toml`` cannot express (everything else is there).

``zoo_configs/`` (the rl-zoo hyperparameters and the pipeline profiles) stays at the repository
root, where ``python -m rl_zoo3.train --conf-file zoo_configs/ppo.yml`` finds it, and is shipped
inside the package as ``sb3_divmorph/zoo_configs/`` by mapping that package onto the root folder:
one copy of each file, in wheels and editable installs alike (``sb3_divmorph.zoo`` finds it with
``importlib.resources``). ``examples/`` ships the same way, as ``divmorph.examples``, so a pip user
runs ``python -m divmorph.examples.distill_dagger`` where a checkout runs ``python examples/distill_dagger.py``.
"""

from setuptools import find_namespace_packages, find_packages, setup

setup(
    packages=[
        *find_packages(include=["unimal_envs*", "sb3_divmorph*", "divmorph*"]),
        # unimal_envs' data folders (the MJCF template, the text embeddings, the shipped robots) hold no
        # code, but setuptools counts them as packages whose files it ships, so they are named as such
        *find_namespace_packages(include=["unimal_envs.assets", "unimal_envs.data", "unimal_envs.data.*"]),
        "sb3_divmorph.zoo_configs",
        "divmorph.examples",
    ],
    package_dir={"sb3_divmorph.zoo_configs": "zoo_configs", "divmorph.examples": "examples"},
)
