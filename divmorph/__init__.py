"""The knowledge-diversion application, built on the library :mod:`sb3_divmorph` and the benchmark :mod:`unimal_envs`.

- :mod:`divmorph.pipeline`: the stages (teachers, distill, hyperdistill, grl, transfer, export,
  evaluate, report) as functions of a profile and a run folder;
- :mod:`divmorph.pretrained`: a model loaded by its run folder, with its statistics, robots and env settings;
- :mod:`divmorph.record`, :mod:`divmorph.plot`: videos and learning curves, headless;
- :mod:`divmorph.shipped`: the shipped runs' models for a pip install;
- :mod:`divmorph.cli`: the ``divmorph`` command (``python -m divmorph`` is the same).

Importing this package imports nothing else, so ``divmorph --help`` answers without torch.
"""
