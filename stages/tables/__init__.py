"""The paper's tables from the pipeline's runs: rows defined by Hydra overrides (``rows``), tables, charts
and the results page (``compare``). Run by ``make compare``."""
