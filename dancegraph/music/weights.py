"""BeatNet's pretrained weights, taken from its PyPI wheel at install time (never at run time).

``python -m dancegraph.music.weights fetch`` downloads ``beatnet==1.1.3`` with pip (the wheel
only, no dependencies; the package is never installed or imported), checks the wheel's sha256
against the pinned value, and extracts ``model_{1,2,3}_weights.pt`` and the licence into
``dancegraph/music/weights/`` (git-ignored), checking each file's sha256 too.
``python -m dancegraph.music.weights verify`` checks what is there; ``... path`` prints the folder.

``DANCEGRAPH_BEATNET_WEIGHTS`` overrides the folder (read-only installs, shared model volumes).

Licence: BeatNet (M. Heydari, F. Cwitkowitz, Z. Duan, ISMIR 2021), CC BY 4.0 — attribution is
required wherever results made with these weights are shown.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path
from types import MappingProxyType

from dancegraph.errors import ModelFileError
from dancegraph.store import file_sha256

BEATNET_VERSION = "1.1.3"
WHEEL_NAME = f"BeatNet-{BEATNET_VERSION}-py3-none-any.whl"
WHEEL_SHA256 = "1ecfa17bdcbe899975a88bdb6efebd6970d846a4f3b6cfd5c6f320647c641c7e"
FILE_SHA256 = MappingProxyType(
    {
        "model_1_weights.pt": "619091bc317ca3e83b45591d46f6de3d5a41588bcb39fe9fe7be30cffa6aca84",
        "model_2_weights.pt": "5878a18c079fa0b0139879b14ed2b5b7595faef8c3d16210aed141fd00fa2d58",
        "model_3_weights.pt": "0c52a074ea38e8cb4a760ecfa3747c9cf91a1e3cd19f238eed80b0de763989ca",
    }
)
LICENSE_NAME = "BEATNET_LICENSE.txt"
ATTRIBUTION = "BeatNet (M. Heydari et al., ISMIR 2021), CC BY 4.0"


def weights_dir() -> Path:
    """The folder holding ``model_N_weights.pt`` (env ``DANCEGRAPH_BEATNET_WEIGHTS`` or the package's)."""
    env = os.environ.get("DANCEGRAPH_BEATNET_WEIGHTS")
    return Path(env) if env else Path(__file__).resolve().parent / "weights"


def weight_path(model: int) -> Path:
    """Path of model ``model`` (1: trained without GTZAN, 2: without Ballroom, 3: without Rock corpus)."""
    if model not in (1, 2, 3):
        raise ValueError(f"BeatNet model must be 1, 2 or 3, got {model}")
    return weights_dir() / f"model_{model}_weights.pt"


def verify(dest: Path | None = None) -> dict[str, str]:
    """Check the weight files in ``dest``; returns {file: 'ok' | 'missing' | 'bad hash'}."""
    dest = dest or weights_dir()
    out = {}
    for name, digest in FILE_SHA256.items():
        p = dest / name
        out[name] = (
            "missing" if not p.is_file() else ("ok" if file_sha256(p) == digest else "bad hash")
        )
    return out


def extract(wheel: Path, dest: Path | None = None) -> list[Path]:
    """Check ``wheel`` against the pinned sha256 and extract the weights and licence into ``dest``."""
    dest = dest or weights_dir()
    digest = file_sha256(wheel)
    if digest != WHEEL_SHA256:
        raise ModelFileError(
            f"{wheel.name}: sha256 {digest} is not the pinned {WHEEL_SHA256}",
            code="model_hash_mismatch",
            field=wheel.name,
        )
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    with zipfile.ZipFile(wheel) as zf:
        for name, want in FILE_SHA256.items():
            data = zf.read(f"BeatNet/models/{name}")
            if hashlib.sha256(data).hexdigest() != want:
                raise ModelFileError(
                    f"{name} in {wheel.name} does not match its pinned sha256",
                    code="model_hash_mismatch",
                    field=name,
                )
            tmp = dest / f".{name}.tmp"
            tmp.write_bytes(data)
            tmp.replace(dest / name)
            written.append(dest / name)
        licence = zf.read(f"BeatNet-{BEATNET_VERSION}.dist-info/LICENSE")
        (dest / LICENSE_NAME).write_bytes(
            f"{ATTRIBUTION}\nWeights extracted from {WHEEL_NAME} (sha256 {WHEEL_SHA256}).\n\n".encode()
            + licence
        )
        written.append(dest / LICENSE_NAME)
    return written


def fetch(dest: Path | None = None, wheel: Path | None = None) -> list[Path]:
    """Download the pinned BeatNet wheel with pip (unless ``wheel`` is given) and extract it.

    Does nothing if all weights are already there with the right hashes.
    """
    dest = dest or weights_dir()
    if wheel is None and all(v == "ok" for v in verify(dest).values()):
        return [dest / n for n in FILE_SHA256]
    if wheel is not None:
        return extract(Path(wheel), dest)
    with tempfile.TemporaryDirectory(prefix="beatnet-wheel-") as tmp:
        cmd = [
            sys.executable,
            "-m",
            "pip",
            "download",
            f"beatnet=={BEATNET_VERSION}",
            "--no-deps",
            "--only-binary=:all:",
            "--disable-pip-version-check",
            "--quiet",
            "-d",
            tmp,
        ]
        subprocess.run(cmd, check=True)
        found = sorted(Path(tmp).glob("*.whl"))
        if not found:
            raise ModelFileError("pip downloaded no BeatNet wheel", code="model_missing")
        return extract(found[0], dest)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m dancegraph.music.weights", description=__doc__)
    ap.add_argument("action", choices=["fetch", "verify", "path"])
    ap.add_argument("--dest", type=Path, default=None, help="folder for the weights")
    ap.add_argument("--wheel", type=Path, default=None, help="use this wheel instead of pip")
    args = ap.parse_args(argv)
    dest = args.dest or weights_dir()
    if args.action == "path":
        print(dest)
        return 0
    if args.action == "fetch":
        for p in fetch(dest, args.wheel):
            print(p)
    status = verify(dest)
    for name, state in status.items():
        print(f"{name}: {state}")
    return 0 if all(v == "ok" for v in status.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
