"""``zoo_configs/``: rl-zoo hyperparameters (``ppo.yml``) and pipeline profiles (``divmorph.yml``).

This folder is installed as the package ``sb3_divmorph.zoo_configs`` (see ``setup.py``), so the
files are found from any working directory through :mod:`sb3_divmorph.zoo`; this file only makes
that mapping work in editable installs too. rl-zoo: ``--conf-file sb3_divmorph.zoo`` from anywhere,
or ``--conf-file zoo_configs/ppo.yml`` from the repository root.
"""
