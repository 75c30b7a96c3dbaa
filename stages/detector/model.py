"""The CenterNet network (backbone + heads), its decoding wrapper for export, and how a trained model is
saved and loaded: ``model.pt`` (a state_dict) beside ``model.json`` (everything needed to rebuild it and
to preprocess its input)."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from deepword.detection.letterbox import MEAN, STD
from deepword.word_format import CLASS_NAMES
from stages.detector.backbones import backbone_spec, build_backbone
from stages.detector.decode import decode_outputs
from stages.detector.heads import CenterNetHeads

DOWN_RATIO = 4  # CenterNet's output stride
WEIGHTS_FILE = "model.pt"
CONFIG_FILE = "model.json"


class CenterNet(nn.Module):
    """Image batch (B, 3, H, W) -> (heatmap probabilities (B, C, H/4, W/4), regression maps): sizes (B, 2, ..) and
    offsets (B, 2, ..) for ``regression="centernet"``, side distances (B, 4, ..) for ``"ttfnet"``; with ``facing``
    the facing map (B, 2, ..) last."""

    def __init__(self, backbone: nn.Module, head_conv: int, num_classes: int = len(CLASS_NAMES),
                 regression: str = "centernet", facing: bool = False):
        super().__init__()
        self.backbone = backbone
        self.heads = CenterNetHeads(backbone.out_channels, head_conv, num_classes, regression, facing)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.heads(self.backbone(images))

    def decode(self, outputs: tuple[torch.Tensor, ...], k: int) -> torch.Tensor:
        """``outputs`` of this network -> (B, k, 6) detections, (B, k, 8) with the facing head (``decode_outputs``)."""
        return decode_outputs(outputs, k=k, down_ratio=DOWN_RATIO, regression=self.heads.regression,
                              facing=self.heads.has_facing)


class CenterNetWithDecode(nn.Module):
    """The network followed by peak extraction and top-K: images -> (B, K, 6) detections in input pixels
    (x1, y1, x2, y2, score, class; then facing x, y with the facing head). The form to export when the runtime
    should do no post-processing."""

    def __init__(self, net: CenterNet, k: int = 100):
        super().__init__()
        self.net, self.k = net, k

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.net.decode(self.net(images), self.k)


def model_config(detector_cfg: dict) -> dict:
    """The JSON-able description of a model built from the stage config ``detector``."""
    return {
        "backbone": backbone_spec(detector_cfg["backbone"]),
        "head_conv": int(detector_cfg["head_conv"]),
        "regression": str(detector_cfg.get("regression", "centernet")),
        "facing": bool(detector_cfg.get("facing", False)),
        "class_names": list(CLASS_NAMES),
        "input_width": int(detector_cfg["input_width"]),
        "input_height": int(detector_cfg["input_height"]),
        "down_ratio": DOWN_RATIO,
        "max_detections": int(detector_cfg["max_detections"]),
        "score_threshold": float(detector_cfg["score_threshold"]),
        "mean": MEAN.tolist(),
        "std": STD.tolist(),
    }


def build_centernet(config: dict) -> CenterNet:
    """A CenterNet from ``model_config(...)``; checks the input size fits the backbone's strides."""
    backbone = build_backbone(config["backbone"])
    multiple = backbone.stride_multiple
    for key in ("input_width", "input_height"):
        if int(config[key]) % multiple:
            raise ValueError(f"detector.{key}={config[key]} must be divisible by {multiple} "
                             f"for backbone {type(backbone).__name__}")
    # a model.json written before the regression choice existed is CenterNet's; before the facing head, without one
    return CenterNet(backbone, int(config["head_conv"]), len(config["class_names"]),
                     config.get("regression", "centernet"), bool(config.get("facing", False)))


def save_detector(out_dir: Path, net: CenterNet, config: dict) -> None:
    torch.save(net.state_dict(), Path(out_dir) / WEIGHTS_FILE)
    (Path(out_dir) / CONFIG_FILE).write_text(json.dumps(config, indent=1))


def load_detector(stage_dir: str | Path) -> tuple[CenterNet, dict]:
    """The trained network (eval mode) and its config from a detector stage's output directory."""
    stage_dir = Path(stage_dir)
    config = json.loads((stage_dir / CONFIG_FILE).read_text())
    net = build_centernet(config)
    net.load_state_dict(torch.load(stage_dir / WEIGHTS_FILE, map_location="cpu", weights_only=True))
    return net.eval(), config
