"""``clip`` embedder: OpenCLIP crop embeddings labelled against a vocabulary file (optional extra).

Needs ``open_clip_torch`` (``pip install 'argus-scenegraph[clip]'``) and LOCAL weights (a checkpoint
file passed as ``pretrained``); nothing is ever downloaded. Labels come from a vocabulary text file,
one name per line (default: ``mapper/vocab/indoor.txt``); each mask's crop is compared with the prompt
``"a photo of a <name>"`` of every name.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.perception.base import Detection, Mask2D
from mapper.perception.sam import BackendUnavailable, usable_device

if TYPE_CHECKING:
    from mapper.geometry.contract import View

DEFAULT_VOCAB = Path(__file__).resolve().parents[1] / "vocab" / "indoor.txt"


def load_vocabulary(path: Path) -> list[str]:
    """Names from a vocabulary file: one per line, blank lines and ``#`` comments ignored, de-duplicated."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as e:
        raise ValueError(f"cannot read vocabulary file {path}: {e.strerror or e}") from None
    names: list[str] = []
    for line in text.splitlines():
        name = line.split("#", 1)[0].strip()
        if name and name not in names:
            names.append(name)
    if not names:
        raise ValueError(f"vocabulary file {path} holds no names")
    return names


class ClipConfig(BaseModel):
    """Options of the ``clip`` embedder."""

    model_config = ConfigDict(extra="forbid")
    model_name: str = Field(default="ViT-B-32", description="OpenCLIP architecture name")
    pretrained: Path | None = Field(default=None, description="local checkpoint file (required)")
    random_init: bool = Field(default=False, description="TESTS ONLY: random weights, no checkpoint")
    vocabulary: Path = Field(default=DEFAULT_VOCAB, description="text file of label names, one per line")
    prompt: str = Field(default="a photo of a {}", description="text prompt template")
    crop_padding: float = Field(default=0.1, ge=0.0, le=1.0, description="crop margin, fraction of the box")
    temperature: float = Field(default=100.0, gt=0.0, description="softmax scale of the cosine similarities")
    top_k: int = Field(default=3, ge=1, le=20, description="label alternatives kept")
    batch_size: int = Field(default=16, ge=1, description="crops per forward pass")
    device: str = Field(default="cpu", description="torch device")


class ClipEmbedder:
    """Crop each mask's bounding box, embed it with OpenCLIP, label it by the nearest vocabulary prompt."""

    name = "clip"
    description = "OpenCLIP crop embeddings labelled against a vocabulary (optional extra, local weights)"

    def __init__(self, **opts: object) -> None:
        self.config = cfg = ClipConfig.model_validate(opts)
        try:
            import open_clip
            import torch
        except RuntimeError as e:  # e.g. a CUDA torchvision beside a CPU torch
            raise BackendUnavailable(
                f"the 'clip' embedder's package open_clip_torch fails to import: {str(e).splitlines()[0][:200]} "
                "(install the torchvision build that matches your torch)"
            ) from None
        except ImportError as e:
            raise BackendUnavailable(
                f"the 'clip' embedder needs the optional package open_clip_torch ({e}); install it with "
                "pip install 'argus-scenegraph[clip]' and pass local weights with "
                "--set perception.embedder_options.pretrained=PATH, or use --embedder classical"
            ) from None
        if cfg.pretrained is None and not cfg.random_init:
            raise BackendUnavailable(
                "the 'clip' embedder needs local weights: --set perception.embedder_options.pretrained=PATH "
                "(nothing is downloaded)"
            )
        if cfg.pretrained is not None and not cfg.pretrained.is_file():
            raise BackendUnavailable(f"OpenCLIP checkpoint {cfg.pretrained} does not exist")
        self.vocabulary = load_vocabulary(cfg.vocabulary)
        usable_device(cfg.device)
        model, _, preprocess = open_clip.create_model_and_transforms(
            cfg.model_name, pretrained=None if cfg.random_init else str(cfg.pretrained), device=cfg.device
        )
        self._model: Any = model.eval()
        self._preprocess = preprocess
        self._torch = torch
        tokenizer = open_clip.get_tokenizer(cfg.model_name)
        with torch.inference_mode():
            tokens = tokenizer([cfg.prompt.format(n) for n in self.vocabulary]).to(cfg.device)
            text = self._model.encode_text(tokens).float()
        self._text = (text / text.norm(dim=-1, keepdim=True).clamp_min(1e-8)).cpu().numpy()

    def _crop(self, image: np.ndarray, mask: np.ndarray) -> Any:
        from PIL import Image

        H, W = image.shape[:2]
        if mask.shape != (H, W):
            from mapper.fusion import resize_mask

            mask = resize_mask(mask, H, W)
        ys, xs = np.nonzero(mask)
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        py, px = int((y1 - y0) * self.config.crop_padding), int((x1 - x0) * self.config.crop_padding)
        crop = image[max(0, y0 - py) : min(H, y1 + py), max(0, x0 - px) : min(W, x1 + px)]
        return self._preprocess(Image.fromarray(np.ascontiguousarray(crop)))

    def embed(self, view: View, masks: Sequence[Mask2D]) -> list[Detection]:
        torch = self._torch
        keep = [m for m in masks if m.mask.any()]
        if not keep:
            return []
        feats = []
        with torch.inference_mode():
            for i in range(0, len(keep), self.config.batch_size):
                batch = torch.stack([self._crop(view.image, m.mask) for m in keep[i : i + self.config.batch_size]])
                f = self._model.encode_image(batch.to(self.config.device)).float()
                feats.append((f / f.norm(dim=-1, keepdim=True).clamp_min(1e-8)).cpu().numpy())
        img = np.concatenate(feats).astype(np.float32)
        logits = self.config.temperature * img @ self._text.T
        logits -= logits.max(axis=1, keepdims=True)
        probs = np.exp(logits)
        probs /= probs.sum(axis=1, keepdims=True)
        out = []
        for m, f, p in zip(keep, img, probs, strict=True):
            order = np.argsort(-p)[: self.config.top_k + 1]
            alts = tuple((self.vocabulary[j], float(p[j])) for j in order[1:])
            out.append(
                Detection(
                    mask=m.mask,
                    label=self.vocabulary[order[0]],
                    confidence=float(p[order[0]]),
                    descriptor=f,
                    alternatives=alts,
                    instance_key=m.instance_key,
                )
            )
        return out
