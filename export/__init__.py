"""tactile.export: a training run's checkpoint to one deployable ONNX file; every byte of ONNX.

Modules, one concept each:

* building graphs: ``traced`` (the pinned exporter path, ``torch.onnx.export``, constant
  folding, inlining, ``Loop`` bodies), ``emd_graph`` (the EMD graph, its sifts in ``Loop``
  nodes), ``coder_graph`` (a sparse coder alone), ``compose`` (wiring ONNX graphs by name),
  ``graph`` (the deployable graph: preprocessing + model + state);
* checking them: ``session`` (the onnxruntime session the checks use), ``windows`` (windows to
  check parity on), ``taps`` (where each sparse coder sits in a graph, and a copy that shows
  it), ``codes`` (the graph's codes against scikit-learn's), ``ties`` (the probability
  differences near-tie atom flips and float32 codes excuse), ``parity`` (onnxruntime vs
  PyTorch);
* the file: ``metadata`` (the contract of :mod:`tactile.contract` filled from a checkpoint),
  ``quantize`` (int8), ``exporter`` (a run to one checked file), ``check`` (is a file a model
  we can deploy);
* ``commands``: ``export`` (``tactile-export``), ``check`` (``tactile-check``).
"""
