"""Detections as the library sees them: letterboxing, decoded detections as WORD records, average precision and where it goes (all torch-free)."""
