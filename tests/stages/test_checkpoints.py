"""best_and_latest: last.ckpt follows every epoch, also those that do not improve the monitored metric."""

import lightning as L
import torch
from torch.utils.data import DataLoader, TensorDataset

from stages.checkpoints import best_and_latest

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
