"""Published backbone weights by name: ``backbone.weights=imagenet``.

``PUBLISHED[(backbone, source)]`` names the publisher's file: its URL and the leading hex digits
of its SHA-256, pinned here (the publishers put them in the file names; torchvision's ResNets,
Facebook's DeiT ViTs). ``resolve(backbone, weights)`` turns a source name into a local file:

- the file lives in torch's hub cache, ``torch.hub.get_dir()/checkpoints/<file name>``
  (``$TORCH_HOME/hub``, by default ``~/.cache/torch/hub``), downloaded once through
  ``torch.hub.download_url_to_file`` (with a progress bar) when it is not there yet;
- its SHA-256 is checked against the pinned prefix after the download and when a cached file is
  first used in a process (a file that fails is removed from the cache, never loaded);
- ``MVTN_WEIGHTS_MIRROR`` (a base URL, ``https://...`` or ``file:///...``): the file is fetched
  from ``<mirror>/<file name>`` instead of the publisher (compute nodes without internet, a lab's
  own copy); the pinned hash still applies.

Any other ``weights`` value is a local file path and is returned as it is (``backbones.load_weights``
reads it and maps DataParallel / DINO key prefixes). What a source means never changes: a new
release of weights gets a new source name. ``check_file(backbone, path)`` checks such a file
before a run starts (``mvtn-train``'s early checks): it loads into the backbone as training will
load it, else one ``WeightsFileError`` line says what is wrong with it.

Errors are one line (``PretrainedError``, a ValueError): an unknown pairing names the available
ones; a failed download names the URL, the reason and how to pass a downloaded file.
"""
from __future__ import annotations

import functools
import hashlib
import os
import pickle
import re
import sys
import warnings
import urllib.error
from dataclasses import dataclass
from pathlib import Path

import torch

MIRROR_ENV = "MVTN_WEIGHTS_MIRROR"


class PretrainedError(ValueError):
    """Published weights that cannot be had (unknown pairing, no network, a file of another hash)."""


class WeightsFileError(ValueError):
    """A local ``backbone.weights`` file that does not load into the backbone (``check_file``)."""


HEAD_ROWS = 1000  # the classifier's rows in the backbone a file is checked against (any count loads)


@dataclass(frozen=True)
class Published:
    """One publisher's file: ``url`` and ``sha256`` (the pinned leading hex digits of its SHA-256)."""

    url: str
    sha256: str
    what: str

    @property
    def file_name(self) -> str:
        return self.url.rsplit("/", 1)[-1]


_TV = "https://download.pytorch.org/models"
_DEIT = "https://dl.fbaipublicfiles.com/deit"
# (backbone, source) -> the file; keys map to ours as they are (torchvision's ResNet names; DeiT's
# timm-style ViT names under its ``model`` entry), the 1000-class head is left fresh
PUBLISHED: dict[tuple[str, str], Published] = {
    ("resnet18", "imagenet"): Published(f"{_TV}/resnet18-f37072fd.pth", "f37072fd", "torchvision IMAGENET1K_V1"),
    ("resnet34", "imagenet"): Published(f"{_TV}/resnet34-b627a593.pth", "b627a593", "torchvision IMAGENET1K_V1"),
    ("resnet50", "imagenet"): Published(f"{_TV}/resnet50-0676ba61.pth", "0676ba61", "torchvision IMAGENET1K_V1"),
    ("resnet101", "imagenet"): Published(f"{_TV}/resnet101-63fe2227.pth", "63fe2227", "torchvision IMAGENET1K_V1"),
    ("vit_tiny", "imagenet"): Published(f"{_DEIT}/deit_tiny_patch16_224-a1311bcf.pth", "a1311bcf", "DeiT-Ti, ImageNet-1k"),
    ("vit_small", "imagenet"): Published(f"{_DEIT}/deit_small_patch16_224-cd65a155.pth", "cd65a155", "DeiT-S, ImageNet-1k"),
    ("vit_base", "imagenet"): Published(f"{_DEIT}/deit_base_patch16_224-b5f2ef4d.pth", "b5f2ef4d", "DeiT-B, ImageNet-1k"),
}
SOURCES = tuple(sorted({source for _, source in PUBLISHED}))


def is_source(weights: str | None) -> bool:
    """True when ``weights`` names published weights (``imagenet``), not a file."""
    return weights in SOURCES


def resolve(backbone: str, weights: str | None, progress: bool | None = None) -> str | None:
    """``backbone.weights`` -> a local file path (None stays None; a path is returned as it is).
    progress: a download's progress bar on stderr (None: when stderr is a terminal)."""
    if not is_source(weights):
        return weights
    check(backbone, weights)
    pub = PUBLISHED[(backbone, weights)]
    path = Path(torch.hub.get_dir()) / "checkpoints" / pub.file_name
    if not path.is_file():
        _download(pub, path, weights, sys.stderr.isatty() if progress is None else progress)
    _check(path, pub, weights)
    return str(path)


def check(backbone: str, weights: str | None) -> None:
    """Raise ``PretrainedError`` (one line) when ``weights`` names a source that has no file for
    ``backbone`` (no network: a compose-time check)."""
    if is_source(weights) and (backbone, weights) not in PUBLISHED:
        have = ", ".join(b for b, s in sorted(PUBLISHED) if s == weights)
        raise PretrainedError(f"backbone.weights={weights}: no published {weights} weights for backbone={backbone} "
                              f"(they exist for: {have}); pass a local file as backbone.weights=PATH")


def url_of(pub: Published) -> str:
    """Where ``pub`` is fetched from: the mirror (``MVTN_WEIGHTS_MIRROR``) when set, else the publisher."""
    mirror = os.environ.get(MIRROR_ENV)
    return f"{mirror.rstrip('/')}/{pub.file_name}" if mirror else pub.url


def _download(pub: Published, path: Path, source: str, progress: bool) -> None:
    url = url_of(pub)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # (a temporary file beside the target, moved into place only once its hash matched)
        torch.hub.download_url_to_file(url, str(path), hash_prefix=pub.sha256, progress=progress)
    except RuntimeError as exc:  # the hash check
        raise PretrainedError(f"backbone.weights={source}: {url} is not the pinned file ({_one_line(exc)}); "
                              "nothing was cached") from exc
    except (urllib.error.URLError, OSError, ValueError) as exc:
        raise PretrainedError(f"backbone.weights={source}: cannot download {url} ({_one_line(exc)}); download it "
                              f"where there is network and pass backbone.weights=/path/to/{pub.file_name}, put it at "
                              f"{path}, or set {MIRROR_ENV} to a folder or URL that holds it") from exc


@functools.lru_cache(maxsize=None)
def _verified(path: str, size: int, mtime_ns: int, prefix: str) -> bool:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest().startswith(prefix)


def _check(path: Path, pub: Published, source: str) -> None:
    st = path.stat()
    if not _verified(str(path), st.st_size, st.st_mtime_ns, pub.sha256):
        path.unlink()
        raise PretrainedError(f"backbone.weights={source}: the cached {path} does not have the pinned SHA-256 "
                              f"({pub.sha256}...); it was removed, run again to download it")


def _one_line(exc: BaseException) -> str:
    reason = getattr(exc, "reason", None) or exc
    return " ".join(str(reason).split()) or type(exc).__name__


def check_file(backbone: str, path: str) -> None:
    """Raise ``WeightsFileError``, one line ``backbone.weights=PATH: what is wrong (expected ...)``,
    unless the local file ``path`` loads into ``backbone`` as training loads it: a file that
    ``torch.load(weights_only=True)`` reads (nothing of the file's choosing runs), holding a
    state_dict of tensors whose keys and shapes fit the backbone (``backbones.load_weights`` into one
    built on the meta device: no memory for its weights). A file is checked once per process."""
    p = Path(path)
    if p.is_dir():
        found = [name for name in ("best.pt", "last.pt") if (p / name).is_file()]
        hint = f"; pass {p / found[0]}" if found else ""
        raise WeightsFileError(_refusal(backbone, path, f"a folder, not a file{hint}"))
    if not p.is_file():
        raise WeightsFileError(_refusal(backbone, path, "no such file"))
    st = p.stat()
    reason = _problem(backbone, str(p.resolve()), st.st_size, st.st_mtime_ns)
    if reason is not None:
        raise WeightsFileError(_refusal(backbone, path, reason))


def _refusal(backbone: str, path: str, reason: str) -> str:
    return (f"backbone.weights={path}: {reason} (expected a state_dict for backbone={backbone} saved with "
            f"torch.save: a torchvision/timm-style .pth or a run's best.pt / last.pt; or one of {list(SOURCES)})")


@functools.lru_cache(maxsize=None)
def _problem(backbone: str, path: str, size: int, mtime_ns: int) -> str | None:
    """What keeps the file at ``path`` (of this size and time) from loading into ``backbone``; None: it loads."""
    from ..runtime.checkpoint import describe_non_checkpoint
    from .backbones import build_backbone, load_weights

    what = describe_non_checkpoint(Path(path))
    if what is not None:
        return f"{what}, not a file torch.save writes"
    with torch.device("meta"):
        model = build_backbone(backbone, num_classes=HEAD_ROWS)
    try:
        with warnings.catch_warnings():  # (copying into meta tensors is a no-op, and torch says so per tensor)
            warnings.simplefilter("ignore")
            load_weights(model, path)
    except ValueError as exc:
        return _load_problem(exc, path, backbone)
    return None


def _load_problem(exc: ValueError, path: str, backbone: str) -> str:
    """``load_weights``' refusal in this module's words: torch's reason in one sentence, without its
    advice to load the file unsafely."""
    cause = exc.__cause__
    if cause is None:  # the file was read: not a state_dict, or one of another network
        text = str(exc)
        if text.startswith(f"cannot load '{path}' into "):  # (the classifier's rows are the dataset's classes)
            text = re.sub(rf"vs model \[{HEAD_ROWS}\b", "vs model [classes", text.split(": ", 1)[1])
            return f"its tensors do not fit backbone={backbone}: {text}"
        return text.replace(f"'{path}' does not hold a", "holds no", 1)
    text = str(cause)
    found = re.search(r"GLOBAL ([\w.]+)", text)
    if isinstance(cause, pickle.UnpicklingError) and found:
        return (f"holds objects other than tensors and plain data (GLOBAL {found.group(1)}), refused unread; "
                "save model.state_dict() rather than the model")
    text = text.split("WeightsUnpickler error:", 1)[-1]  # (torch's reason, after its advice)
    first = next((line.strip() for line in text.splitlines() if line.strip()), type(cause).__name__)
    return f"cannot be read ({type(cause).__name__}: {first.split('. ')[0]})"
