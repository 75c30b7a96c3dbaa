"""Training precision of the Lightning stages, decided at run time from what the machine can do.

``trainer.precision: auto`` (the CPU default, ``trainer=cpu``) means bf16 mixed precision where the hardware
runs bfloat16 natively, fp32 elsewhere. ``trainer=gpu`` and ``trainer=ddp`` set ``32-true`` (fp32); on a GPU,
``trainer.precision=auto`` trains in bf16 where the GPU supports it and ``trainer.precision=bf16-mixed`` asks for
it outright (any value other than ``auto`` is passed to Lightning as it is). On a CPU "natively" means the ``avx512_bf16`` or ``amx_bf16``
instructions: oneDNN emulates bf16 on older AVX-512 CPUs (torch's ``_is_mkldnn_bf16_supported`` says
yes there) but that is slower than fp32, so torch's check alone would slow those machines down.
Measured on an ``avx512_bf16`` CPU (detector, batch 8, 320x256, 2 threads): bf16 autocast 1.8x the fp32
step rate, 2.45x with channels_last (``benchmarks/bench_detector_training.py`` re-measures it).

The resolved value is what the stage records (an MLflow parameter and its output metadata), so a run
trained in bf16 is never mistaken for an fp32 one.
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)

AUTO = "auto"
BF16 = "bf16-mixed"
FP32 = "32-true"
BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> set[str]:
    """The CPU feature flags the kernel reports (empty where there is no /proc/cpuinfo, e.g. macOS)."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith(("flags", "Features")):
            return set(line.split(":", 1)[1].split())
    return set()


def cpu_has_native_bf16() -> bool:
    """True when the CPU executes bfloat16 dot products in hardware and torch's oneDNN can use them."""
    import torch

    if not (torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()):
        return False
    return any(flag in cpu_flags() for flag in BF16_CPU_FLAGS)


def gpu_has_bf16() -> bool:
    import torch

    return torch.cuda.is_available() and torch.cuda.is_bf16_supported()


def trains_on_gpu(accelerator: str) -> bool:
    """Whether Lightning's ``accelerator`` setting puts training on a GPU on this machine."""
    import torch

    accelerator = str(accelerator)
    return accelerator in ("gpu", "cuda") or (accelerator == AUTO and torch.cuda.is_available())


def resolve_precision(requested: str, accelerator: str) -> str:
    """Lightning's ``precision`` for a training run: ``requested`` unless it is ``auto``, which becomes
    ``bf16-mixed`` on hardware with native bf16 (see the module doc) and ``32-true`` elsewhere."""
    requested = str(requested)
    if requested != AUTO:
        return requested
    if trains_on_gpu(accelerator):
        return BF16 if gpu_has_bf16() else FP32
    if cpu_has_native_bf16():
        return BF16
    warn_fp32_fallback()
    return FP32


_warned = False


def warn_fp32_fallback() -> None:
    """Once a process (the relation stage resolves the precision for each ensemble member): the profiles' fixed
    epoch counts were chosen with bf16, so say what fp32 costs before the stages train (docs/results.md, "How long
    `make pipeline` takes")."""
    global _warned
    if _warned:
        return
    _warned = True
    log.warning("trainer.precision=auto: this CPU has no native bf16 (%s), so training runs in fp32, about twice "
                "as slow a step (a quick-profile detector epoch took 27-36 s on a 2-core AVX-512 host against 15-17 s "
                "with bf16); with detector.epochs=auto the plan fits fewer detector epochs into the profile's minutes, "
                "a weaker detector than a bf16 host's, and detector.epochs=N sets them; the epoch lines give the time "
                "left", " / ".join(BF16_CPU_FLAGS))
