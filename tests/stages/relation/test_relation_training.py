"""Training: overfitting one batch, Lightning fast_dev_run, NaN loss, and the stage end to end."""

import json
import math
from dataclasses import asdict
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from deepword.relation_graph import InputConfig
from stages.relation.backbone_spec import CONV_FC
from stages.relation.decode import allowed_owners
from stages.relation.lightning import (
    GraphDataset,
    RelationDataModule,
    RelationModule,
    collate_graphs,
    score_split,
)
from stages.relation.losses import owner_ranking, relation_loss
from stages.relation.model import ModelConfig
from tests.stages.relation import relation_data as rd

torch.set_num_threads(1)
TINY = ModelConfig(backbone={"_target_": CONV_FC, "input_size": 28, "expansion": 1}, hidden=64, embed_dim=32,
                   gat_hidden=32)
LOSS = {"pos_weight": 1.0, "neg_weight": 1.0, "role_weight": 0.1}
DECODE = {"threshold": 0.5, "one_owner": True}


# the additions to the paper that conf/relation/default.yaml switches on
SHIPPED = ({"edge_geometry": True, "geometry_gate": True}, {"rank_weight": 0.5}, {"min_containment": 0.8})


def _module(lr: float = 3e-3, additions: bool = False) -> RelationModule:
    torch.manual_seed(0)
    model, loss, decode = asdict(TINY), dict(LOSS), dict(DECODE)
    if additions:
        for part, extra in zip((model, loss, decode), SHIPPED, strict=True):
            part.update(extra)
    return RelationModule(model=model, loss=loss, decode=decode, optim={"lr": lr, "weight_decay": 0.0})


def _split(n: int, seed: int = 0):
    return rd.split(rd.records(n, seed=seed), InputConfig(input_size=28, max_objects=16))


@pytest.mark.parametrize("additions", [False, True], ids=["paper", "shipped"])
def test_overfits_one_batch_to_full_wheel_accuracy(additions):
    split = _split(8)
    module = _module(additions=additions)
    batch = collate_graphs([GraphDataset(split)[i] for i in range(len(split))])
    opt = torch.optim.Adam(module.parameters(), lr=3e-3)
    start = score_split(module, split, 8)["wheel_acc"]
    for _ in range(100):
        module.train()
        loss = module._loss(module(batch), batch)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    metrics = score_split(module, split, 8)
    assert start < 90 and metrics["wheel_acc"] == 100.0 and metrics["couple_f1"] > 95


def test_owner_ranking_trains_each_wheels_order_among_its_allowed_vehicles():
    # nodes 0, 1 vehicles, 2, 3 wheels; wheel 2 belongs to vehicle 0, wheel 3 to nobody
    target = torch.zeros(1, 4, 4)
    target[0, 2, 0] = target[0, 0, 2] = 1
    allowed = torch.zeros(1, 4, 4, dtype=torch.bool)
    allowed[0, 2:, :2] = True

    def loss(s20: float, s21: float, s30: float = 0.0) -> float:
        scores = torch.zeros(1, 4, 4)
        scores[0, 2, 0], scores[0, 2, 1], scores[0, 3, 0] = s20, s21, s30
        return owner_ranking(scores, target, allowed).item()

    assert loss(0.9, 0.6) < loss(0.6, 0.9)                                  # the owner ahead of the other
    assert loss(0.9, 0.6) == pytest.approx(math.log(1 + math.exp(-3)), rel=1e-5)  # softmax of score / 0.1
    assert loss(0.9, 0.6, s30=0.99) == loss(0.9, 0.6)                       # an ownerless wheel adds nothing
    allowed[0, 2, 1] = False                                                # the decode may not choose it
    assert loss(0.6, 0.9) == pytest.approx(0.0, abs=1e-6)


def test_gate_loss_needs_the_gate_and_adds_its_weighted_term():
    split = _split(4)
    batch = collate_graphs([GraphDataset(split)[i] for i in range(len(split))])
    module = _module(additions=True)
    outputs = module(batch)
    logits = module.model.gate.logits(module.model.geometry(batch["coords"]))
    args = (outputs, batch, 1.0, 1.0, 0.1, 0.5, 0.8)
    without = relation_loss(*args)
    with_gate = relation_loss(*args, gate_logits=logits, gate_weight=2.0)
    assert without["gate"].item() == 0.0 and with_gate["gate"].item() > 0
    assert with_gate["loss"].item() == pytest.approx(without["loss"].item() + 2.0 * with_gate["gate"].item(), rel=1e-5)
    with pytest.raises(ValueError, match="geometry_gate"):
        relation_loss(*args, gate_weight=1.0)


def test_gate_loss_teaches_the_gate_ownership_from_box_geometry_alone():
    # trained on nothing but its own loss, the gate must rank each wheel's owner first among its allowed vehicles
    split = _split(8)
    module = _module(additions=True)
    batch = collate_graphs([GraphDataset(split)[i] for i in range(len(split))])
    gate = module.model.gate
    geometry = module.model.geometry(batch["coords"])
    allowed = allowed_owners(batch["classes"], batch["cand"], batch["coords"], 0.0)
    has_owner = (batch["owner"].bool() & allowed).any(-1)

    def owner_first_share() -> float:
        with torch.no_grad():
            logits = torch.where(allowed, gate.logits(geometry), torch.full_like(geometry[..., 0], -1e9))
        best = logits.argmax(-1, keepdim=True)
        right = batch["owner"].gather(-1, best).squeeze(-1).bool()
        return float(right[has_owner].float().mean())

    opt = torch.optim.Adam(gate.parameters(), lr=1e-2)
    for _ in range(150):
        loss = relation_loss(module(batch), batch, 1.0, 1.0, 0.1, 0.0, 0.0, gate.logits(geometry), 1.0)["gate"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert owner_first_share() > 0.95


def _trainer(**kw) -> L.Trainer:
    return L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                     enable_progress_bar=False, enable_model_summary=False, **kw)


def test_fast_dev_run_trains_and_validates():
    data = RelationDataModule(_split(6), _split(4, seed=1), batch_size=3, hflip=0.5)
    module = _module()
    before = [p.detach().clone() for p in module.parameters()]
    _trainer(fast_dev_run=True).fit(module, datamodule=data)
    assert any(not torch.equal(a, b) for a, b in zip(before, module.parameters(), strict=True))


def test_nan_loss_stops_training_with_a_clear_message():
    train = _split(4)
    train.coords[0, 0, 0] = np.nan  # one poisoned node input
    data = RelationDataModule(train, _split(2, seed=1), batch_size=4)
    with pytest.raises(FloatingPointError, match=r"relation: training loss is nan .* epoch 0, batch 0"):
        _trainer(max_epochs=1, num_sanity_val_steps=0).fit(_module(), datamodule=data)


def test_batches_are_padded_to_their_largest_graph_with_the_split_values():
    split = _split(3)
    items = [GraphDataset(split)[i] for i in range(3)]
    sizes = np.diff(split.offsets)
    batch = collate_graphs(items)
    n = int(sizes.max())
    assert n < split.classes.shape[1] and batch["crops"].shape == (3, n, 3, 28, 28)
    for key in ("coords", "classes", "valid", "role"):
        assert torch.equal(batch[key], torch.from_numpy(getattr(split, key)[:, :n]).to(batch[key].dtype))
    for key in ("adj", "cand", "owner", "couple"):
        assert torch.equal(batch[key], torch.from_numpy(getattr(split, key)[:, :n, :n]))
    for i, k in enumerate(sizes):
        a = int(split.offsets[i])
        assert torch.equal(batch["crops"][i, :k], torch.from_numpy(split.crops[a : a + k]))
        assert not batch["crops"][i, k:].any()


def test_hflip_mirrors_crops_and_x_coordinates_only():
    split = _split(1)
    plain, flipped = GraphDataset(split)[0], GraphDataset(split, hflip=1.0)[0]
    k = int(split.valid[0].sum())
    assert torch.equal(flipped["crops"], plain["crops"].flip(-1))
    assert torch.allclose(flipped["coords"][:k, 0], 1 - plain["coords"][:k, 2])
    assert torch.equal(flipped["coords"][:k, 1::2], plain["coords"][:k, 1::2])
    assert torch.equal(flipped["coords"][k:], plain["coords"][k:]) and torch.equal(flipped["adj"], plain["adj"])


def _write_dataset(root, n_train=16, n_val=6):
    """A data-stage-like directory (labels, PNGs, dataset.json, splits.json) and a priors directory."""
    import cv2

    from deepword.priors import Mixture1D, PairPrior, Priors
    from deepword.word_format import write_dataset_index, write_records

    recs = rd.records(n_train + n_val, seed=2)
    for rec in recs:
        path = root / "data" / rec.image
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), cv2.cvtColor(rd.render(rec), cv2.COLOR_RGB2BGR))
    write_records(root / "data" / "labels.jsonl", recs)
    images = [r.image for r in recs]
    splits = {"train": images[:n_train], "val": images[n_train:], "test": images[n_train:], "easy": [],
              "hard": [], "mixed": []}
    write_dataset_index(root / "data", root / "data", splits)

    def prior(mu):
        mix = Mixture1D(weights=[1.0], means=[float(np.log(mu))], variances=[0.36])
        return PairPrior(mode="prior", pair=mix, normaliser=mix.max_density())

    (root / "priors").mkdir()
    Priors(prior(3.0), prior(4.0)).save(root / "priors")
    return recs


def _stage_cfg(**train):
    """A small relation stage config on the real conf/relation/default.yaml (root seed 0)."""
    rel = OmegaConf.load("conf/relation/default.yaml")
    del rel["defaults"]
    rel.backbone = OmegaConf.load("conf/relation/backbone/conv_fc.yaml")
    rel.max_objects = 16
    rel.model.hidden, rel.model.embed_dim = 32, 16
    rel.train.epochs, rel.train.batch_size = 2, 8
    rel.ensemble = train.pop("ensemble", 1)  # one network unless a test asks for an ensemble
    rel.distill.update(train.pop("distill", {}))
    rel.train.update(train)
    trainer = OmegaConf.create({"accelerator": "cpu", "devices": 1, "strategy": "auto", "num_nodes": 1,
                                "precision": "auto", "threads": 1})  # bf16 backbone where the CPU has it
    evaluation = OmegaConf.load("conf/eval/default.yaml")  # relation.val_min_box_px follows eval.min_box_px
    return OmegaConf.create({"relation": rel, "trainer": trainer, "seed": 0, "eval": evaluation})


def _run_stage(root, out_name: str, **train) -> tuple[dict, Path]:
    from stages.relation.stage import run

    out = root / out_name
    out.mkdir()
    return run(_stage_cfg(**train), {"data": root / "data", "priors": root / "priors"}, out), out


@pytest.mark.slow
def test_stage_trains_saves_and_predicts(tmp_path):
    from stages.relation.predict import RelationPredictor

    recs = _write_dataset(tmp_path)
    metrics, out = _run_stage(tmp_path, "relation")

    assert {"relation.val.wheel_acc", "relation.val.image_acc", "relation.params", "relation.size_mb"} <= set(metrics)
    assert 0 <= metrics["relation.val.wheel_acc"] <= 100 and metrics["relation.params"] > 1000
    assert sorted(p.name for p in out.iterdir()) == ["artifacts", "relation.json", "relation.pt"]
    assert (out / "artifacts" / "relation_curves.png").stat().st_size > 1000
    meta = json.loads((out / "relation.json").read_text())
    assert meta["has_roles"] and meta["inputs"]["max_objects"] == 16 and meta["seed"] == 0
    assert [sorted(r) for r in meta["curves"]] == [["epoch", "train/loss", "val/loss", "val/wheel_acc"]] * 2

    predictor = RelationPredictor.from_dirs(out, tmp_path / "priors")
    rec = recs[-1]
    pred = predictor.predict(rec, rd.render(rec))
    assert np.array_equal(pred.boxes, rec.boxes)
    wheels = set(rec.box_ids[rec.class_ids == 1].tolist())
    assert all(w in wheels and v not in wheels for v, w, _ in pred.relations)
    assert len({w for _, w, _ in pred.relations}) == len(pred.relations)  # one owner per wheel
    # the predictor decides exactly what the training-time decoder decided (same weights, same graph)
    many = predictor.predict_many(recs[16:], rd.render, batch_size=4)
    assert [r.relations for r in many][-1] == pred.relations


@pytest.mark.slow
def test_loader_processes_train_reproducibly(tmp_path, monkeypatch):
    """relation.train.num_workers: the training graphs (flips, crop augmentation, box warps) come from a loader
    process, as on a GPU; its draws follow the training seed, so the same config trains the same weights. (Left
    null, none on a CPU: tests/stages/test_loader_workers.py.)"""
    import stages.relation.lightning as relation_lightning

    workers = []

    class Recording(relation_lightning.RelationDataModule):
        def train_dataloader(self):
            loader = super().train_dataloader()
            workers.append(loader.num_workers)
            return loader

    monkeypatch.setattr(relation_lightning, "RelationDataModule", Recording)
    _write_dataset(tmp_path)
    _, first = _run_stage(tmp_path, "workers_a", epochs=1, num_workers=1)
    _, second = _run_stage(tmp_path, "workers_b", epochs=1, num_workers=1)
    weights = [torch.load(d / "relation.pt", weights_only=True) for d in (first, second)]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert workers == [1, 1]


@pytest.mark.slow
def test_training_seed_changes_the_weights(tmp_path):
    """relation.train.seed (default: the root seed) is the seed the stage trains with: at one root seed,
    another training seed trains other weights, and relation.json records it."""
    _write_dataset(tmp_path)
    _, first = _run_stage(tmp_path, "seed_0", epochs=1)
    _, second = _run_stage(tmp_path, "seed_1", epochs=1, seed=1)
    weights = [torch.load(d / "relation.pt", weights_only=True) for d in (first, second)]
    assert weights[0].keys() == weights[1].keys()
    assert any(not torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert [json.loads((d / "relation.json").read_text())["seed"] for d in (first, second)] == [0, 1]


@pytest.mark.slow
def test_an_ensemble_trains_its_members_from_consecutive_seeds_and_resumes(tmp_path, monkeypatch):
    """relation.ensemble=2: member k is the network a lone training from seed + k gives (bit for bit);
    relation.json records the seeds, the metrics hold each member's val scores beside the ensemble's, and
    load_network returns the ensemble. A run stopped after its first member resumes without retraining it."""
    import lightning as L

    from stages.relation import stage
    from stages.relation.model import RelationEnsemble

    recs = _write_dataset(tmp_path)
    _, lone = _run_stage(tmp_path, "lone_seed_1", epochs=1, seed=1)
    calls = {"fit": 0}
    fit = L.Trainer.fit

    def counted_fit(self, *args, **kwargs):
        calls["fit"] += 1
        if calls["fit"] == 2 and calls.get("fail", True):
            raise KeyboardInterrupt("stopped during the second member")
        return fit(self, *args, **kwargs)

    monkeypatch.setattr(L.Trainer, "fit", counted_fit)
    out = tmp_path / "ensemble"
    out.mkdir()
    cfg = _stage_cfg(epochs=1, ensemble=2, distill={"enabled": False})  # the members ship (the student's: test_relation_distill)
    inputs = {"data": tmp_path / "data", "priors": tmp_path / "priors"}
    with pytest.raises(KeyboardInterrupt):
        stage.run(cfg, inputs, out)
    assert (out / "members" / "0" / "member.pt").is_file()
    calls.update(fit=0, fail=False)
    metrics = stage.run(cfg, inputs, out)
    assert calls["fit"] == 1  # only the second member trained again

    meta = json.loads((out / "relation.json").read_text())
    assert meta["ensemble"] == 2 and meta["seeds"] == [0, 1] and meta["seed"] == 0
    assert metrics["relation.ensemble"] == 2
    assert {"relation.member0.val.wheel_acc", "relation.member1.val.wheel_acc", "relation.val.wheel_acc"} <= set(metrics)
    assert sorted(p.name for p in out.iterdir()) == ["artifacts", "relation.json", "relation.pt"]
    net, _ = stage.load_network(out)
    assert isinstance(net, RelationEnsemble) and len(net.members) == 2
    alone = torch.load(lone / "relation.pt", weights_only=True)
    member1 = net.members[1].state_dict()
    assert all(torch.equal(alone[k], member1[k]) for k in alone)  # member 1 = the lone network of seed 1
    member0 = net.members[0].state_dict()
    assert any(not torch.equal(member0[k], member1[k]) for k in member0)
    from stages.relation.predict import RelationPredictor  # the torch predictor runs the ensemble too

    rec = recs[-1]
    pred = RelationPredictor.from_dirs(out, tmp_path / "priors").predict(rec, rd.render(rec))
    assert np.array_equal(pred.boxes, rec.boxes) and len({w for _, w, _ in pred.relations}) == len(pred.relations)


@pytest.mark.slow
def test_weight_averaging_ships_the_averaged_weights(tmp_path):
    """relation.train.ema_decay: validation, selection and relation.pt see the exponential moving average of
    the weights. With a decay near 1 the average stays at the first step's weights, so a second epoch moves
    the shipped weights far less than it moves the trained ones."""
    _write_dataset(tmp_path)

    def weights(name, **train):
        _, out = _run_stage(tmp_path, name, patience=10, select="loss", **train)
        return torch.load(out / "relation.pt", weights_only=True)

    def moved(a, b):
        return sum(float((a[k].float() - b[k].float()).norm()) for k in a if a[k].is_floating_point())

    plain = moved(weights("plain_1", epochs=1), weights("plain_2", epochs=2))
    averaged = moved(weights("ema_1", epochs=1, ema_decay=0.99999), weights("ema_2", epochs=2, ema_decay=0.99999))
    assert plain > 0 and averaged < 0.05 * plain


def test_unknown_selection_mode_is_refused():
    with pytest.raises(ValueError, match="relation.train.select"):
        RelationModule(model=asdict(TINY), loss=LOSS, decode=DECODE, optim={"lr": 1e-3, "weight_decay": 0.0},
                       select="pair_f1")


@pytest.mark.slow
@pytest.mark.parametrize("select", ["wheel_acc", "loss"])
def test_checkpoint_is_the_selected_epoch(tmp_path, select):
    """relation.train.select decides which epoch's weights ship: the first epoch with the best val wheel_acc,
    or the epoch with the lowest val loss."""
    _write_dataset(tmp_path)
    _, out = _run_stage(tmp_path, select, epochs=4, patience=10, select=select)
    meta = json.loads((out / "relation.json").read_text())
    curves = meta["curves"]
    if select == "loss":
        expected = min(range(len(curves)), key=lambda e: curves[e]["val/loss"])
    else:
        expected = max(range(len(curves)), key=lambda e: (curves[e]["val/wheel_acc"], -e))
    assert meta["best_epoch"] == expected
