"""The `deepword infer` and `deepword tune` commands: a pipeline run's artifacts found through MLflow (resolve), then the library's runtime (deepword.inference)."""
