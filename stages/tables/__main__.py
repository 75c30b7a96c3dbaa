"""``python -m stages.tables``: see ``stages.tables.compare``."""

from stages.tables.compare import main

main()
