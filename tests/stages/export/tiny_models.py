"""Sizes of the small upstream models the export tests build (``conftest``) and check against. (A module of
its own, not conftest.py: test modules import from it, and ``conftest`` is one module name for every test
folder's conftest.)"""

from pathlib import Path

from omegaconf import OmegaConf

# the evaluate stage's default grids of the baselines' search
EVAL_GRIDS = OmegaConf.to_container(OmegaConf.load(Path(__file__).parents[3] / "conf/eval/default.yaml").baseline_grids)

PRIORS_CFG = {"mode": "prior", "components": [1, 2], "n_init": 1, "reg_covar": 1e-4, "max_fit_samples": 2000,
              "plot_bins": 20}
CONV_FC_16 = {"_target_": "stages.relation.backbones.ConvFC", "input_size": 16, "expansion": 1}
RESNET18_16 = {"_target_": "stages.relation.backbones.ResNet18", "input_size": 16, "base_width": 8}
RELATION_MODEL = {"backbone": CONV_FC_16, "hidden": 16,
                  "embed_dim": 8, "gat": True, "gat_hidden": 8, "gcn_layers": 2,
                  "edge_geometry": True, "geometry_gate": True}  # the default network: both geometry additions
MAX_OBJECTS = 20
DETECTOR = {"backbone": {"_target_": "stages.detector.backbones.TinyBackbone", "channels": [4, 8, 8, 8],
                         "out_channels": 8}, "head_conv": 8,
            "input_width": 64, "input_height": 64, "max_detections": 10, "score_threshold": 0.1}
EXPORT_CFG = {"min_box_px": 4, "register": True, "int8": {"op_types": ["MatMul", "Gemm"]},
              "parity": {"max_abs_diff": 1e-4, "min_agreement": 99.9, "images": None, "detector_images": 3},
              "latency": {"threads": 1, "runs": 3, "warmup": 1, "images": 4},
              "footprint_point": {"vehicle": 0.1, "wheel": None},
              "operating_point": {"grid": [0.1, 0.3, 0.5], "min_side_grid": {"wheel": [0, 4]}, "match_iou": 0.5,
                                  "images": None, "threads": 1},
              # the IoU rule fitted as the `evaluated` fixture fits its logic row (fit_images 20, the default grids)
              "end_to_end": {"method": "deepword_then_logic",
                             "fit": {"images": 20, "couple_tolerance": EVAL_GRIDS["couple_tolerance"],
                                     "logic_iou": EVAL_GRIDS["logic_iou"]}}}
