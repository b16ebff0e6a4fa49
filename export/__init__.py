"""tactile.export: a training run's checkpoint to one deployable ONNX file.

Modules, one concept each: ``graph`` (the graph: preprocessing + model + state), ``compose``
(wiring ONNX graphs by name), ``windows`` (windows to check parity on), ``parity`` (onnxruntime
vs PyTorch), ``metadata`` (the contract of :mod:`tactile.contract` filled from a checkpoint),
``quantize`` (int8), ``cli`` (``tactile-export``), ``check`` (``tactile-check``).
"""
