"""Helpers of the data stage tests (a uniquely named module: other test folders have a conftest too)."""

from pathlib import Path

from omegaconf import OmegaConf

CONF = Path(__file__).resolve().parents[3] / "conf" / "data"


def synword_cfg(frames: int = 4, size=(320, 240), workers: int = 1) -> dict:
    cfg = OmegaConf.to_container(OmegaConf.load(CONF / "synword.yaml"), resolve=True)
    cfg.update(frames=frames, image_size=list(size), workers=workers)
    return cfg
