"""The DeepWORD library: the domain code the pipeline's stages, the inference runtime and the ``deepword`` command
stand on (docs/design.md §2). No Lightning, MLflow or Hydra here, and torch only in the modules that need it; it
never imports ``stages`` or ``pipeline``."""
