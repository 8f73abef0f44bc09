"""Device selection: use a GPU when one exists, the CPU otherwise; ``--device`` overrides."""

from __future__ import annotations

from aeroloc.errors import AerolocError


def pick_device(name: str | None = "auto"):
    import torch

    name = (name or "auto").lower()
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise AerolocError(f"unknown device '{name}' (use auto, cpu, cuda, cuda:N or mps)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise AerolocError(f"device '{name}' requested but no CUDA GPU is available (use --device cpu)")
    return dev
