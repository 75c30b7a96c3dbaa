"""What a relation backbone is in a config, without torch: the ``relation/backbone`` group's node names its class
(``_target_``) and holds the keyword arguments it takes, ``input_size`` (the crop side S) among them; the network's
width (``out_dim``, ``relation.model.hidden``) is given when it is built (``stages.relation.backbones.build_backbone``).

Models and MLflow runs from before the ``_target_`` named a backbone by ``name`` (``conv_fc``, ``resnet18``) with the
fields ``input_size``, ``expansion`` and ``base_width`` every backbone carried; ``LEGACY_BACKBONES`` says which class
each name is and which of those fields it takes, so their relation.json still loads (``legacy_backbone``) and their
runs still match the table rows (``stages.tables.rows``).
"""

from __future__ import annotations

TARGET = "_target_"
CONV_FC = "stages.relation.backbones.ConvFC"
RESNET18 = "stages.relation.backbones.ResNet18"
# a backbone's name before ``_target_`` -> (its class, the fields of the old common layout it takes)
LEGACY_BACKBONES = {"conv_fc": (CONV_FC, ("input_size", "expansion")),
                    "resnet18": (RESNET18, ("input_size", "base_width"))}


def legacy_backbone(name: str, fields: dict) -> dict:
    """The backbone node of a model saved with ``backbone: <name>`` and the common fields in ``fields``."""
    if name not in LEGACY_BACKBONES:
        raise ValueError(f"unknown relation backbone {name!r} (a model saved before relation/backbone named its "
                         f"class knows {', '.join(LEGACY_BACKBONES)})")
    target, keys = LEGACY_BACKBONES[name]
    return {TARGET: target, **{k: fields[k] for k in keys if k in fields}}


def backbone_target(params: dict[str, str], prefix: str = "relation.backbone.") -> str | None:
    """The backbone class a run's flattened parameters name: ``<prefix>_target_``, or for a run logged before it
    existed the class of ``<prefix>name``; None when neither is there."""
    if f"{prefix}{TARGET}" in params:
        return params[f"{prefix}{TARGET}"]
    name = params.get(f"{prefix}name")
    return None if name is None else LEGACY_BACKBONES.get(name, (name,))[0]
