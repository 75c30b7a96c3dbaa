"""Inference with a shipped bundle (an export stage's output) in onnxruntime, without torch: the runtime the evaluate stage scores and `deepword infer` runs, and footprints for its predictions."""
