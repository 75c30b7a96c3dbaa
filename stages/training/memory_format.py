"""Which memory layout a network trains in: channels_last (NHWC) where it is safe, NCHW elsewhere.

NHWC is oneDNN's native convolution layout, so a CPU step skips the reorders around every convolution and
BatchNorm. Measured on 2 cores, one training step against NCHW (``make bench ARGS=detector_training``):

- a host with native bf16 (avx512_bf16/amx_bf16), in bf16: detector 1.47x, facing network 1.34x;
- an AVX-512 host without bf16, in fp32: detector 1.63x, facing network 1.52x, relation backbone 1.33x;
- the same host with oneDNN held to AVX2 (``ONEDNN_MAX_CPU_ISA=AVX2``, as on most laptops): facing 1.14x,
  relation backbone 1.26x.

One pattern is not safe: in torch 2.13 oneDNN's fp32 NHWC backward of a 1x1 convolution with stride 2 and
2-15 input channels (a residual shortcut behind a narrow stem, e.g. a detector backbone with an 8- or
12-channel stem) crashes the process on AVX-512 CPUs (segfault or double free; 16 channels and more, other kernel sizes and strides,
bf16, and oneDNN held to AVX2 ran). A network holding such a convolution trains in NCHW on the CPU, and the stage
says why.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

# oneDNN's AVX-512 kernels block channels by 16; the strided 1x1 backward fails below one block
NHWC_MIN_CHANNELS = 16


def nhwc_unsafe_convolutions(net) -> list[str]:
    """Names of ``net``'s convolutions whose fp32 NHWC backward crashes oneDNN (see the module docstring)."""
    from torch import nn

    return [name for name, m in net.named_modules()
            if isinstance(m, nn.Conv2d) and m.kernel_size == (1, 1) and m.stride != (1, 1)
            and 1 < m.in_channels < NHWC_MIN_CHANNELS]


def use_channels_last(requested: bool, net, bf16: bool, on_gpu: bool, what: str) -> bool:
    """Whether ``net`` (``what`` names it in the log) trains in channels_last: when ``requested``, in bf16 anywhere and
    in fp32 on a CPU unless it holds a convolution whose NHWC backward crashes there. fp32 on a GPU stays NCHW (not
    measured there). ``net`` may be a function building the network: it is called only when the answer needs it, with
    torch's random state restored afterwards, so that a stage that seeded before asking builds its own network from the
    same draw as without the question."""
    import torch
    from torch import nn

    if not requested or (on_gpu and not bf16):
        return False
    if bf16:
        return True
    if not isinstance(net, nn.Module):
        with torch.random.fork_rng(devices=[]):
            net = net()
    unsafe = nhwc_unsafe_convolutions(net)
    if unsafe:
        log.info("%s trains in NCHW, not channels_last: oneDNN's fp32 NHWC backward crashes on the strided 1x1 "
                 "convolution(s) %s (fewer than %d input channels)", what, ", ".join(unsafe), NHWC_MIN_CHANNELS)
        return False
    return True
