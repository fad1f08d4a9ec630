"""The ``divmorph`` command line (:mod:`divmorph.cli`) of the knowledge-diversion pipeline.

The library is :mod:`sb3_divmorph` (policies, training tools, the pipeline's stages) with the
benchmark :mod:`unimal_envs`; this package only parses commands and calls the pipeline. It is a
package of its own so that ``divmorph --help`` answers without importing the library (and torch):
importing any ``sb3_divmorph`` module imports the package, which registers its policies with
Stable-Baselines3. ``python -m divmorph`` is the same command.
"""
