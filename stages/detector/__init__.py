"""The CenterNet detector stage ("Objects as Points", Zhou et al. 2019): vehicles and wheels as centre
heatmap peaks with box size and sub-pixel offset, at output stride 4.

Domain code (letterboxing, augmentation, targets, losses, decoding, networks, metrics) is plain numpy /
torch and importable without Lightning or MLflow; ``lightning.py`` and ``stage.py`` are the edges.
"""
