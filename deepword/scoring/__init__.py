"""Scoring relation predictions against a WORD-style dataset (`deepword score`), the pair errors by cause and the report tables."""
