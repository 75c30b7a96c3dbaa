"""After a multi-process (DDP) fit: every rank must hold the same weights. DDP keeps its replicas in step by
construction (one initial broadcast, averaged gradients), so a difference means the ranks did not train
together: another checkpoint resumed, other code, a rank that left the group. Checked on every rank, so that
no rank saves or reports weights the others do not share."""

from __future__ import annotations

import hashlib


def weights_digest(module) -> str:
    """sha256 over every parameter and buffer of ``module`` (names, dtypes, shapes and bytes)."""
    import torch

    digest = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        flat = tensor.detach().cpu().contiguous().reshape(-1)
        digest.update(f"{name}:{flat.dtype}:{tuple(tensor.shape)}".encode())
        digest.update(flat.view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def check_replicas_agree(module, stage: str) -> int:
    """The number of ranks that trained ``module`` together (1 outside a process group), after checking that
    all of them hold bit-identical weights; raises naming the ranks that differ."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return 1
    digests: list[str | None] = [None] * dist.get_world_size()
    dist.all_gather_object(digests, weights_digest(module))
    if len(set(digests)) != 1:
        differ = [r for r, d in enumerate(digests) if d != digests[0]]
        raise RuntimeError(f"{stage}: after training, rank(s) {differ} hold other weights than rank 0: the ranks "
                           "did not train as one process group")
    if dist.get_rank() == 0:
        print(f"{stage}: the {len(digests)} ranks hold identical weights (sha256 {digests[0][:12]})", flush=True)
    return len(digests)
