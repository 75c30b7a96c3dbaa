"""ONNX export of the relation network and the detector, parity, INT8 and latency: the bundle `stages.inference` runs."""
