"""Shared checks of the learned geometry backends: torch device, local checkpoints, clear errors.

Every failure a user can cause (missing extra, missing weights, GPU requested but absent) becomes one
``ModelUnavailable`` with one line saying what to do, never a traceback from inside a model library.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any


class ModelUnavailable(RuntimeError):
    """A learned backend cannot be built: package, weights or device missing."""


def import_or_explain(module: str, backend: str, install: str) -> Any:
    """``importlib.import_module(module)``, or ``ModelUnavailable`` naming the install command."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ModelUnavailable(
            f"the {backend} reconstructor needs the optional package {module!r} ({e}); install it with: {install}"
        ) from None
    except RuntimeError as e:  # e.g. a CUDA torchvision beside a CPU torch
        raise ModelUnavailable(
            f"the {backend} reconstructor's package {module!r} fails to import: {str(e).splitlines()[0][:200]} "
            "(install the torchvision build that matches your torch)"
        ) from None


def check_device(device: str) -> str:
    """The torch device string if usable here, else ``ModelUnavailable`` (CUDA requested without a GPU)."""
    import torch

    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ModelUnavailable(f"device {device!r} requested but torch sees no CUDA GPU here: use device = \"cpu\"")
    if device.startswith("mps") and not torch.backends.mps.is_available():
        raise ModelUnavailable(f"device {device!r} requested but MPS is not available here: use device = \"cpu\"")
    try:
        torch.empty(1, device=device)
    except (RuntimeError, ValueError) as e:
        raise ModelUnavailable(f"torch cannot use device {device!r}: {str(e).splitlines()[0]}") from None
    return device


def load_pretrained(model_cls: Any, checkpoint: str, backend: str, **overrides: Any) -> Any:
    """``model_cls.from_pretrained`` from a local directory, or from the Hugging Face cache without
    downloading; a missing checkpoint is one ``ModelUnavailable`` naming the download command."""
    local = Path(checkpoint).expanduser()
    try:
        if local.exists():
            return model_cls.from_pretrained(str(local), **overrides)
        return model_cls.from_pretrained(checkpoint, local_files_only=True, **overrides)
    except Exception as e:  # noqa: BLE001 - the hub raises several types for a missing cache entry or a broken directory
        where = "directory" if local.exists() else "Hugging Face cache entry"
        raise ModelUnavailable(
            f"{backend} checkpoint {checkpoint!r} cannot be loaded from the local {where} ({type(e).__name__}); "
            f"nothing is downloaded at run time: fetch it once with `huggingface-cli download {checkpoint}` "
            "(or `--local-dir DIR` and give DIR as checkpoint)"
        ) from None
