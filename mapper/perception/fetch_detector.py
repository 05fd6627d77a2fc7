"""Fetch the `detector` segmenter's weights once, at install time (never at run time).

The model is MediaPipe's SSD-MobileNetV2 object detector (24 Open Images classes, fp16 TFLite,
Apache-2.0; see ``weights/NOTICE.md``). It ships inside the asset bundle of the npm package
``@mediapipe/objectron``; this step takes the package's tarball (``npm pack``, or a tarball you give with
``--tarball``), cuts the model out of the bundle at its known offsets, checks its sha256 and writes it to
the model folder. Weights are not kept in the repository.

Model folder: ``$ARGUS_MODELS/detector`` if set, else ``<python prefix>/share/argus/models/detector``
(inside the virtual environment, so ``make clean`` removes it too).

Usage::

    python -m mapper.perception.fetch_detector            # what `make install` runs
    python -m mapper.perception.fetch_detector --tarball mediapipe-objectron-0.4.1675468480.tgz
"""

from __future__ import annotations

import argparse
import hashlib
import io
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

PACKAGE = "@mediapipe/objectron@0.4.1675468480"
BUNDLE = "package/objectron_solution_packed_assets.data"
MODEL_NAME = "ssd_mobilenetv2_oidv4_fp16.tflite"
MODEL_BYTES = (184, 9987912)  # offsets of the model inside the asset bundle
MODEL_SHA256 = "d0a5255bf8c4f5a0bc4240741a76c41d5e939f7655078f945f50ab53a9375da6"


class FetchError(RuntimeError):
    """The weights could not be fetched or did not check out."""


def models_dir() -> Path:
    """Where fetched model files live (``$ARGUS_MODELS`` or the Python prefix's ``share/argus/models``)."""
    env = os.environ.get("ARGUS_MODELS", "").strip()
    return Path(env).expanduser() if env else Path(sys.prefix) / "share" / "argus" / "models"


def model_path() -> Path:
    return models_dir() / "detector" / MODEL_NAME


def extract_model(tarball: bytes) -> bytes:
    """The detector model cut out of the npm tarball's asset bundle, checked against its sha256."""
    try:
        with tarfile.open(fileobj=io.BytesIO(tarball), mode="r:gz") as tar:
            member = tar.extractfile(BUNDLE)
            if member is None:
                raise FetchError(f"{BUNDLE} is not a file in the tarball")
            bundle = member.read()
    except (tarfile.TarError, KeyError, OSError) as e:
        raise FetchError(f"not the {PACKAGE} tarball: {e}") from None
    start, end = MODEL_BYTES
    model = bundle[start:end]
    digest = hashlib.sha256(model).hexdigest()
    if digest != MODEL_SHA256:
        raise FetchError(f"the model cut from {BUNDLE} has sha256 {digest}, expected {MODEL_SHA256}")
    return model


def npm_pack(workdir: Path) -> bytes:
    """``npm pack`` the package into ``workdir`` and return the tarball's bytes."""
    npm = shutil.which("npm")
    if npm is None:
        raise FetchError("npm is not installed; get the tarball elsewhere and pass --tarball")
    try:
        out = subprocess.run([npm, "pack", PACKAGE, "--silent"], cwd=workdir, capture_output=True, text=True,
                             timeout=300, check=True).stdout.strip().splitlines()
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as e:
        raise FetchError(f"npm pack {PACKAGE} failed: {getattr(e, 'stderr', '') or e}") from None
    return (workdir / out[-1]).read_bytes()


def fetch(tarball: Path | None = None, dest: Path | None = None) -> Path:
    """Write the checked model to ``dest`` (default :func:`model_path`); a no-op when it is already there."""
    dest = dest or model_path()
    if dest.exists() and hashlib.sha256(dest.read_bytes()).hexdigest() == MODEL_SHA256:
        return dest
    if tarball is not None:
        model = extract_model(tarball.read_bytes())
    else:
        with tempfile.TemporaryDirectory() as tmp:
            model = extract_model(npm_pack(Path(tmp)))
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp_path = dest.with_name(dest.name + ".tmp")
    tmp_path.write_bytes(model)
    os.replace(tmp_path, dest)
    return dest


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mapper.perception.fetch_detector", description=__doc__.split("\n\n")[0])
    p.add_argument("--tarball", type=Path, default=None, help=f"a local {PACKAGE} tarball instead of npm pack")
    p.add_argument("--dest", type=Path, default=None, help=f"where to write the model (default {model_path()})")
    a = p.parse_args(argv)
    try:
        path = fetch(a.tarball, a.dest)
    except (FetchError, OSError) as e:
        print(f"fetch_detector: {e}", file=sys.stderr)
        return 1
    print(f"detector weights: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
