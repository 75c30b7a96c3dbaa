"""``python -m pipeline [overrides]``: the Hydra entry point (see ``pipeline.cli``)."""

from pipeline.cli import main

if __name__ == "__main__":
    main()
