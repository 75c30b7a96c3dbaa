"""Hand-written relation rules: the logic-model baselines (docs/design.md §7) and one method falling back on another."""
