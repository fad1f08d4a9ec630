"""Deployment: a trained policy pruned and folded into a small actor for one robot and task, and
run without this project (ONNX).

May import: :mod:`sb3_divmorph.nn`, :mod:`sb3_divmorph.policies` (``onnx_actor`` imports only
numpy and onnxruntime, so it can be copied next to a robot's controller).

- :mod:`~sb3_divmorph.deploy.deployment`: what every deployed actor shares (baked normalisation,
  FLOP count, ONNX export).
- :mod:`~sb3_divmorph.deploy.compact`: DivMorph / MetaMorph pruned and merged (``CompactActor``).
- :mod:`~sb3_divmorph.deploy.modumorph_actor`, :mod:`~sb3_divmorph.deploy.hyperdistill_mlp`: the
  baselines' deployed forms.
- :mod:`~sb3_divmorph.deploy.onnx_actor`: ``OnnxActor``, an exported actor under onnxruntime.
"""
