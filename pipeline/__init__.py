"""The DeepWORD pipeline engine: stage DAG, content-addressed cache, MLflow tracking, CLI.

It knows nothing about wheels and never imports ``stages``; stages are named in ``conf/config.yaml``.
Entry point: ``python -m pipeline`` (``pipeline.cli``); programmatic: ``pipeline.runner.run_pipeline``.
"""
