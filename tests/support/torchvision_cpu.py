"""Test-environment helper: make PyPI's torchvision importable next to a CPU-only torch.

PyPI only carries CUDA builds of torchvision; beside the CPU build of torch (what this project's machines
install) its compiled extension cannot load (``libc10_cuda.so`` is missing) and ``import torchvision``
fails while registering fake kernels for the missing ops. The model packages use torchvision for image
transforms, and SAM's mask generator for ``nms``. For the real-package tests only, this helper skips the
fake-kernel registrations and registers a CPU ``torchvision::nms`` written here (greedy NMS, the textbook
algorithm); every other torchvision op stays absent and would fail loudly if called. Users install the
torchvision build that matches their torch and never need this.
"""

from __future__ import annotations

import importlib
import sys
import types


def _nms_cpu(dets, scores, iou_threshold):  # type: ignore[no-untyped-def]
    import torch

    order = torch.argsort(scores, descending=True)
    x0, y0, x1, y1 = dets.unbind(1)
    area = (x1 - x0).clamp(min=0) * (y1 - y0).clamp(min=0)
    keep = []
    alive = torch.ones(len(order), dtype=torch.bool)
    for r, i in enumerate(order.tolist()):
        if not alive[r]:
            continue
        keep.append(i)
        rest = order[r + 1 :]
        w = (torch.minimum(x1[i], x1[rest]) - torch.maximum(x0[i], x0[rest])).clamp(min=0)
        h = (torch.minimum(y1[i], y1[rest]) - torch.maximum(y0[i], y0[rest])).clamp(min=0)
        inter = w * h
        iou = inter / (area[i] + area[rest] - inter).clamp(min=1e-12)
        alive[r + 1 :] &= iou <= iou_threshold
    return torch.tensor(keep, dtype=torch.int64)


_LIB = None


def ensure_torchvision() -> str:
    """Import torchvision, with the CPU shim if its compiled ops cannot load. Returns "native" or "shim";
    raises ImportError when torchvision is not installed."""
    global _LIB
    try:
        importlib.import_module("torchvision")
        return "native"
    except RuntimeError as e:
        if "does not exist" not in str(e):
            raise
    import torch

    for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
        del sys.modules[name]
    sys.modules["torchvision._meta_registrations"] = types.ModuleType("torchvision._meta_registrations")
    if _LIB is None and not hasattr(torch.ops.torchvision, "nms"):
        _LIB = torch.library.Library("torchvision", "DEF")
        _LIB.define("nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
        _LIB.impl("nms", _nms_cpu, "CPU")
    importlib.import_module("torchvision")
    ext = importlib.import_module("torchvision.extension")
    ext._has_ops = lambda: True  # type: ignore[attr-defined]  # nms is registered above
    return "shim"
