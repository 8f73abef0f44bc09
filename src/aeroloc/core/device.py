"""Device selection: use a GPU when one exists, the CPU otherwise; ``--device`` overrides."""

from __future__ import annotations

from aeroloc.core.errors import AerolocError


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


_CONTROLLER = None


def single_threaded_blas():
    """A context in which numpy's BLAS (OpenBLAS) runs on one thread.

    Localization alternates torch (its own thread pool) with numpy matrix products (the mutual-NN screen). An
    idle multi-threaded OpenBLAS keeps its threads spinning, and they take the cores away from torch: on 2 CPU
    cores the NAIP query descriptor took 94 ms (median) between screens against 30 ms with one BLAS thread, and the
    whole query 272 against 197 ms. The screen's products lose less than that to a single thread.
    """
    global _CONTROLLER
    import sys

    from threadpoolctl import ThreadpoolController

    # the loaded libraries are scanned (~4 ms) again whenever modules were imported since: a BLAS loaded later
    # (scipy's own OpenBLAS, first imported by a later stage) would otherwise keep its threads
    if _CONTROLLER is None or _CONTROLLER[0] != len(sys.modules):
        _CONTROLLER = (len(sys.modules), ThreadpoolController())
    return _CONTROLLER[1].limit(limits=1, user_api="blas")
