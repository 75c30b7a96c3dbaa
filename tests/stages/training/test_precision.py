import pytest

from stages.training import precision
from stages.training.precision import BF16, FP32, resolve_precision


@pytest.fixture
def cpu(monkeypatch):
    """Pretend to be a CPU machine with the given flags (and oneDNN bf16 support as given)."""

    def set_cpu(flags: set[str], onednn_bf16: bool = True):
        import torch

        monkeypatch.setattr(precision, "cpu_flags", lambda: set(flags))
        monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: onednn_bf16)
        monkeypatch.setattr(torch.cuda, "is_available", lambda: False)

    return set_cpu


def test_auto_is_bf16_only_with_native_bf16_instructions(cpu):
    cpu({"avx2", "avx512f", "avx512_bf16"})
    assert resolve_precision("auto", "cpu") == BF16
    cpu({"avx2", "amx_bf16"})
    assert resolve_precision("auto", "auto") == BF16


def test_auto_falls_back_to_fp32_where_bf16_would_be_emulated(cpu):
    cpu({"avx2", "avx512f", "avx512bw"})  # oneDNN emulates bf16 here: slower than fp32
    assert resolve_precision("auto", "cpu") == FP32
    cpu({"avx512_bf16"}, onednn_bf16=False)
    assert resolve_precision("auto", "cpu") == FP32
    cpu(set())  # no /proc/cpuinfo
    assert resolve_precision("auto", "cpu") == FP32


def test_an_explicit_precision_is_kept(cpu):
    cpu({"avx512_bf16"})
    assert resolve_precision("32-true", "cpu") == FP32
    assert resolve_precision("bf16-mixed", "cpu") == BF16


def test_cpu_flags_reads_the_flags_line(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu avx512f avx512_bf16\n\nprocessor\t: 1\nflags\t\t: fpu\n")
    assert precision.cpu_flags(info) == {"fpu", "avx512f", "avx512_bf16"}
    assert precision.cpu_flags(tmp_path / "missing") == set()


def test_the_fp32_fallback_says_training_will_take_longer(cpu, caplog, monkeypatch):
    monkeypatch.setattr(precision, "_warned", False)
    cpu({"avx2", "avx512f"})
    with caplog.at_level("WARNING", logger="stages.training.precision"):
        assert resolve_precision("auto", "cpu") == FP32
        assert resolve_precision("auto", "cpu") == FP32  # the relation ensemble asks once a member
    assert caplog.text.count("no native bf16") == 1 and "detector.epochs" in caplog.text
    caplog.clear()
    monkeypatch.setattr(precision, "_warned", False)
    cpu({"avx512_bf16"})
    with caplog.at_level("WARNING", logger="stages.training.precision"):
        assert resolve_precision("auto", "cpu") == BF16
        assert resolve_precision("32-true", "cpu") == FP32  # asked for: nothing to say
    assert caplog.text == ""
