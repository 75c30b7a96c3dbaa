"""Progress output without a terminal is whole lines: no carriage returns, one line per epoch / tenth."""

import io

import torch

from deepword.progress import ProgressCounter, on_terminal, progress_lines
from stages.training.lightning_logs import lightning_progress


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_loop_prints_a_line_every_tenth_without_a_terminal_and_a_bar_on_one():
    log = io.StringIO()
    assert list(progress_lines(range(20), 20, "frames", "frame", log)) == list(range(20))
    lines = log.getvalue().splitlines()
    assert len(lines) == 10 and lines[-1].startswith("frames: 20/20 frames (") and "\r" not in log.getvalue()
    terminal = FakeTerminal()
    assert on_terminal(terminal) and list(progress_lines(range(3), 3, "frames", "frame", terminal)) == [0, 1, 2]
    assert "\r" in terminal.getvalue()  # tqdm's live bar


def test_progress_reported_by_a_callback_is_a_line_every_tenth_without_a_terminal_and_a_bar_on_one():
    log = io.StringIO()
    counter = ProgressCounter("subsets", "subset", log)
    for done in range(1, 101, 3):   # batches of 3: the counts skip the tenths themselves
        counter(done, 100)
    counter(100, 100)
    counter(100, 100)   # the end once
    counter.close()
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and len(lines) == 10
    assert lines[0].startswith("subsets: 10/100 subsets (") and lines[-1].startswith("subsets: 100/100 subsets (")
    terminal = FakeTerminal()
    counter = ProgressCounter("subsets", "subset", terminal)
    counter(5, 10)
    counter.close()
    assert "\r" in terminal.getvalue()


def test_training_without_a_terminal_prints_one_line_per_epoch():
    import lightning as L

    class Tiny(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.layer = torch.nn.Linear(2, 1)

        def training_step(self, batch, batch_idx):
            loss = self.layer(batch[0]).pow(2).mean()
            self.log("train/loss", loss, on_epoch=True, on_step=False)
            return loss

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    log = io.StringIO()
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(8, 2)), batch_size=4)
    trainer = L.Trainer(max_epochs=3, callbacks=lightning_progress("tiny", log), logger=False,
                        enable_checkpointing=False, enable_model_summary=False, accelerator="cpu")
    trainer.fit(Tiny(), data)
    lines = log.getvalue().splitlines()
    assert [line.split(":")[0] for line in lines] == ["tiny epoch 1/3", "tiny epoch 2/3", "tiny epoch 3/3"]
    assert "train/loss=" in lines[0] and "\r" not in log.getvalue()
    assert lines[0].endswith(" left)") and lines[1].endswith(" left)")  # the time left, while epochs remain
    assert lines[2].endswith(" s)") and "left" not in lines[2]
    assert lightning_progress("tiny", FakeTerminal()) == []  # a terminal keeps Lightning's own bar
    import pickle

    pickle.loads(pickle.dumps(lightning_progress("tiny")))  # DDP spawn pickles the Trainer's callbacks


def test_time_left_reads_at_the_precision_an_estimate_deserves():
    from stages.training.lightning_logs import format_duration

    assert format_duration(42.4) == "42 s"
    assert format_duration(89) == "89 s"
    assert format_duration(7 * 60 + 10) == "7 min"
    assert format_duration(65 * 60 + 20) == "1 h 05 min"
