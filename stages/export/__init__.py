"""ONNX export of the relation network and the detector, parity, INT8, latency, and `deepword infer`."""
