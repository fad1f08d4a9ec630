"""Short scripts on the Python API, shipped with the package: from a checkout ``python examples/NAME.py``,
from a pip install ``python -m divmorph.examples.NAME`` (``distill_dagger``, ``load_run_model``,
``transfer``, ``export_actor``; each takes ``--help``). ``docs/examples.md`` says what each does and how long it takes."""
