"""Lightning's log lines printed once under the pipeline's logging.

``import lightning`` gives the ``lightning`` logger a console handler of its own, yet the logger still
propagates to the root logger, which Hydra configures (console and the job's log file): every Lightning
line ("GPU available", "`Trainer.fit` stopped") came out twice, once without the pipeline's format. (Its
``lightning.pytorch`` / ``lightning.fabric`` loggers, when imported before the root had handlers, print
through handlers of their own and do not propagate: their lines never reached the job's log file.)"""

from __future__ import annotations

import logging


def route_lightning_logs() -> None:
    """When the root logger has handlers, drop the ``lightning`` logger's own, so its lines reach the
    console once, through the root's handlers. Without root handlers (a bare script) Lightning keeps its own."""
    import lightning  # noqa: F401  (importing it is what adds the handler)

    if not logging.getLogger().handlers:
        return
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            logger.removeHandler(handler)
        logger.propagate = True
