"""The `evaluate` stage: the §7 metrics, the logic-model baselines and the Table 3 report."""
