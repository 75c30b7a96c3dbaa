"""Starting weights: the ``init`` config group (docs/stages.md, "init: starting from earlier weights").

``init=scratch`` (the default) trains from random weights. ``init=run`` starts a network from what an earlier
pipeline run trained: the run id (the invocation's parent run, or one of its stage runs) is looked up in the
MLflow store, its ``<network>`` stage run names the cache entry it computed or used (tag ``cache_key``), and that
entry's weights file is the start. ``init=checkpoints`` names the files (or stage output directories) directly.

Each training stage's ``resolve`` hook (``stages.<network>.warm_start``) calls ``resolve_start`` at plan time,
before any stage runs: the weights file joins the stage's inputs (the cache key covers its sha256, not the run
id or the path), the fine-tuning budget joins its config (``init.train``), and the lineage becomes tags of the
stage's MLflow run and of the parent run. Every problem -- unknown run id, a run without that stage, a cache
entry gone, a missing file, weights of another architecture -- is an ``InitError`` naming what to change.

Nothing heavy at import: the hook runs on every plan, and torch or MLflow are imported only for ``init`` other
than ``scratch``.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

INIT_INPUT = "init"  # the stage input under which the starting weights file arrives
NETWORKS = ("detector", "relation")
SOURCES = ("scratch", "run", "checkpoints")


class InitError(ValueError):
    """The configured starting weights cannot be used; the message says what to change."""


@dataclass(frozen=True)
class Network:
    """What ``resolve_start`` needs to know about one trained network."""

    name: str            # the stage, and the network's name in ``init`` (init.<name>, init.<name>_train)
    weights_file: str    # what its stage writes in its output directory
    ckpt_prefix: str     # the network's prefix in its Lightning module's state_dict (a .ckpt)


def init_config(cfg) -> dict | None:
    """The resolved ``init`` group as plain values; None for scratch (or no group at all)."""
    from omegaconf import OmegaConf

    node = cfg.get("init") if hasattr(cfg, "get") else None
    if node is None:
        return None
    init = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else dict(node)
    source = init.get("source", "scratch")
    if source not in SOURCES:
        raise InitError(f"init.source={source!r}: expected one of {list(SOURCES)} (choose init=scratch|run|checkpoints)")
    return None if source == "scratch" else init


def starts_from_weights(init: dict, network: str) -> bool:
    if init["source"] == "run":
        networks = list(init.get("networks") or [])
        unknown = [n for n in networks if n not in NETWORKS]
        if unknown:
            raise InitError(f"init.networks: unknown network(s) {unknown}; choose among {list(NETWORKS)}")
        return network in networks
    return init.get(network) is not None


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with Path(path).open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# -- where the weights are ----------------------------------------------------------------------------------


def _weights_in(path: Path, net: Network, what: str) -> Path:
    """A weights file, or the weights file of a stage output directory (or of its cache entry)."""
    if path.is_file():
        return path
    if path.is_dir():
        for candidate in (path / net.weights_file, path / "out" / net.weights_file):
            if candidate.is_file():
                return candidate
        raise InitError(f"{what}={path}: a directory without {net.weights_file} (expected a {net.name} stage's "
                        "output directory, or a weights file)")
    raise InitError(f"{what}={path}: no such file or directory")


def _search_stage_run(client, experiment_id: str, parent_id: str, stage: str):
    runs = client.search_runs([experiment_id], filter_string=f"tags.`mlflow.parentRunId` = '{parent_id}' "
                                                             f"AND tags.stage = '{stage}'",
                              order_by=["attributes.start_time DESC"], max_results=50)
    finished = [r for r in runs if r.info.status == "FINISHED"]
    return (finished or runs or [None])[0]


def _from_run(init: dict, net: Network, context) -> tuple[Path, dict[str, str]]:
    """The weights file of ``net``'s stage in the pipeline run ``init.run``, and the lineage tags."""
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    run_id = str(init.get("run") or "").strip()
    if not run_id:
        raise InitError("init=run needs init.run=<MLflow run id> (a pipeline run or one of its stage runs)")
    uri = str(init.get("tracking_uri") or context.tracking_uri)
    client = MlflowClient(tracking_uri=uri)
    try:
        run = client.get_run(run_id)
    except MlflowException as exc:
        raise InitError(f"init.run={run_id}: no such run in the MLflow store {uri} "
                        f"({str(exc).splitlines()[0][:200]}); set init.tracking_uri if it lives in another store, "
                        "or use init=checkpoints") from exc
    tags = run.data.tags
    parent_id = tags.get("mlflow.parentRunId", run_id) if "stage" in tags else run_id
    parent = run if parent_id == run_id else client.get_run(parent_id)
    stage_run = run if tags.get("stage") == net.name else _search_stage_run(
        client, run.info.experiment_id, parent_id, net.name)
    if stage_run is None:
        raise InitError(f"init.run={run_id}: pipeline run {parent_id} has no '{net.name}' stage run (left out by "
                        f"pipeline.skip or pipeline.until?); pick another run, or leave {net.name} out of "
                        "init.networks")
    if stage_run.info.status != "FINISHED":
        raise InitError(f"init.run={run_id}: its '{net.name}' stage run {stage_run.info.run_id} did not finish "
                        f"({stage_run.info.status}); pick another run")
    key = stage_run.data.tags.get("cache_key")
    if not key:
        raise InitError(f"init.run={run_id}: its '{net.name}' stage run {stage_run.info.run_id} has no cache_key "
                        "tag: not a run of this pipeline")
    cache_dirs = [Path(context.cache_dir)]
    recorded = parent.data.params.get("pipeline.cache_dir")
    if recorded and Path(recorded).is_absolute() and Path(recorded) != cache_dirs[0]:
        cache_dirs.append(Path(recorded))
    for cache_dir in cache_dirs:
        entry = cache_dir / net.name / key
        if (entry / "manifest.json").is_file() and (entry / "out" / net.weights_file).is_file():
            path = entry / "out" / net.weights_file
            break
    else:
        raise InitError(f"init.run={run_id}: the cache entry of its '{net.name}' stage ({net.name}/{key[:10]}...) "
                        f"is gone from {', '.join(str(d) for d in cache_dirs)} (removed, or written under another "
                        "pipeline.cache_dir): re-run that pipeline, or use init=checkpoints with a copy of the weights")
    link = f"#/experiments/{parent.info.experiment_id}/runs/{parent_id}"
    lineage = {
        "init.source": "run",
        "init.source_run": parent_id,
        f"init.{net.name}_run": stage_run.data.tags.get("computed_by_run") or stage_run.info.run_id,
        "mlflow.note.content": f"Starts from the weights of pipeline run [{parent_id}]({link}) "
                               f"({parent.info.run_name or 'unnamed'}; init=run).",
    }
    return path, lineage


def locate(init: dict, net: Network, context) -> tuple[Path, dict[str, str]]:
    """(the starting weights file of ``net``, lineage tags) for init=run or init=checkpoints."""
    if init["source"] == "run":
        return _from_run(init, net, context)
    path = Path(str(init[net.name])).expanduser()
    return _weights_in(path, net, f"init.{net.name}"), {"init.source": "checkpoints"}


# -- what the weights are -----------------------------------------------------------------------------------


def load_state(path: Path, net: Network) -> dict:
    """The network's state_dict from a weights file (``torch.load(weights_only=True)``): a plain state_dict, or a
    Lightning checkpoint of the stage's module (its ``<prefix>`` parameters)."""
    import torch

    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise InitError(f"init: cannot read {path} as {net.name} weights ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0][:200]})") from exc
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = {k.removeprefix(net.ckpt_prefix): v for k, v in obj["state_dict"].items() if k.startswith(net.ckpt_prefix)}
    if not isinstance(obj, dict) or not obj or not all(hasattr(v, "shape") for v in obj.values()):
        raise InitError(f"init: {path} holds no {net.name} state_dict")
    return obj


def check_fits(expected: dict, state: dict, path: Path, what: str, group_of) -> None:
    """Raise naming the first key whose presence or shape differs between the configured model's state_dict
    (``expected``) and the checkpoint's, and the config group to change (``group_of(key)``)."""
    def shape(t) -> list[int]:
        return list(t.shape)

    problem = None
    for key, tensor in expected.items():
        if key not in state:
            problem = (key, f"the configured model has '{key}' {shape(tensor)}, the checkpoint has no such key")
        elif shape(state[key]) != shape(tensor):
            problem = (key, f"first mismatch at '{key}': checkpoint {shape(state[key])}, configured model "
                            f"{shape(tensor)}")
        if problem:
            break
    if problem is None:
        extra = [k for k in state if k not in expected]
        if extra:
            problem = (extra[0], f"the checkpoint has '{extra[0]}' {shape(state[extra[0]])}, the configured model "
                                 "has no such key")
    if problem is not None:
        key, detail = problem
        raise InitError(f"{what}: {path} does not fit the configured {what.removeprefix('init.')} network: {detail}; "
                        f"set {group_of(key)} as the run that trained it did")


BUDGETS = ("tenth", "whole")   # init.budget: what a null init.<network>_train.epochs takes


def scaled_epochs(epochs: int, cfg) -> int:
    """The default fine-tuning epochs of a from-scratch budget of ``epochs``, by ``cfg``'s ``init.budget``
    (conf/init/_finetune.yaml): ``tenth`` (the default) a tenth, rounded up, a quick round on a team's own images;
    ``whole`` all of them, the starting run trained on for as long again (with the generator's images beside a
    team's, the recipe docs/adapt.md recommends)."""
    from omegaconf import OmegaConf

    name = str(OmegaConf.select(cfg, "init.budget", default=None) or "tenth")
    if name not in BUDGETS:
        raise InitError(f"init.budget={name}: expected one of {', '.join(BUDGETS)}")
    return int(epochs) if name == "whole" else max(1, math.ceil(int(epochs) / 10))


def check_budget(name: str, budget: dict) -> dict:
    """``init.<name>_train`` with every value filled in, checked."""
    if int(budget["epochs"]) < 1 or int(budget["epochs"]) != budget["epochs"]:
        raise InitError(f"init.{name}_train.epochs={budget['epochs']}: expected a whole number >= 1")
    if not float(budget["lr"]) > 0:
        raise InitError(f"init.{name}_train.lr={budget['lr']}: expected > 0")
    if not 0 <= float(budget["ema_decay"]) < 1:
        raise InitError(f"init.{name}_train.ema_decay={budget['ema_decay']}: expected in [0, 1)")
    if "patience" in budget and int(budget["patience"]) < 1:
        raise InitError(f"init.{name}_train.patience={budget['patience']}: expected >= 1")
    if "warmup_fraction" in budget and not 0 <= float(budget["warmup_fraction"]) <= 1:
        raise InitError(f"init.{name}_train.warmup_fraction={budget['warmup_fraction']}: expected in [0, 1]")
    return budget


def resolve_start(cfg, context, net: Network, budget, check) -> dict | None:
    """The ``resolve`` hook's answer for ``net`` (pipeline.keys): None when it trains from scratch; else the
    weights file as input ``init``, ``{"init": {"train": budget}}`` as config and the lineage as tags.
    ``budget(init_train, cfg)``: the fine-tuning budget with its nulls filled in; ``check(path, state, cfg)``:
    raises when the weights do not fit the configured network."""
    init = init_config(cfg)
    if init is None or not starts_from_weights(init, net.name):
        return None
    path, tags = locate(init, net, context)
    check(path, load_state(path, net), cfg)
    digest = file_sha256(path)
    train = check_budget(net.name, budget(dict(init.get(f"{net.name}_train") or {}), cfg))
    tags |= {f"init.{net.name}_checkpoint": str(Path(path).resolve()), f"init.{net.name}_sha256": digest}
    return {"config": {"init": {"train": train}}, "files": {INIT_INPUT: str(path)}, "tags": tags}
