import pytest

from stages.training.loader_workers import MAX_ACCELERATOR_WORKERS, loader_workers


@pytest.fixture
def cuda(monkeypatch):
    """Pretend a GPU is (or is not) there."""

    def set_cuda(available: bool):
        import torch

        monkeypatch.setattr(torch.cuda, "is_available", lambda: available)

    return set_cuda


def test_auto_is_in_process_on_a_cpu(cuda):
    cuda(False)
    assert loader_workers(None, "cpu", cores=16) == 0
    assert loader_workers(None, "auto", cores=16) == 0
    cuda(True)  # a GPU in the machine, but the run asked for the CPU
    assert loader_workers(None, "cpu", cores=16) == 0


def test_auto_uses_worker_processes_on_an_accelerator(cuda):
    cuda(True)
    assert loader_workers(None, "gpu", cores=16) == MAX_ACCELERATOR_WORKERS
    assert loader_workers(None, "auto", cores=16) == MAX_ACCELERATOR_WORKERS
    assert loader_workers(None, "gpu", cores=6) == 4  # one core for the training process, one for the rest
    assert loader_workers(None, "cuda", cores=2) == 0
    assert loader_workers(None, "gpu", cores=1) == 0


def test_an_explicit_count_is_kept_and_checked(cuda):
    cuda(False)
    assert loader_workers(3, "cpu", cores=2) == 3
    cuda(True)
    assert loader_workers(0, "gpu", cores=16) == 0
    with pytest.raises(ValueError, match="num_workers must be >= 0"):
        loader_workers(-1, "gpu")
