"""edge-landing: an edge inference runtime for safe UAV landing.

One import root for the whole project; each part is a subpackage named after its role:

- ``edge_landing.runtime``: what the drone runs (core messages and geometry, perception, fusion, I/O, pipeline);
- ``edge_landing.cli``: the ``edge-run`` and ``edge-eval`` command lines and the one-line error convention;
- ``edge_landing.evaluation``: offline metrics, scene folders, the paper's tables;
- ``edge_landing.calibration``: per-scene and in-flight depth scale;
- ``edge_landing.export``: the PyTorch zoo, ONNX export, INT8 quantization, training (``[export]`` extra);
- ``edge_landing.sim``: the synthetic benchmark generator (``[sim]`` extra);
- ``edge_landing.benchmarks``: speed and accuracy reports (``[bench]`` extra).

Importing this package loads nothing else.
"""
__version__ = "0.2.0"
