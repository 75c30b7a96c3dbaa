"""The one error type the engine raises for problems the user can fix (config, cache, tracking)."""


class PipelineError(RuntimeError):
    """A clear, user-facing pipeline problem; the CLI prints its message without a traceback."""
