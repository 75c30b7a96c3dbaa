"""Lightning's lines reach a configured root logger once, not also through Lightning's own console handler."""

import logging

from stages.training.lightning_logs import route_lightning_logs


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__()
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


def test_lightning_lines_are_printed_once_through_the_root_handlers():
    import lightning  # noqa: F401

    names = ("lightning", "lightning.pytorch", "lightning.fabric")
    saved = {n: (list(logging.getLogger(n).handlers), logging.getLogger(n).propagate) for n in names}
    logging.getLogger("lightning").addHandler(logging.NullHandler())  # what `import lightning` adds (an
    # earlier stage run in this session may already have routed the real one away)
    pytorch_logger = logging.getLogger("lightning.pytorch")
    pytorch_logger.addHandler(logging.NullHandler())  # as when imported before the root had handlers
    pytorch_logger.propagate = False
    root, collect = logging.getLogger(), _Collect()
    root.addHandler(collect)
    try:
        route_lightning_logs()
        assert all(not logging.getLogger(n).handlers for n in names)
        logging.getLogger("lightning.pytorch.trainer").warning("Trainer.fit stopped")
        assert collect.lines == ["Trainer.fit stopped"]  # reached the root's handlers, once
    finally:
        root.removeHandler(collect)
        for name, (handlers, propagate) in saved.items():
            logger = logging.getLogger(name)
            for handler in list(logger.handlers):
                logger.removeHandler(handler)
            for handler in handlers:
                logger.addHandler(handler)
            logger.propagate = propagate


def test_importing_lightning_still_adds_its_own_handler():
    """The reason for route_lightning_logs; when this fails, Lightning stopped doing it and the module can go."""
    import subprocess
    import sys

    code = "import logging, lightning; print(len(logging.getLogger('lightning').handlers))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert int(out.strip().splitlines()[-1]) >= 1


def test_lightnings_cloud_logger_tip_is_dropped_and_its_other_lines_kept():
    from lightning.pytorch.utilities.rank_zero import rank_zero_info

    route_lightning_logs()
    rank_zero, collect = logging.getLogger("lightning.pytorch.utilities.rank_zero"), _Collect()
    rank_zero.addHandler(collect)
    try:
        rank_zero_info("\N{ELECTRIC LIGHT BULB} Tip: For seamless cloud logging and experiment tracking, try installing "
                       "[litlogger](https://pypi.org/project/litlogger/) to enable LitLogger")
        rank_zero_info("GPU available: False, used: False")
        assert collect.lines == ["GPU available: False, used: False"]
    finally:
        rank_zero.removeHandler(collect)
