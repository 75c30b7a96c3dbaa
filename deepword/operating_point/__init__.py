"""The detector's operating point: the search over per-class score thresholds and minimum box sides, and its report."""
