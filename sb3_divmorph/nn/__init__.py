"""Building blocks of the policies: layers that can be diverted, gates, the Transformer, token
decoders, feature extractors and the masked action distribution.

May import: torch, Stable-Baselines3, :mod:`unimal_envs.contract` -- nothing else of this package.

- :mod:`~sb3_divmorph.nn.layers`: ``FactorizedLinear`` (rank-1 units: learngenes, tailors; Cayley
  square factor), ``DenseLinear``, ``LinearBuilder``.
- :mod:`~sb3_divmorph.nn.gates`: soft TopK gates, the morphology encoder, ``DiversionRouter``.
- :mod:`~sb3_divmorph.nn.transformer`: the pre-LN encoder with dense or factorized projections.
- :mod:`~sb3_divmorph.nn.decoders`: per-token action / value decoders.
- :mod:`~sb3_divmorph.nn.extractors`: limbs as tokens (``MorphologyTransformerExtractor``), exteroception.
- :mod:`~sb3_divmorph.nn.distributions`: the diagonal Gaussian over real action slots only.
"""
