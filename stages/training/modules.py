"""Networks built the Hydra way: a config node names a class (``_target_``) and holds the keyword arguments it
takes (the relation and detector backbones: ``conf/relation/backbone``, ``conf/detector/backbone``).

``build_module`` imports the class with ``hydra.utils.get_object`` and calls it, rather than ``instantiate``, because
the node may also come from a trained model's JSON on disk (relation.json, model.json): only an ``nn.Module`` class is
built, its arguments are the node's plain values (nothing nested is instantiated), and a missing or unexpected
argument is an error naming the config node.
"""

from __future__ import annotations

from hydra.utils import get_object
from torch import nn

TARGET = "_target_"


def build_module(spec: dict, where: str, **given) -> nn.Module:
    """``spec[_target_](**spec's other keys, **given)``, an ``nn.Module``; ``where`` names the config node in errors."""
    if not isinstance(spec, dict) or TARGET not in spec:
        raise ValueError(f"{where}: no {TARGET} (the class to build) in {spec!r}")
    target = spec[TARGET]
    try:
        cls = get_object(target)
    except Exception as exc:   # Hydra wraps the import error in its own
        raise ValueError(f"{where}.{TARGET}: cannot import {target!r}: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise TypeError(f"{where}.{TARGET}: {target!r} is not a torch nn.Module class")
    kwargs = {k: v for k, v in spec.items() if k != TARGET}
    try:
        return cls(**kwargs, **given)
    except TypeError as exc:
        raise TypeError(f"{where}: {target} does not take the arguments {sorted(kwargs)} (+ {sorted(given)}): "
                        f"{exc}") from exc
