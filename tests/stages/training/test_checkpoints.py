"""best_and_latest: last.ckpt follows every epoch, also those that do not improve the monitored metric;
weight_averaging: the checkpoints hold the exponential moving average of the weights."""

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset

from stages.training.checkpoints import best_and_latest, weight_averaging

torch.set_num_threads(1)


class PeakThenWorse(L.LightningModule):
    """Logs a metric that is best in epoch 0 and worse afterwards."""

    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).pow(2).mean()

    def validation_step(self, batch, batch_idx):
        self.log("val/score", 10.0 - self.current_epoch)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def test_last_checkpoint_is_the_final_epoch_even_without_improvement(tmp_path):
    loader = DataLoader(TensorDataset(torch.randn(4, 2)), batch_size=2)
    best, latest = best_and_latest(tmp_path, "val/score", "max")
    trainer = L.Trainer(max_epochs=3, callbacks=[best, latest], logger=False, enable_progress_bar=False,
                        enable_model_summary=False, accelerator="cpu", default_root_dir=tmp_path)
    trainer.fit(PeakThenWorse(), loader, loader)
    assert torch.load(tmp_path / "best.ckpt", weights_only=True)["epoch"] == 0
    assert torch.load(tmp_path / "last.ckpt", weights_only=True)["epoch"] == 2
    assert sorted(p.name for p in tmp_path.glob("*.ckpt")) == ["best.ckpt", "last.ckpt"]


class RecordsWeights(PeakThenWorse):
    """Keeps the raw weights after every optimiser step."""

    def __init__(self):
        super().__init__()
        self.history = []

    def on_train_batch_end(self, outputs, batch, batch_idx):
        self.history.append(self.layer.weight.detach().clone())


@pytest.mark.parametrize("multi_tensor", [False, True])
def test_weight_averaging_checkpoints_hold_the_moving_average_of_every_step(tmp_path, multi_tensor):
    assert weight_averaging(0.0, multi_tensor) == []
    with pytest.raises(ValueError, match="decay"):
        weight_averaging(1.0, multi_tensor)
    torch.manual_seed(0)
    loader = DataLoader(TensorDataset(torch.randn(6, 2)), batch_size=2)
    best, latest = best_and_latest(tmp_path, "val/score", "max")
    module = RecordsWeights()
    trainer = L.Trainer(max_epochs=2, callbacks=[*weight_averaging(0.75, multi_tensor), best, latest], logger=False,
                        enable_progress_bar=False, enable_model_summary=False, accelerator="cpu", default_root_dir=tmp_path)
    trainer.fit(module, loader, loader)
    expected = module.history[0]  # the first update copies, every later one is 0.75 x average + 0.25 x weights
    for weights in module.history[1:]:
        expected = 0.75 * expected + 0.25 * weights
    saved = torch.load(tmp_path / "last.ckpt", weights_only=True)["state_dict"]["layer.weight"]
    assert len(module.history) == 6 and not torch.allclose(saved, module.history[-1])
    assert torch.allclose(saved, expected)
